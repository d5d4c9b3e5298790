"""hyper calibrate and the ODE growth model it fits on (hyper.model.surrogate)."""

import numpy as np
import pytest

from hyper.analysis import calibrate
from hyper.commands import calibrate as calibrate_job
from hyper.core.params import InputError
from hyper.model import protocols, signaling, surrogate
from hyper.runs import runspec

MWF = protocols.named("mwf")
FACTOR = surrogate.SECTION_FACTOR["idealized"]


def synthetic(kM: float, every_weeks: float, sigma: float, seed: int = 3) -> calibrate.Dataset:
    """CSA/CSA0 of the ODE growth model at kM on mwf, sampled every ``every_weeks``, with noise."""
    t = np.arange(every_weeks, 9.0 + 1e-9, every_weeks) * protocols.WEEK
    g = surrogate.grow(signaling.SignalingParams(kM=kM), MWF, np.concatenate([[0.0], t]), factor=FACTOR)
    noise = np.random.default_rng(seed).normal(0.0, sigma, t.size)
    return calibrate.Dataset("synthetic", t, g.csa_ratio[1:] + noise, MWF)


def fit_kM(data: calibrate.Dataset) -> calibrate.Fit:
    bounds = np.array([calibrate.BOUNDS["kM"]])
    evaluate = calibrate.surrogate_model([data], ["kM"], signaling.SignalingParams(), signaling_dt=0.125,
                                         factor=FACTOR, feedback="hill")
    return calibrate.fit(evaluate, [data], ["kM"], bounds, np.array([0.01]))


def test_a_known_kM_is_recovered_within_its_interval():
    f = fit_kM(synthetic(0.016, 1.0, 0.003))
    assert f.low[0] < 0.016 < f.high[0]
    assert f.high[0] - f.low[0] < 0.004  # an informative interval, not the bounds
    assert f.at_bound == []


def test_the_interval_shrinks_as_points_are_added():
    widths = [np.ptp([f.low[0], f.high[0]]) for f in (fit_kM(synthetic(0.016, every, 0.003)) for every in (1.0, 0.25))]
    assert widths[1] < 0.7 * widths[0]


def test_the_band_holds_the_fitted_curve():
    data = synthetic(0.016, 1.0, 0.003)
    f = fit_kM(data)
    evaluate = calibrate.surrogate_model([data], ["kM"], signaling.SignalingParams(), signaling_dt=0.125,
                                         factor=FACTOR, feedback="hill")
    curve, half = calibrate.band(evaluate, f, f.bounds, [data.t])
    assert np.all(half >= 0) and half[-1] > half[0]
    assert np.allclose(curve, evaluate(f.x)[0])


@pytest.mark.parametrize("name", ["mwf", "every3days", "weekly"])
def test_the_ode_growth_model_equals_the_coupled_idealized_run(name):
    """Within SURROGATE_ERROR of the 9-week growth, at every growth-step end (same steps)."""
    from mpi4py import MPI

    from hyper.runs import driver

    protocol = protocols.named(name)
    model, *_ = driver.build(MPI.COMM_WORLD, runspec.RunSpec("idealized", protocol))
    reports = list(model.run())
    t = np.array([r.t for r in reports])
    coupled = np.array([r.csa_ratio for r in reports])
    fast = surrogate.grow(signaling.SignalingParams(), protocol, t, factor=FACTOR)
    assert np.max(np.abs(fast.csa_ratio - coupled)) <= surrogate.SURROGATE_ERROR * (coupled[-1] - 1.0)
    assert np.allclose(fast.kM, [r.kM for r in reports], rtol=1e-4)


def test_the_cylinder_grows_by_N():
    g = surrogate.grow(signaling.SignalingParams(), MWF, [0.0, MWF.end], factor=1.0)
    assert g.csa_ratio[-1] == g.N[-1] > 1.08


def test_intensity_batch_is_the_same_bits_as_each_protocol():
    schedule = protocols.named("weekly")
    unit, params = surrogate.intensity_batch(schedule, [0.3, 0.8])
    batch = surrogate.grow(params, unit, [schedule.end])
    single = surrogate.grow(signaling.SignalingParams(), schedule, [schedule.end])  # intensity 0.8
    assert batch.N[0, 1] == single.N[0]


# ------------------------------------------------------------------------------ refusals


def write(tmp_path, text: str):
    path = tmp_path / "data.csv"
    path.write_text(text)
    return path


