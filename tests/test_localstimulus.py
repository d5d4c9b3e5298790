"""Issue 35 item 2: local mechanosensing (--stimulus local). Each cell's stimulus β I Fmax is
scaled by its active fibre stress in the session's contraction over the volume-weighted mean;
a uniform stress is the paper's model, and the switch off leaves today's series as they were."""

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np
import pytest
from mpi4py import MPI

from hyper.core.params import InputError
from hyper.fem import fibers, stimulus
from hyper.fem import geometry as geo
from hyper.fem.coupled import GrowthSettings, build_model
from hyper.model import signaling
from hyper.model.heterogeneity import cell_identity
from hyper.model.protocols import Protocol, Session
from hyper.runs.runspec import RunSpec
from test_reliability import measures  # a run's (t, CSA, V, states) per step

GROWING = signaling.SignalingParams(thetaM=0.46)  # mTOR above its threshold from the first hour
SETTINGS = GrowthSettings(growth_dt=24.0, sections=0)
LOCAL = GrowthSettings(growth_dt=24.0, sections=0, stimulus="local")


def short() -> Protocol:
    return Protocol((Session(0.0, 1.0, 0.8), Session(48.0, 1.0, 0.8)), end=96.0, name="short")


def build(name, settings, comm=MPI.COMM_SELF, protocol=None, params=GROWING):
    g = geo.load(name, comm)
    return build_model(g, fibers.fiber_field(g), protocol or short(), params=params, settings=settings)


def run(name, settings, comm=MPI.COMM_SELF, protocol=None, params=GROWING):
    model = build(name, settings, comm, protocol, params)
    return model, list(model.run())


def same_series(a, b, rtol=0.0):
    for x, y in zip(a, b, strict=True):
        assert x.t == y.t
        np.testing.assert_allclose([x.csa_ratio, x.volume_ratio, x.kM], [y.csa_ratio, y.volume_ratio, y.kM],
                                   rtol=rtol, atol=0.0)
        np.testing.assert_allclose(x.states, y.states, rtol=max(rtol, 1e-15), atol=0.0)


# ------------------------------------------------------------------ the normalisation


def test_a_uniform_field_gives_exactly_one_on_any_volumes():
    rng = np.random.default_rng(3)
    volumes = rng.uniform(1e-9, 3e-9, 1000)
    for value in (2.3e4, 1.0 / 3.0, 7.0):
        factors = stimulus.normalised(np.full(1000, value), volumes, MPI.COMM_SELF)
        assert np.all(factors == 1.0)


def test_the_factors_have_a_volume_weighted_mean_of_one_and_keep_the_order():
    rng = np.random.default_rng(4)
    volumes = rng.uniform(1.0, 3.0, 500)
    values = rng.uniform(1e4, 4e4, 500)
    factors = stimulus.normalised(values, volumes, MPI.COMM_SELF)
    assert np.sum(factors * volumes) / np.sum(volumes) == pytest.approx(1.0, rel=1e-14)
    np.testing.assert_allclose(factors, values / (np.sum(values * volumes) / np.sum(volumes)), rtol=1e-14)
    order = np.argsort(values)
    assert np.all(np.diff(factors[order]) >= 0)
    # no activation: nobody is singled out
    assert np.all(stimulus.normalised(np.zeros(5), np.ones(5), MPI.COMM_SELF) == 1.0)
    with pytest.raises(InputError, match="finite and >= 0"):
        stimulus.normalised(np.array([1.0, -1.0]), np.ones(2), MPI.COMM_SELF)


# ------------------------------------------------------------------ the coupled model


