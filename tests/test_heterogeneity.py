"""Heterogeneous signaling: per-cell parameter fields, their seeding and statistics, and the
coupled model with per-cell parameters."""

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np
import pytest
from dolfinx import mesh as dmesh
from mpi4py import MPI
from scipy import optimize

from hyper.analysis import ensemble
from hyper.commands import ensemble as ensemble_job
from hyper.core.params import InputError
from hyper.fem import fibers
from hyper.fem import geometry as geo
from hyper.fem.coupled import GrowthSettings, build_model
from hyper.model import heterogeneity, signaling
from hyper.model.protocols import Protocol, Session
from hyper.runs import runspec

# mTOR starts just above its threshold, so the muscle grows from the first hour.
GROWING = signaling.SignalingParams(thetaM=0.46)


def short_protocol() -> Protocol:
    return Protocol((Session(0.0, 1.0, 0.8), Session(48.0, 1.0, 0.8)), end=96.0, name="short")


def coupled_run(params):
    g = geo.load("idealized", MPI.COMM_SELF)
    model = build_model(g, fibers.fiber_field(g), short_protocol(),
                         params=params(g.mesh) if callable(params) else params,
                         settings=GrowthSettings(growth_dt=24.0))
    series = np.array([[r.t, r.csa_ratio, r.volume_ratio, r.kM, *r.states] for r in model.run()])
    return series, model


def test_uniform_parameters_as_cell_arrays_reproduce_the_homogeneous_run():
    """ε = 0 gives every cell the baseline values as arrays: one ODE per cell, ϑ per cell,
    and the homogeneous model's answer (one ODE for the body) to round-off."""
    homogeneous, m1 = coupled_run(GROWING)
    flat = heterogeneity.Heterogeneity(epsilon=0.0)
    per_cell, m2 = coupled_run(lambda mesh: heterogeneity.cell_params(mesh, flat, 7, GROWING))
    assert m2.params.size == len(m2.growth.cells) and m2.y.shape == (5, len(m2.growth.cells))
    assert m1.step == m2.step == 6 and homogeneous[-1, 1] > 1.002  # it grew
    np.testing.assert_allclose(per_cell, homogeneous, rtol=1e-10, atol=0)
    np.testing.assert_allclose(m2.growth.Gbar, m1.growth.Gbar, rtol=0, atol=1e-10)


def test_uniform_noise_is_keyed_by_global_cell_and_uniform():
    n = 20000
    cells = np.arange(n)
    xi = heterogeneity.uniform_noise(cells, n, seed=3)
    assert xi.shape == (12, n) and np.all(np.abs(xi) <= 1)
    # U(-1, 1): mean 0, variance 1/3 (standard errors 0.004 and 0.002 per row)
    np.testing.assert_allclose(xi.mean(axis=1), 0.0, atol=0.02)
    np.testing.assert_allclose(xi.var(axis=1), 1 / 3, atol=0.01)
    # parameters and seeds draw independent numbers
    corr = np.corrcoef(np.vstack([xi, heterogeneity.uniform_noise(cells, n, seed=4)]))
    assert np.max(np.abs(corr - np.eye(24))) < 0.04
    # a cell's value depends on its global index only, not on which cells are asked for
    perm = np.random.default_rng(0).permutation(n)[:500]
    np.testing.assert_array_equal(heterogeneity.uniform_noise(perm, n, seed=3), xi[:, perm])


def test_perturb_scales_only_the_twelve_rates():
    xi = np.linspace(-1, 1, 12 * 5).reshape(12, 5)
    p = heterogeneity.perturb(signaling.SignalingParams(), xi, 0.1)
    base = signaling.SignalingParams()
    for k, name in enumerate(heterogeneity.PERTURBED):
        np.testing.assert_array_equal(getattr(p, name), getattr(base, name) * (1 + 0.1 * xi[k]))
    for name in ("kM", "kF", "thetaM", "thetaF", "beta", "Fmax", "tau_h"):
        assert getattr(p, name) == getattr(base, name)
    assert p.size == 5


@pytest.mark.parametrize("bad", [dict(epsilon=1.0), dict(epsilon=-0.1), dict(model="spde"), dict(length=0.0),
                                 dict(nu=-1.0), dict(epsilon=True)])
def test_bad_heterogeneity_is_an_input_error(bad):
    with pytest.raises(InputError):
        heterogeneity.Heterogeneity(**bad)


def box(n: int, side: float):
    return dmesh.create_box(MPI.COMM_SELF, [[0.0, 0.0, 0.0], [side] * 3], [n] * 3)


