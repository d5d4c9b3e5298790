"""Sobol indices of the 9-week CSA gain (``hyper sobol --function csa-gain``): the design's
parameters and bounds, the batched evaluation on the fast growth model against
member-by-member `surrogate.grow` runs (bit for bit), masked failures, and small-N runs
through the CLI (farm, chunks, resume) whose indices sum sensibly and agree on the leading
parameter between two seeds."""

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from hyper.analysis import chunks, sobol
from hyper.analysis import sobolmodels as models
from hyper.commands import sobol as sobol_job
from hyper.model import signaling, surrogate
from hyper.model.protocols import Protocol, named

GAIN = sobol.gain_problem()
RHO = surrogate.section_factor("idealized")


@pytest.fixture(scope="module")
def design():
    """4 base samples of the 17-parameter design: 4 (2 x 17 + 2) = 144 parameter sets."""
    return sobol.sample(GAIN, 4, seed=11)


def one(X, i, protocol):
    """Member i of X run alone (scalar parameters: signaling's one-member path) on the surrogate."""
    names = list(models.GAIN_PARAMETERS)
    p = models.sample_params(X[i : i + 1, :-1], names[:-1]).member(0)
    g = surrogate.grow(p, protocol, [protocol.end], factor=RHO, hill_n=float(X[i, -1]))
    return float(g.csa_ratio[-1]) - 1.0


def test_gain_design_names_and_bounds(design):
    assert GAIN["names"] == [*models.PARAMETERS, "thetaM", "thetaF", "hill_n"]
    assert design.shape == (144, 17)
    base = signaling.SignalingParams()
    for k, name in enumerate(GAIN["names"]):
        value = models.HILL_N if name == "hill_n" else getattr(base, name)
        assert GAIN["bounds"][k] == [0.5 * value, 2.0 * value]
        ratio = design[:, k] / value
        assert ratio.min() >= 0.5 and ratio.max() <= 2.0
    assert GAIN["bounds"][-1] == [2.0, 8.0]


def test_gain_batch_equals_member_by_member(design):
    # every member over the first training fortnight of mwf (rest week, then 6 sessions with
    # the feedback updated at every period end), and three over the full 9 weeks
    mwf = named("mwf")
    short = Protocol(tuple(s for s in mwf.sessions if s.start < 336.0), 336.0, "mwf-2w")
    batch = models.csa_gain(design, protocol=short)
    single = np.array([one(design, i, short) for i in range(len(design))])
    assert np.array_equal(batch, single)
    assert np.ptp(single) > 0.01
    full = models.csa_gain(design)
    assert np.array_equal(full, models.csa_gain(design, backend="numpy"))
    for i in (0, 57, 143):
        assert full[i] == one(design, i, mwf)
    # the gain is bounded by N in [Nmin, Nmax] = [0.5, 1.3], up to the last step's overshoot
    assert np.all((full >= RHO * (0.5 - 1.0) - 1e-3) & (full <= RHO * 0.3 + 1e-3))


def test_gain_at_the_baseline_and_the_feedback_exponent():
    # the baseline gain of mwf on the idealized muscle, and the feedback's exponent at work:
    # a steeper Hill law (larger n) brakes harder once CSA/CSA0 > 1
    X = np.array([[2.0], [4.0], [8.0]])
    g = models.csa_gain(X, names=("hill_n",))
    base = surrogate.grow(signaling.SignalingParams(), named("mwf"), [1512.0], factor=RHO)
    assert g[1] == float(base.csa_ratio[-1]) - 1.0
    assert g[0] > g[1] > g[2] > 0.05


def test_gain_failing_member_is_masked():
    # beta = 0.8 makes RK4 with dt = 0.05 h unstable for that member only
    X = np.array([[0.04, 0.01, 4.0], [0.8, 0.01, 4.0], [0.04, 0.02, 6.0]])
    g = models.csa_gain(X, names=("beta", "kM", "hill_n"))
    assert np.isnan(g[1]) and np.isfinite(g[[0, 2]]).all()
    for i in (0, 2):
        p = models.sample_params(X[i : i + 1, :2], ("beta", "kM")).member(0)
        assert g[i] == float(surrogate.grow(p, named("mwf"), [1512.0], factor=RHO,
                                            hill_n=X[i, 2]).csa_ratio[-1]) - 1.0
    with pytest.raises(signaling.SignalingError):
        models.csa_gain(X, names=("beta", "kM", "hill_n"), backend="numpy")