def test_a_uniform_stress_is_the_global_model_bit_for_bit(monkeypatch):
    """Every cell with the same stress: factors of exactly 1, per-cell ODEs that are the
    global ODE's bits (the RK4 gives a batch member its single run's bits), the same ϑ."""
    def uniform(geometry, a0, intensities, **kwargs):
        n = geometry.mesh.topology.index_map(3).size_local
        field = stimulus.normalised(np.full(n, 2.5e4), np.linspace(1.0, 2.0, n), geometry.mesh.comm)
        return {0.8: field}, {}

    _, today = run("cylinder", SETTINGS)
    monkeypatch.setattr(stimulus, "session_factors", uniform)
    model, local = run("cylinder", LOCAL)
    assert model.y.ndim == 2 and np.all(model.stimulus_factors[0.8] == 1.0)  # a per-cell run
    for a, b in zip(local, today, strict=True):
        assert (a.t, a.csa_ratio, a.volume_ratio, a.kM) == (b.t, b.csa_ratio, b.volume_ratio, b.kM)
        # the cell mean of n equal states: the state to the rounding of the sum
        np.testing.assert_allclose(a.states, b.states, rtol=4e-16 * model.y.shape[1], atol=0.0)
    assert today[-1].csa_ratio > 1.005  # it grew


def test_the_cylinder_contracts_uniformly_and_grows_as_the_global_model():
    """Axial fibres, flat ends on springs: the contraction is homogeneous up to the end cells'
    discretisation (factors 0.996 to 1.002), and the growth is the global model's: the CSA gain
    to 9e-6 of itself, the volume gain to 5e-8 (the volume-weighted mean factor is 1)."""
    _, today = run("cylinder", SETTINGS)
    model, local = run("cylinder", LOCAL)
    record = model.stimulus_record
    assert record["stimulus_alpha"] == 0.8
    assert 0.99 < record["stimulus_factor_min"] <= 1.0 <= record["stimulus_factor_max"] < 1.01
    # 0.8 σact fact(λ/λ0) with fact < 1: the fibres shorten (to ℓ ≈ 0.5, fact ≈ 0.1) against the springs
    assert 0.05 * 0.8 * 3e5 < record["stimulus_stress_mean_pa"] < 0.2 * 0.8 * 3e5
    assert record["stimulus_stress_max_pa"] / record["stimulus_stress_min_pa"] < 1.01
    assert local[-1].csa_ratio - 1 == pytest.approx(today[-1].csa_ratio - 1, rel=3e-5)
    assert local[-1].volume_ratio - 1 == pytest.approx(today[-1].volume_ratio - 1, rel=3e-7)


def test_the_switch_off_is_todays_model():
    _, default = run("cylinder", SETTINGS)
    model, off = run("cylinder", GrowthSettings(growth_dt=24.0, sections=0, stimulus="global"))
    assert model.stimulus_factors is None and model.y.ndim == 1 and model.stimulus_record == {}
    same_series(off, default)
    assert "stimulus" not in GrowthSettings().model_attributes()
    assert GrowthSettings(stimulus="local").model_attributes()["stimulus"] == "local"


def test_where_the_stress_is_higher_the_muscle_grows_more():
    """The idealized shape's contraction is far from uniform (factors 0.58 to 1.46 at α = 0.8):
    the factors average to 1 over the volume, and a cell's growth rises with its factor. The
    paper's parameters: N grows by the training alone (four daily sessions, then three days)."""
    daily = Protocol(tuple(Session(24.0 * k, 1.0, 0.8) for k in range(4)), end=168.0, name="daily")
    model, local = run("idealized", LOCAL, protocol=daily, params=signaling.SignalingParams())
    _, today = run("idealized", SETTINGS, protocol=daily, params=signaling.SignalingParams())
    s = model.stimulus_factors[0.8]
    volumes = stimulus.CellAverages(model.geometry, 1.0).volumes
    assert np.sum(s * volumes) / np.sum(volumes) == pytest.approx(1.0, rel=1e-13)
    assert s.min() < 0.8 and s.max() > 1.2
    N = model.y[signaling.STATES.index("N")]
    det = model.growth.cell_det()
    order = np.argsort(s)
    assert np.all(np.diff(N[order]) >= 0)  # the ODEs: more stimulus, more protein (kM and h are shared)
    assert np.corrcoef(s, det)[0, 1] > 0.95  # and the growth tensor follows
    # the ODEs alone give ΔN 0.0076 at 1.3 β and 0.0059 at 0.7 β (IGF1 saturates): 1.29 times
    assert N[s > 1.2].mean() - 1 > 1.15 * (N[s < 0.8].mean() - 1) > 0
    # the muscle as a whole: near the global model, not equal (the response is not linear in β)
    assert local[-1].volume_ratio - 1 == pytest.approx(today[-1].volume_ratio - 1, rel=0.3)


