"""hyper calibrate --method bayes (hyper.analysis.bayes): calibrated intervals on synthetic data.

The synthetic data are the ODE growth model's own CSA at a known kM plus Gaussian noise of a
known σ, on a short protocol (three weeks, Mon-Wed-Fri) so that a model batch takes
milliseconds; the statistical test uses a fixed set of seeds, so it passes or fails the same
way every time.
"""

from pathlib import Path

import h5py
import numpy as np
import pytest

from hyper.analysis import bayes, calibrate
from hyper.commands import calibrate as calibrate_job
from hyper.core.params import InputError
from hyper.model import signaling, surrogate
from hyper.model.protocols import Protocol, Session

SHORT = Protocol(tuple(Session(168.0 * w + 48.0 * d, 1.0, 0.8) for w in range(3) for d in range(3)), 3 * 168.0,
                 "short")
FACTOR = surrogate.SECTION_FACTOR["idealized"]
KM, SIGMA = 0.016, 0.002
DT = 0.25


def truth(t: np.ndarray) -> np.ndarray:
    g = surrogate.grow(signaling.SignalingParams(kM=KM), SHORT, np.concatenate([[0.0], t]), factor=FACTOR,
                       signaling_dt=DT)
    return g.csa_ratio[1:]


def problem(points: int, seed: int, noise=None) -> tuple[bayes.Problem, calibrate.Dataset, object]:
    t = np.linspace(SHORT.end / points, SHORT.end, points)
    y = truth(t) + np.random.default_rng(seed).normal(0.0, SIGMA, points)
    data = calibrate.Dataset("synthetic", t, y, SHORT)
    evaluate = calibrate.surrogate_model([data], ["kM"], signaling.SignalingParams(), signaling_dt=DT,
                                         factor=FACTOR, feedback="hill")
    priors, noise_prior = bayes.read_priors(None, {"kM": calibrate.BOUNDS["kM"]})
    return bayes.Problem(("kM",), (priors["kM"],), ("synthetic",), (points,), y, (noise,), noise_prior), data, evaluate


def test_the_95_percent_interval_covers_the_truth_in_at_least_90_percent_of_50_replicates():
    """Noise fitted (log-uniform prior), four points each: the credible interval of kM."""
    covered = 0
    for seed in range(50):
        p, _, evaluate = problem(4, seed)
        post = bayes.grid(p, evaluate, draws=500, seed=seed)
        covered += post.low[0] <= KM <= post.high[0]
    assert covered >= 45, f"{covered} of 50"


def test_the_posterior_narrows_as_points_are_added():
    widths = []
    for points in (3, 12):
        p, _, evaluate = problem(points, 7, noise=SIGMA)
        post = bayes.grid(p, evaluate, draws=500)
        widths.append(post.high[0] - post.low[0])
    assert widths[1] < 0.7 * widths[0]


def test_emcee_agrees_with_the_exact_grid():
    """kM and the noise: one batch of walkers per step; the same posterior as the grid's."""
    p, data, evaluate = problem(6, 11)
    exact = bayes.grid(p, evaluate, draws=4000)
    f = calibrate.fit(evaluate, [data], ["kM"], np.array([calibrate.BOUNDS["kM"]]), np.array([0.01]))
    post = bayes.sample(p, evaluate, np.array([f.x[0], SIGMA]), walkers=16, steps=400, seed=1)
    assert post.columns == ["kM", "sigma_synthetic"]
    assert abs(post.median[0] / exact.median[0] - 1) < 0.01
    width = exact.high[0] - exact.low[0]
    assert abs(post.low[0] - exact.low[0]) < 0.15 * width and abs(post.high[0] - exact.high[0]) < 0.15 * width
    d = post.diagnostics
    assert 0.2 < d["acceptance"] < 0.9 and all(t > 0 for t in d["tau"]) and all(e > 100 for e in d["ess"])


def test_the_predictive_band_holds_the_credible_band():
    p, data, evaluate = problem(6, 5)
    post = bayes.grid(p, evaluate, draws=1000)
    median, lo, hi, plo, phi = bayes.predictive(p, evaluate, post, [data.t])
    assert np.all(plo < lo) and np.all(lo <= median) and np.all(median <= hi) and np.all(hi < phi)


def test_a_joint_fit_has_one_noise_per_study_and_narrows_the_interval():
    a, da, alone = problem(4, 1)
    b, db, _ = problem(4, 2)
    evaluate = calibrate.surrogate_model([da, db], ["kM"], signaling.SignalingParams(), signaling_dt=DT,
                                         factor=FACTOR, feedback="hill")
    joint = bayes.Problem(("kM",), a.priors, ("a", "b"), (4, 4), np.concatenate([a.y, b.y]), (None, 0.002),
                          a.noise_prior)
    post = bayes.grid(joint, evaluate, draws=500)
    single = bayes.grid(a, alone, draws=500)
    assert post.columns == ["kM", "sigma_a"]
    assert post.high[0] - post.low[0] < single.high[0] - single.low[0]


@pytest.mark.parametrize("text, message", [
    ("[kX]\nlow = 0.001\nhigh = 0.1\n", "unknown parameter 'kX'"),
    ("[kF]\nlow = 0.001\n", "[kF] is not fitted"),
    ("[kM]\nlow = 0.1\nhigh = 0.01\n", "need low < high"),
    ("[kM]\nlow = nan\n", "expected a finite number, got nan"),
    ("[kM]\nhigh = inf\n", "expected a finite number, got inf"),
    ("[kM]\nkind = \"gamma\"\n", "kind must be one of"),
    ("[kM]\nkind = \"log-normal\"\nmedian = 0.5\nsigma = 1\n", "needs a median in"),
    ("[kM]\nkind = \"uniform\"\nlow = -1\n", "kM must be >= 0"),
    ("[noise]\nkind = \"uniform\"\nlow = 0\n", "noise level needs low > 0"),
    ("[kM]\nspread = 1\n", "unknown key 'spread'"),
])
def test_bad_priors_are_refused(tmp_path, text, message):
    path = tmp_path / "priors.toml"
    path.write_text(text)
    with pytest.raises(InputError) as err:
        bayes.read_priors(path, {"kM": calibrate.BOUNDS["kM"]})
    assert message in str(err.value)


def test_the_job_stores_the_samples_with_the_data_digest(tmp_path, capsys):
    out = tmp_path / "out"
    args = ["--data", "data/defreitas.csv", "--protocol", "mwf", "--fit", "kM", "--method", "bayes", "--no-check",
            "--output", str(out)]
    assert calibrate_job.main(args) == 0
    printed = capsys.readouterr().out
    assert "kM = " in printed and "credible" in printed and "ESS" in printed
    from hyper.runs.checkpoint import file_digest

    with h5py.File(out / "posterior.h5") as f:
        assert f["kM"].shape == f["sigma_defreitas"].shape and f["kM"].attrs["units"] == "1/h"
        assert f["data_defreitas"].attrs["file_sha256"] == file_digest(Path("data/defreitas.csv"))
        assert "ess" in f["diagnostics"].attrs and f.attrs["sampler"] == "grid"
        low, high = f["summary"].attrs["low"][0], f["summary"].attrs["high"][0]
    assert 0.010 < low < 0.0145 < high < 0.019  # beside least squares' [0.01106, 0.01791]
    assert (out / "calibration.png").stat().st_size > 0