def read(out):
    with h5py.File(out / "sobol.h5") as f:
        return {k: f[k][()] for k in ("S1", "S1_conf", "ST", "ST_conf", "X", "Y")}, dict(f.attrs)


def test_cli_gain_indices_sum_sensibly_and_lead_stably(tmp_path, capsys):
    runs = {}
    for seed in (1, 2):
        out = tmp_path / f"seed{seed}"
        argv = ["--function", "csa-gain", "--samples", "256", "--chunk", "2500", "--seed", str(seed),
                "--output", str(out)]
        assert sobol_job.main(argv, comm=MPI.COMM_SELF) == 0
        assert "failed members: 0" in capsys.readouterr().out
        runs[seed], attrs = read(out)
        assert attrs["function"] == "csa-gain" and attrs["protocol"] == "mwf" and attrs["D"] == 17
        assert attrs["evaluations"] == 256 * 36 and attrs["geometry"] == "idealized"
        assert (out / "spread.png").stat().st_size > 0 and (out / "indices.png").stat().st_size > 0
    r = runs[1]
    # the chunks hold csa_gain's numbers
    assert np.array_equal(r["Y"][:40], models.csa_gain(r["X"][:40]))
    for r in runs.values():
        # S1 <= ST within the bootstrap intervals; the first-order indices sum to at most 1 and
        # the total ones to at least the first-order sum (interactions), within the error
        slack = r["S1_conf"] + r["ST_conf"]
        assert np.all(r["S1"] <= r["ST"] + slack)
        assert r["S1"].sum() <= 1.0 + np.sqrt((r["S1_conf"] ** 2).sum())
        assert r["ST"].sum() >= r["S1"].sum() - np.sqrt((slack**2).sum())
        assert np.all(r["ST"] >= -r["ST_conf"])
    lead = [models.GAIN_PARAMETERS[int(np.argmax(r["ST"]))] for r in runs.values()]
    assert lead[0] == lead[1]
    # a rerun finds every chunk done
    assert sobol_job.main(argv, comm=MPI.COMM_SELF) == 0
    assert "0 to run, 4 skipped" in capsys.readouterr().out


def test_cli_gain_digest_differs_from_signaling_and_bad_geometry(tmp_path, capsys):
    out = tmp_path / "g"
    assert sobol_job.main(["--function", "csa-gain", "--samples", "2", "--output", str(out)], comm=MPI.COMM_SELF) == 0
    gain_key = [p.name for p in (out / "chunks").iterdir()]
    assert sobol_job.main(["--samples", "2", "--output", str(out)], comm=MPI.COMM_SELF) == 0
    assert "removed chunks of other settings: " + gain_key[0] in capsys.readouterr().out
    bad = tmp_path / "bad"
    assert sobol_job.main(["--function", "csa-gain", "--geometry", "sphere", "--output", str(bad)],
                      comm=MPI.COMM_SELF) == 2
    assert "--geometry" in capsys.readouterr().err and not bad.exists()


@pytest.mark.mpi
def test_mpi_gain_farm_equals_serial(tmp_path):
    from pathlib import Path

    comm = MPI.COMM_WORLD
    assert comm.size == 2
    folder = Path(comm.bcast(str(tmp_path) if comm.rank == 0 else None, root=0))
    X = sobol.sample(GAIN, 8, seed=4)  # 288 rows, 6 chunks of 50
    Y, results = chunks.run_chunks(comm, X, models.csa_gain, folder / "par", "k", chunk=50)
    if comm.rank == 0:
        assert [r.status for r in results] == ["done"] * 6
        assert np.array_equal(Y, models.csa_gain(X))
    else:
        assert Y is None