@pytest.mark.parametrize("text, message", [
    ("week,area\n0,1\n1,1.1\n", "missing column 'csa'"),
    ("csa\n1\n1.1\n", "one time column"),
    ("week,csa\n0,1\n2,1.1\n1,1.2\n", "line 4: time must increase strictly"),
    ("week,csa\n0,1\n1,nan\n", "line 3: NaN"),
    ("month,csa\n0,1\n1,1.1\n", "unknown time unit 'month'"),
    ("week,csa\n1,1\n2,1.1\n", "the first row must be time 0"),
    ("week,csa\n0,1\n1,x\n", "line 3: not a number"),
])
def test_bad_data_files_are_refused_with_one_line(tmp_path, capsys, text, message):
    path = write(tmp_path, text)
    assert calibrate_job.main(["--data", str(path), "--protocol", "mwf", "--fit", "kM", "--output", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and message in err[0]


@pytest.mark.parametrize("option, message", [
    ("kX", "unknown parameter 'kX'"),
    ("a3", "a3: no default bounds"),
    ("kM=0:inf", "expected finite bounds"),
    ("kM=0.1:0.01", "need LOW < HIGH"),
    ("kM=", "expected finite bounds"),
])
def test_unknown_or_unbounded_fit_parameters_are_refused(tmp_path, capsys, option, message):
    args = ["--data", "data/defreitas.csv", "--protocol", "mwf", "--fit", option, "--output", str(tmp_path)]
    assert calibrate_job.main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and message in err[0]


def test_every_data_file_needs_its_protocol(tmp_path, capsys):
    args = ["--data", "data/damas.csv", "--data", "data/seynnes.csv", "--protocol", "data/damas.toml", "--fit", "kM",
            "--output", str(tmp_path)]
    assert calibrate_job.main(args) == 2
    assert "one protocol per data file" in capsys.readouterr().err


def test_the_shipped_data_and_protocols_read():
    for name, protocol in (("defreitas", "mwf"), ("damas", "data/damas.toml"), ("seynnes", "data/seynnes.toml")):
        d = calibrate.dataset(f"data/{name}.csv", protocols.resolve(protocol))
        assert d.t[-1] <= d.protocol.end and np.all(d.csa_ratio > 1.0)


def test_a_parameter_the_data_do_not_see_gets_its_bounds_as_interval():
    """kF acts only while FOXO is above its threshold, which training keeps it below."""
    data = synthetic(0.016, 1.0, 0.003)
    bounds = np.array([calibrate.BOUNDS["kM"], calibrate.BOUNDS["kF"]])
    evaluate = calibrate.surrogate_model([data], ["kM", "kF"], signaling.SignalingParams(), signaling_dt=0.125,
                                         factor=FACTOR, feedback="hill")
    f = calibrate.fit(evaluate, [data], ["kM", "kF"], bounds, np.array([0.01, 0.019]))
    assert f.unseen == ["kF"] and (f.low[1], f.high[1]) == tuple(bounds[1])
    assert f.low[0] < 0.016 < f.high[0]


def test_a_known_detraining_time_constant_is_recovered_with_kM():
    """Issue 35 item 4: the gain's turnover τ (hyper calibrate --fit detraining) from a training
    block then six weeks of rest, sampled weekly with noise: kM and τ jointly within their intervals."""
    protocol = protocols.Protocol(MWF.sessions, end=MWF.end + 6 * protocols.WEEK, name="mwf_then_rest")
    t = np.arange(1.0, protocol.end / protocols.WEEK + 1e-9) * protocols.WEEK
    truth = surrogate.grow(signaling.SignalingParams(kM=0.012), protocol, np.concatenate([[0.0], t]),
                           detraining=500.0, growth_dt=168.0)
    assert truth.csa_ratio[-1] - 1 < 0.5 * (truth.csa_ratio.max() - 1)  # the rest weeks lose most of the gain
    data = calibrate.Dataset("synthetic", t, truth.csa_ratio[1:] + np.random.default_rng(3).normal(0, 0.002, t.size),
                             protocol)
    names = ["kM", "detraining"]
    evaluate = calibrate.surrogate_model([data], names, signaling.SignalingParams(), signaling_dt=0.125,
                                         factor=1.0, feedback="hill", growth_dt=168.0)
    # each member alone equals the batch row: the per-member path is the same model
    np.testing.assert_array_equal(evaluate(np.array([[0.012, 500.0], [0.02, 300.0]]))[0],
                                  evaluate(np.array([0.012, 500.0]))[0])
    bounds = np.array([calibrate.BOUNDS[n] for n in names])
    f = calibrate.fit(evaluate, [data], names, bounds, np.array([0.01, np.sqrt(bounds[1].prod())]))
    assert f.low[0] < 0.012 < f.high[0] and f.low[1] < 500.0 < f.high[1]
    assert f.high[1] - f.low[1] < 300.0 and f.at_bound == []


def test_detraining_is_a_fittable_parameter_with_checked_bounds():
    assert calibrate_job.fit_option("detraining") == ("detraining", calibrate.BOUNDS["detraining"])
    assert calibrate_job.fit_option("detraining=100:1000") == ("detraining", (100.0, 1000.0))
    with pytest.raises(InputError, match="detraining"):
        calibrate_job.fit_option("detraining=0:1000")  # τ must be a positive time


def test_the_ogasawara_detraining_weeks_are_fitted_better_with_the_turnover():
    """Issue 35 item 4 on published data (data/ogasawara*.csv, docs/growth-laws.md): jointly on
    the detraining and the continuous group, kM with τ fits better than kM alone, and τ is
    bounded by the data (its interval ends below the upper bound)."""
    from hyper.core import resources
    from hyper.runs import measured

    folder = resources.folder("data")
    sets = [measured.read(folder / f"{name}.csv") for name in ("ogasawara", "ogasawara-continuous")]
    data = [calibrate.Dataset(m.path.stem, m.t, m.csa_ratio, protocols.load(folder / f"{m.path.stem}.toml"))
            for m in sets]

    def fitted(names):
        evaluate = calibrate.surrogate_model(data, names, signaling.SignalingParams(), signaling_dt=0.125,
                                             factor=FACTOR, feedback="hill", growth_dt=168.0)
        bounds = np.array([calibrate.BOUNDS[n] for n in names])
        return calibrate.fit(evaluate, data, names, bounds, np.sqrt(bounds.prod(axis=1)))

    alone, turnover = fitted(["kM"]), fitted(["kM", "detraining"])
    assert turnover.rmse < 0.8 * alone.rmse
    assert turnover.high[1] < 0.1 * calibrate.BOUNDS["detraining"][1] and "detraining" not in turnover.at_bound