# ------------------------------------------------------------------ refusals


@pytest.mark.parametrize("value", ["regional", "", None, 1])
def test_bad_switch_values_are_refused(value):
    with pytest.raises(InputError, match=r"must be one of global, local"):
        GrowthSettings(stimulus=value)


def mixed() -> Protocol:
    return Protocol((Session(0.0, 1.0, 0.8), Session(48.0, 4.0, 0.2), Session(96.0, 1.0, 0.0)), end=168.0,
                    name="mixed")


def test_sessions_of_several_intensities_each_drive_the_cells_with_their_own_factors():
    """β s_c(I) I Fmax in the session of intensity I: a member is the single run whose sessions
    have intensity I s_c(I) (to the rounding of the products); equal factors for every intensity
    give the one-field run's bits."""
    from hyper.model.signaling import integrate

    factors = {0.8: np.array([1.2, 0.7]), 0.2: np.array([0.6, 1.4])}
    times = np.array([0.0, 24.0, 50.0, 100.0, 168.0])
    y0 = np.repeat(signaling.start_state()[:, None], 2, axis=1)
    beta = signaling.SignalingParams().beta
    params = signaling.SignalingParams(beta=np.full(2, beta))
    _, ys = stimulus.SessionFactors(integrate, beta, factors)(params, mixed(), y0, 0.0, 168.0, 0.05, out_times=times)
    for c in range(2):
        scaled = Protocol(tuple(Session(s.start, s.duration, s.intensity * factors.get(s.intensity, [1, 1])[c])
                                for s in mixed().sessions), end=168.0, name="scaled")
        _, alone = integrate(signaling.SignalingParams(), scaled, y0[:, c], 0.0, 168.0, 0.05, out_times=times)
        np.testing.assert_allclose(ys[:, :, c], alone, rtol=1e-12)
    assert np.abs(ys[:, :, 0] - ys[:, :, 1]).max() > 1e-3  # the members differ
    same = {0.8: factors[0.8], 0.2: factors[0.8]}
    _, one = integrate(signaling.SignalingParams(beta=beta * factors[0.8]), mixed(), y0, 0.0, 168.0, 0.05,
                       out_times=times)
    _, both = stimulus.SessionFactors(integrate, beta, same)(params, mixed(), y0, 0.0, 168.0, 0.05, out_times=times)
    assert np.array_equal(one, both)


def test_a_run_of_several_intensities_solves_the_contraction_at_each():
    model = build("idealized", LOCAL, protocol=mixed(), params=signaling.SignalingParams())
    record = model.stimulus_record
    assert record["stimulus_alpha"] == [0.2, 0.8] and list(model.stimulus_factors) == [0.2, 0.8]
    low, high = model.stimulus_factors[0.2], model.stimulus_factors[0.8]
    volumes = stimulus.CellAverages(model.geometry, 1.0).volumes
    for s in (low, high):
        assert np.sum(s * volumes) / np.sum(volumes) == pytest.approx(1.0, rel=1e-13)
    assert np.ptp(low) < np.ptp(high)  # a weaker contraction is the more uniform
    np.testing.assert_array_equal(model.params.beta, signaling.SignalingParams().beta * low)  # what a checkpoint keeps
    reports = list(model.run())
    assert reports[-1].t == 168.0 and reports[-1].volume_ratio > 1.0


# ------------------------------------------------------------------ parallel