def binned_correlation(points, z, lags, width):
    """Per-sample ratio estimate Σ z_i z_j / Σ (z_i² + z_j²)/2 over pairs at distance lag ± width."""
    i, j = np.triu_indices(len(points), 1)
    d = np.linalg.norm(points[i] - points[j], axis=1)
    rho = []
    for lag in lags:
        sel = np.abs(d - lag) < width
        a, b = z[:, i[sel]], z[:, j[sel]]
        rho.append((a * b).sum(axis=1) / (0.5 * (a**2 + b**2)).sum(axis=1))
    return np.array(rho).T, [d[np.abs(d - lag) < width] for lag in lags]


@pytest.mark.parametrize("nu", [1.0, 2.5])
def test_matern_field_has_the_requested_variance_and_range_on_two_meshes(nu):
    """Samples at the cell midpoints of two box meshes (h = 3ℓ/8 and 3ℓ/16): unit variance,
    the Matérn correlation at lags ℓ/4, ℓ/2, ℓ, and a fitted range within sampling error."""
    length, side = 1.0, 3.0
    spec = heterogeneity.Heterogeneity(model="matern", length=length, nu=nu)
    lags = np.array([0.25, 0.5, 1.0])
    samples = [(seed, k) for seed in range(4) for k in range(10)]
    for n in (8, 16):
        mesh = box(n, side)
        grid = heterogeneity.matern_grid(mesh, spec)
        assert grid.clipped < 1e-3
        x = heterogeneity.cell_midpoints(mesh)
        z = np.array([grid.sample(seed, k, x) for seed, k in samples])
        per_sample = (z**2).mean(axis=1)
        se = per_sample.std(ddof=1) / np.sqrt(len(per_sample))
        assert abs(per_sample.mean() - 1.0) < 3 * se + 0.01, (n, per_sample.mean(), se)

        pick = np.random.default_rng(n).choice(len(x), min(len(x), 1000), replace=False)
        rho, distances = binned_correlation(x[pick], z[:, pick], lags, 0.06)
        expected = np.array([heterogeneity.matern_correlation(d, length, nu).mean() for d in distances])
        se = rho.std(axis=0, ddof=1) / np.sqrt(len(rho))
        assert np.all(np.abs(rho.mean(axis=0) - expected) < 3 * se + 0.01), (n, rho.mean(axis=0), expected, se)

        def misfit(ell):
            return [heterogeneity.matern_correlation(d, ell, nu).mean() for d in distances] - rho.mean(axis=0)

        fitted = optimize.least_squares(misfit, length).x[0]
        assert abs(fitted / length - 1) < 0.05, (n, fitted)

    # the same sample seen by both meshes: cells of the coarse mesh hold the field's
    # values at their midpoints whatever else the mesh has
    coarse = heterogeneity.cell_midpoints(box(8, side))
    np.testing.assert_array_equal(heterogeneity.matern_grid(box(16, side), spec).sample(0, 0, coarse),
                                  grid.sample(0, 0, coarse))


def test_matern_xi_is_uniform_on_the_cells():
    """ξ = erf(z/√2): a U(-1, 1) marginal like the independent model's."""
    mesh = box(12, 0.3)
    xi = heterogeneity.cell_xi(mesh, heterogeneity.Heterogeneity(model="matern", length=0.05), seed=2)
    assert xi.shape == (12, 6 * 12**3) and np.all(np.abs(xi) < 1)
    # 216 ranges³ of volume per parameter field, 12 fields: loose but real bounds
    assert abs(xi.mean()) < 0.05 and abs(xi.var() - 1 / 3) < 0.03
    np.testing.assert_allclose(np.histogram(xi, bins=4, range=(-1, 1))[0] / xi.size, 0.25, atol=0.03)


@pytest.mark.mpi
@pytest.mark.parametrize("model", heterogeneity.MODELS)
def test_cell_parameter_field_is_the_same_on_one_and_two_ranks(model):
    comm = MPI.COMM_WORLD
    assert comm.size == 2
    spec = heterogeneity.Heterogeneity(model=model, epsilon=0.1, length=0.03)

    def by_original_cell(comm):
        mesh = geo.load("idealized", comm).mesh
        params = heterogeneity.cell_params(mesh, spec, seed=5)
        original, _ = heterogeneity.cell_identity(mesh)
        values = np.array([getattr(params, name) for name in heterogeneity.PERTURBED])
        parts = comm.allgather((original, values))
        index = np.concatenate([p[0] for p in parts])
        out = np.empty((12, len(index)))
        out[:, index] = np.concatenate([p[1] for p in parts], axis=1)
        assert np.array_equal(np.sort(index), np.arange(len(index)))
        return out

    parallel = by_original_cell(comm)
    serial = by_original_cell(MPI.COMM_SELF)
    np.testing.assert_array_equal(parallel, serial)
    assert np.ptp(serial[0]) > 0.1 * 0.09  # a10 really varies (±10 %)