@pytest.mark.mpi
def test_two_ranks_give_the_one_rank_factors_and_series():
    comm = MPI.COMM_WORLD
    assert comm.size == 2

    def by_original_cell(model):
        original, _ = cell_identity(model.geometry.mesh)
        parts = model.geometry.mesh.comm.allgather((original, model.stimulus_factors[0.8]))
        out = np.empty(sum(len(p[0]) for p in parts))
        for index, values in parts:
            out[index] = values
        return out

    parallel, series2 = run("idealized", LOCAL, comm)
    serial, series1 = run("idealized", LOCAL, MPI.COMM_SELF)
    # the contraction converges to Newton's tolerance on either partition
    np.testing.assert_allclose(by_original_cell(parallel), by_original_cell(serial), rtol=1e-7)
    same_series(series2, series1, rtol=1e-8)


def test_the_study_of_a_local_run_reruns_it(tmp_path):
    from hyper.analysis import study
    from hyper.runs import provenance

    spec = RunSpec("cylinder", short(), settings=LOCAL)
    text = provenance.study_text(spec)
    assert 'stimulus = "local"' in text
    assert "stimulus" not in provenance.study_text(RunSpec("cylinder", short(), settings=SETTINGS))
    path = tmp_path / "s.toml"
    path.write_text(text)
    again, _ = study.steps(study.load(path))
    assert again == LOCAL
    assert spec.digest() != RunSpec("cylinder", short(), settings=SETTINGS).digest()


def test_grow_records_the_switch_and_writes_the_factor_field(tmp_path):
    import h5py

    from hyper.commands import grow

    protocol = tmp_path / "short.toml"
    protocol.write_text('name = "short"\nend = 96.0\n[[session]]\nstart = 0.0\nduration = 1.0\nintensity = 0.8\n')
    out = tmp_path / "run.h5"
    assert grow.main(["--geometry", "cylinder", "--protocol", str(protocol), "--stimulus", "local",
                      "--growth-dt", "24", "--output", str(out), "--quiet"]) == 0
    with h5py.File(out) as f:
        assert f.attrs["stimulus_alpha"] == 0.8 and f.attrs["stimulus_newton_iterations"] > 0
        assert 0.99 < f.attrs["stimulus_factor_min"] <= 1.0 <= f.attrs["stimulus_factor_max"] < 1.01
        assert f["settings"].attrs["stimulus"] == "local"
        assert 'stimulus = "local"' in f.attrs["study"]
    with h5py.File(tmp_path / "run_fields.h5") as f:
        factor = f["Function/stimulus_factor/0"][()].ravel()
        assert factor.size == f["Function/detGbar/0"].shape[0]  # one per cell, as det Ḡ
        assert 0.99 < factor.min() <= factor.max() < 1.01
    assert "stimulus_factor" in (tmp_path / "run_fields.xdmf").read_text()


def test_a_local_run_resumes_bit_for_bit_from_its_checkpoint(tmp_path):
    """The factors reach the ODEs as a per-cell β, which the checkpoint carries with the other
    per-cell parameters: a resumed run goes on with them."""
    from hyper.runs import checkpoint as ckpt

    comm = MPI.COMM_SELF
    reference = measures(build("cylinder", LOCAL))
    model = build("cylinder", LOCAL)
    first = measures(model, until=2)
    state = model.state()
    assert "params.beta" in state.per_cell
    ckpt.write(comm, tmp_path / "state.h5", state.original, state.per_cell, state.glob, series={},
               attrs={"run_digest": "test"})
    again = build("cylinder", LOCAL)
    again.restore(ckpt.read(comm, tmp_path / "state.h5", "test", again.local_original_cells()))
    np.testing.assert_array_equal(again.params.beta, model.params.beta)
    assert first + measures(again) == reference


def test_a_contraction_that_cannot_be_solved_fails_the_run_as_a_step_would(monkeypatch):
    from hyper.fem.mechanics import SolverError
    from hyper.model.failure import GrowthFailure

    def diverging(problem, target, **kwargs):
        raise SolverError("Newton did not converge")

    monkeypatch.setattr(stimulus, "ramp", diverging)
    with pytest.raises(GrowthFailure, match=r"the contraction of --stimulus local at α = 0.8: Newton did not"):
        build("cylinder", LOCAL)