def test_ensemble_cli_rejects_bad_input_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "ens"
    for argv in (["--epsilon", "1.5"], ["--geometry", "nowhere"], ["--samples", "0"],
                 ["--model", "matern", "--length", "-1"]):
        assert ensemble_job.main([*argv, "--output", str(out)]) == 2
        assert "error:" in capsys.readouterr().err
    assert not out.exists()


def test_state_std_and_summary():
    comm = MPI.COMM_SELF
    y = np.array([[1.0, 3.0]] * 5)
    np.testing.assert_allclose(ensemble.state_std(comm, y), 1.0)
    np.testing.assert_array_equal(ensemble.state_std(comm, np.ones(5)), 0.0)
    t = np.array([0.0, 1.0])
    uniform = {"t": t, "csa_ratio": np.array([1, 1.10]), "volume_ratio": np.array([1, 1.10]),
               "kM": np.array([0.01, 0.009])}
    samples = {f"s{i}": {**uniform, "csa_ratio": np.array([1, c]), "volume_ratio": np.array([1, v]),
                         "roughness_N": 10.0, "roughness_detGbar": 8.0, "roughness_u": 2.0}
               for i, (c, v) in enumerate([(1.08, 1.09), (1.06, 1.09)])}
    s = ensemble.summary(uniform, samples)
    assert s["csa_ratio"]["mean"] == pytest.approx(1.07)
    assert s["csa_ratio"]["growth_deficit_percent"] == pytest.approx(30.0)
    assert s["volume_ratio"]["std"] == pytest.approx(0.0, abs=1e-15)
    assert s["roughness_ratio_detGbar_over_u"] == pytest.approx(4.0)


SHORT = """name = "short"
end = 96.0
[[session]]
start = 24.0
duration = 1.0
intensity = 0.8
"""


class StopAfter:
    """A stop() that turns true at its n-th call (the run asks at each step boundary)."""

    def __init__(self, n):
        self.n, self.calls = n, 0

    def __call__(self):
        self.calls += 1
        return self.calls >= self.n


def test_an_ensemble_sample_stopped_by_sigterm_resumes_to_the_uninterrupted_result(tmp_path):
    """run.execute's checkpoints serve the per-cell state: parameters, one ODE per cell,
    the spread columns and the N snapshots come back, and the resumed series is the
    uninterrupted one, bit for bit."""
    from hyper.fem.coupled import GrowthSettings
    from hyper.model import protocols
    from hyper.runs import driver

    comm = MPI.COMM_SELF
    (tmp_path / "short.toml").write_text(SHORT)
    protocol = protocols.load(tmp_path / "short.toml")
    spec = runspec.RunSpec("cylinder", protocol, settings=GrowthSettings(growth_dt=12.0),
                       heterogeneity=heterogeneity.Heterogeneity(epsilon=0.05), seed=3)
    whole = ensemble.Sample(spec, tmp_path / "whole" / "seed3.h5")
    ensemble.run_sample(comm, whole, snapshot_every=2)

    cut = ensemble.Sample(spec, tmp_path / "cut" / "seed3.h5")
    with pytest.raises(driver.Interrupted):
        ensemble.run_sample(comm, cut, snapshot_every=2, stop=StopAfter(3))
    assert not cut.h5.exists() and cut.outputs.checkpoint.is_file()
    assert ckpt_status(cut.outputs.status) == "interrupted"
    ensemble.run_sample(comm, cut, snapshot_every=2)
    assert not cut.outputs.checkpoint.exists() and not cut.outputs.status.exists()

    a, b = ensemble.read(whole.h5), ensemble.read(cut.h5)
    assert set(a) == set(b) and "N_std" in a and a["N_std"][-1] > 0  # cells really differ
    for name in ("t", "csa_ratio", "volume_ratio", "kM", "N", "N_std", "final_N", "final_detGbar"):
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    assert a["roughness_N"] == b["roughness_N"]
    import h5py

    with h5py.File(whole.outputs.fields.with_suffix(".h5")) as f, h5py.File(cut.outputs.fields.with_suffix(".h5")) as g:
        assert sorted(f["Function"]) == sorted(g["Function"]) and "N" in f["Function"]
        for name in f["Function"]:
            for step in f["Function"][name]:
                np.testing.assert_array_equal(f["Function"][name][step][...], g["Function"][name][step][...])


def ckpt_status(path):
    from hyper.runs import status

    return status.read_status(path)["state"]
