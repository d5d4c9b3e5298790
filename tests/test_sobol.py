"""Sobol analysis (MODEL.md §7): the batched evaluator against one-at-a-time runs, SALib's indices
of the Ishigami function through the farm + chunk path (serial and mpirun -n 2), resuming a
killed run, failure accounting, and the CLI."""

import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from hyper.analysis import chunks, sobol, sobolplot
from hyper.analysis import sobolmodels as models
from hyper.commands import sobol as sobol_job
from hyper.model import signaling
from hyper.model.protocols import Protocol, Session, named

ISHIGAMI = sobol.ishigami_problem()


@pytest.fixture(scope="module")
def design():
    """8 base samples of the 14-parameter design: 8 (2 x 14 + 2) = 240 parameter sets."""
    return sobol.sample(sobol.problem(), 8, seed=3)


# --- the evaluator -----------------------------------------------------------------------


def test_design_shape_and_bounds(design):
    assert design.shape == (240, 14)
    base = signaling.SignalingParams()
    for k, name in enumerate(models.PARAMETERS):
        ratio = design[:, k] / getattr(base, name)
        assert ratio.min() >= 0.5 and ratio.max() <= 2.0


def test_batch_equals_one_at_a_time(design):
    # One-at-a-time runs are pure Python (about 1 s per member over 480 h here), so the 240
    # members are compared over the first day of daily15: a session, the delayed IGF1
    # stimulus, the AKT bump and its end, and threshold crossings of FOXO and mTOR.
    day = Protocol((Session(0.0, 1.0, 0.8),), 30.0, "day")
    batch = models.final_N(design, protocol=day)
    single = np.array([signaling.integrate(models.sample_params(design[i : i + 1]).member(0), day,
                                           signaling.rest_state(),
                                   0.0, 30.0)[1][-1, 4]
                       for i in range(len(design))])
    assert np.max(np.abs(batch - single)) <= 1e-12
    assert np.ptp(single) > 0.01  # the parameters matter over one day already
    for i in (0, 117):  # and two members run alone over the whole protocol
        p = models.sample_params(design[i : i + 1]).member(0)
        alone = signaling.integrate(p, named("daily15"), signaling.rest_state(), 0.0, 480.0)[1][-1, 4]
        assert abs(alone - models.final_N(design[i : i + 1])[0]) <= 1e-12


def test_compiled_kernel_follows_signaling_bit_for_bit(design):
    # The C kernel repeats signaling's RK4 expression for expression, so both backends give
    # the same bits (chunks of either backend can be mixed in one run). A failure here means
    # signaling's RK4 arithmetic changed: update signaling.compiled.SOURCE to match it.
    full = models.final_N(design)
    assert np.array_equal(full, models.final_N(design, backend="numpy"))
    # N stays in [Nmin, Nmax] = [0.5, 1.3] up to the last step's overshoot
    assert np.all((full >= 0.5 - 1e-3) & (full <= 1.3 + 1e-3))


def test_a_failing_member_is_masked_not_fatal():
    # beta = 0.8 makes the session stimulus 96/h: RK4 with dt = 0.05 h is unstable for that member only
    X = np.array([[0.04, 0.01], [0.8, 0.01], [0.04, 0.02]])
    N = models.final_N(X, names=("beta", "kM"))
    assert np.isnan(N[1])
    for i in (0, 2):
        p = models.sample_params(X[i : i + 1], ("beta", "kM")).member(0)
        assert N[i] == signaling.integrate(p, named("daily15"), signaling.rest_state(), 0.0, 480.0)[1][-1, 4]
    # the numpy backend fails the whole batch
    with pytest.raises(signaling.SignalingError, match="member 1"):
        models.final_N(X, names=("beta", "kM"), backend="numpy")


# --- analysis ----------------------------------------------------------------------------


def check_ishigami(ind, tol=0.04):
    exact = sobol.ishigami_exact()
    np.testing.assert_allclose(ind.S1, exact["S1"], atol=tol)
    np.testing.assert_allclose(ind.ST, exact["ST"], atol=tol)
    np.testing.assert_allclose(ind.S2[0, 2], exact["S2"][0, 2], atol=2 * tol)
    assert ind.names == ("x1", "x2", "x3")


def test_ishigami_exact_values():
    exact = sobol.ishigami_exact()
    np.testing.assert_allclose(exact["S1"], [0.3139, 0.4424, 0.0], atol=1e-4)
    np.testing.assert_allclose(exact["ST"], [0.5576, 0.4424, 0.2437], atol=1e-4)


def test_ishigami_through_the_farm_and_chunks(tmp_path):
    X = sobol.sample(ISHIGAMI, 2048, seed=5)
    Y, results = chunks.run_chunks(MPI.COMM_SELF, X, models.ishigami, tmp_path, "k", chunk=3000)
    assert [r.status for r in results] == ["done"] * 6
    assert np.array_equal(Y, models.ishigami(X))
    assert len(list((tmp_path / "k").glob("rows_*.npz"))) == 6
    check_ishigami(sobol.analyze(ISHIGAMI, Y, seed=5))


class Evaluator:
    """Ishigami that counts its calls and, like a killed run, dies after ``die_after`` chunks."""

    def __init__(self, die_after=None):
        self.calls = 0
        self.die_after = die_after

    def __call__(self, X):
        if self.die_after is not None and self.calls >= self.die_after:
            raise RuntimeError("killed")
        self.calls += 1
        return models.ishigami(X)


def test_killed_run_resumes_without_recomputing(tmp_path):
    X = sobol.sample(ISHIGAMI, 512, seed=2)  # 4096 rows, 9 chunks of 500
    reference, _ = chunks.run_chunks(MPI.COMM_SELF, X, models.ishigami, tmp_path / "ref", "k", chunk=500)

    first = Evaluator(die_after=4)
    Y, results = chunks.run_chunks(MPI.COMM_SELF, X, first, tmp_path / "run", "k", chunk=500)
    assert Y is None and sum(r.status == "done" for r in results) == 4 and first.calls == 4
    # a half-written chunk is invisible: only whole files under their final name count
    (tmp_path / "run" / "k" / "rows_000004000_000004096.npz.partial").write_bytes(b"junk")

    again = Evaluator()
    Y, results = chunks.run_chunks(MPI.COMM_SELF, X, again, tmp_path / "run", "k", chunk=500)
    assert again.calls == 9 - 4
    assert [r.status for r in results].count("skipped") == 4
    assert np.array_equal(Y, reference)
    a, b = sobol.analyze(ISHIGAMI, Y, seed=2), sobol.analyze(ISHIGAMI, reference, seed=2)
    assert (np.array_equal(a.S1, b.S1) and np.array_equal(a.ST_conf, b.ST_conf)
            and np.array_equal(a.S2, b.S2, equal_nan=True))

    # a truncated chunk file or one of other settings (another digest inside) is recomputed
    path = next((tmp_path / "run" / "k").glob("rows_000000000_*.npz"))
    path.write_bytes(path.read_bytes()[:50])
    third = Evaluator()
    Y, _ = chunks.run_chunks(MPI.COMM_SELF, X, third, tmp_path / "run", "k", chunk=500)
    assert third.calls == 1 and np.array_equal(Y, reference)


def test_digest_changes_with_samples_and_settings():
    X = sobol.sample(ISHIGAMI, 8, seed=1)
    key = chunks.digest(X, {"dt": 0.05})
    assert key == chunks.digest(X.copy(), {"dt": 0.05})
    assert key != chunks.digest(X, {"dt": 0.1})
    assert key != chunks.digest(sobol.sample(ISHIGAMI, 8, seed=2), {"dt": 0.05})


def test_failures_abort_or_drop_their_base_samples():
    X = sobol.sample(ISHIGAMI, 256, seed=4)
    Y = models.ishigami(X)
    Y[[5, 6, 8 * 40 + 1]] = np.nan  # two failed rows in base sample 0, one in base sample 40
    with pytest.raises(ValueError, match="3 of 2048 model evaluations failed .in 2 base samples"):
        sobol.analyze(ISHIGAMI, Y, seed=1)
    ind = sobol.analyze(ISHIGAMI, Y, seed=1, on_failure="drop")
    assert (ind.dropped, ind.base_samples) == (2, 254)
    keep = np.ones(256, bool)
    keep[[0, 40]] = False
    manual = sobol.analyze(ISHIGAMI, Y.reshape(256, 8)[keep].ravel(), seed=1)
    assert np.array_equal(ind.ST, manual.ST) and np.array_equal(ind.S1_conf, manual.S1_conf)


# --- CLI ---------------------------------------------------------------------------------


def test_cli_ishigami_writes_results_and_resumes(tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["--function", "ishigami", "--samples", "1024", "--chunk", "2000", "--output", str(out), "--seed", "7"]
    assert sobol_job.main(argv, comm=MPI.COMM_SELF) == 0
    text = capsys.readouterr().out
    assert "failed members: 0" in text and "not a power of 2" not in text
    lines = (out / "indices.csv").read_text().splitlines()
    assert lines[0] == "parameter,S1,S1_conf,ST,ST_conf" and [l.split(",")[0] for l in lines[1:]] == ["x1", "x2", "x3"]
    with h5py.File(out / "sobol.h5") as f:
        assert f.attrs["complete"] and f.attrs["failures"] == 0 and f.attrs["N"] == 1024
        assert f["Y"].shape == (8192,) and f["S2"].shape == (3, 3) and f["S1_bootstrap"].shape == (100, 3)
        assert [n.decode() for n in f["parameters"][()]] == ["x1", "x2", "x3"]
        assert "version_SALib" in f.attrs and "wall_s" in f.attrs
        S1 = f["S1"][()]
    assert (out / "spread.png").stat().st_size > 0 and (out / "indices.png").stat().st_size > 0
    # a rerun finds every chunk done and gives the same numbers
    assert sobol_job.main(argv, comm=MPI.COMM_SELF) == 0
    assert "0 to run, 5 skipped" in capsys.readouterr().out
    with h5py.File(out / "sobol.h5") as f:
        assert np.array_equal(f["S1"][()], S1)
    # another seed is another design: the old chunks go, all are computed anew
    assert sobol_job.main([*argv[:-1], "8"], comm=MPI.COMM_SELF) == 0
    text = capsys.readouterr().out
    assert "removed chunks of other settings" in text and "5 to run, 0 skipped" in text
    assert len(list((out / "chunks").iterdir())) == 1


def test_cli_signaling_small(tmp_path, capsys):
    out = tmp_path / "s"
    assert sobol_job.main(["--samples", "16", "--chunk", "200", "--output", str(out)], comm=MPI.COMM_SELF) == 0
    with h5py.File(out / "sobol.h5") as f:
        assert f.attrs["evaluations"] == 480 and f.attrs["dt"] == 0.05 and f.attrs["protocol"] == "daily15"
        assert f.attrs["failures"] == 0 and f["failed_rows"].shape == (0,)
        assert f["protocol"].attrs["end"] == 480.0 and f["signaling"].attrs["kM"] == 0.01
        X, Y = f["X"][()], f["Y"][()]
    assert np.array_equal(Y[:30], models.final_N(X[:30]))
    # the result's study text is a --problem file that reruns the same analysis
    with h5py.File(out / "sobol.h5") as f:
        study, digest = f.attrs["study"], f.attrs["digest"]
    assert study.startswith("[sobol]") and 'protocol = "daily15"' in study and "samples = 16" in study
    (tmp_path / "again.toml").write_text(study)
    again = tmp_path / "again"
    assert sobol_job.main(["--problem", str(tmp_path / "again.toml"), "--chunk", "200", "--output", str(again)],
                      comm=MPI.COMM_SELF) == 0
    with h5py.File(again / "sobol.h5") as f:
        assert f.attrs["digest"] == digest and np.array_equal(f["Y"][()], Y)


def test_cli_failures_are_reported(tmp_path, capsys):
    # dt = 0.7 h is beyond RK4's stability limit during sessions: every member fails
    out = tmp_path / "f"
    assert sobol_job.main(["--samples", "2", "--signaling-dt", "0.7", "--output", str(out)], comm=MPI.COMM_SELF) == 1
    captured = capsys.readouterr()
    assert "failed members: 60" in captured.out and "60 of 60 model evaluations failed" in captured.err
    assert not (out / "sobol.h5").exists()


@pytest.mark.parametrize("args, message", [
    (["--samples", "1"], "--samples: expected an integer in [2, "),
    (["--signaling-dt", "0"], "--signaling-dt: expected a finite number of hours > 0"),
    (["--chunk", "0"], "--chunk: expected an integer in [1, "),
    (["--protocol", "nope"], "unknown protocol 'nope'"),
])
def test_cli_bad_input(tmp_path, capsys, args, message):
    out = tmp_path / "bad"
    assert sobol_job.main([*args, "--output", str(out)], comm=MPI.COMM_SELF) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


# --- mpirun -n 2 -------------------------------------------------------------------------


@pytest.mark.mpi
def test_mpi_ishigami_farm_equals_serial(tmp_path):
    comm = MPI.COMM_WORLD
    assert comm.size == 2
    folder = Path(comm.bcast(str(tmp_path) if comm.rank == 0 else None, root=0))
    X = sobol.sample(ISHIGAMI, 1024, seed=9)

    def slow(rows):  # long enough for rank 1 to ask for work while rank 0 is busy
        time.sleep(0.05)
        return models.ishigami(rows)

    Y, results = chunks.run_chunks(comm, X, slow, folder / "par", "k", chunk=700)
    assert {r.group for r in results} == {0, 1}  # both ranks evaluated chunks
    if comm.rank == 0:
        serial, _ = chunks.run_chunks(MPI.COMM_SELF, X, models.ishigami, folder / "ser", "k", chunk=700)
        assert np.array_equal(Y, serial)
        a, b = sobol.analyze(ISHIGAMI, Y, seed=9), sobol.analyze(ISHIGAMI, serial, seed=9)
        assert np.array_equal(a.S1, b.S1) and np.array_equal(a.ST, b.ST) and np.array_equal(a.ST_conf, b.ST_conf)
        check_ishigami(a)
    else:
        assert Y is None


def test_a_sigterm_lets_the_chunk_in_progress_finish_and_starts_no_other(tmp_path):
    """What Slurm's warning does to a Sobol job: the chunks done are kept, the rest left for
    the rerun, which computes only those and gives the uninterrupted outputs."""
    X = sobol.sample(sobol.ishigami_problem(), 64, seed=3)
    reference, _ = chunks.run_chunks(MPI.COMM_SELF, X, models.ishigami, tmp_path / "ref", "k", chunk=100)
    calls = []

    def stop():
        calls.append(1)
        return len(calls) > 2  # asked before each chunk: two run, then the TERM has come

    Y, results = chunks.run_chunks(MPI.COMM_SELF, X, models.ishigami, tmp_path / "run", "k", chunk=100, stop=stop)
    assert Y is None
    assert sum(chunks.interrupted(r) for r in results) == len(results) - 2
    assert len(list((tmp_path / "run" / "k").glob("*.npz"))) == 2
    Y, results = chunks.run_chunks(MPI.COMM_SELF, X, models.ishigami, tmp_path / "run", "k", chunk=100)
    assert sum(r.status == "skipped" for r in results) == 2
    np.testing.assert_array_equal(Y, reference)


def test_the_default_base_sample_count_is_a_power_of_two():
    args = sobol_job.parser().parse_args([])
    sobol_job._check(args)
    assert args.samples == sobol.SAMPLES and args.samples & (args.samples - 1) == 0


def test_the_problem_from_options_and_from_a_file(tmp_path):
    from hyper.model import protocols

    args = sobol_job.parser().parse_args(["--parameters", "kM", "kF", "--range", "0.8", "1.25", "--protocol", "weekly",
                                      "--at", "200"])
    protocol, prob = sobol_job._check(args)
    assert prob == {"num_vars": 2, "names": ["kM", "kF"], "bounds": [[0.008, 0.0125], [0.8 * 0.019, 1.25 * 0.019]]}
    assert protocol.name == "weekly" and args.at == 200.0
    # a study file's [sobol] table in SALib's form; options override it
    path = tmp_path / "study.toml"
    path.write_text('geometries = ["cylinder"]\nprotocols = ["weekly"]\n[sobol]\nfunction = "csa-gain"\n'
                    'protocol = "every3days"\nnames = ["kM", "hill_n"]\nbounds = [[0.005, 0.02], [2, 8]]\n'
                    'num_vars = 2\nsamples = 64\nat = 336\n')
    args = sobol_job.parser().parse_args(["--problem", str(path)])
    protocol, prob = sobol_job._check(args)
    assert (args.function, args.samples, args.at, protocol.name) == ("csa-gain", 64, 336.0, "every3days")
    assert prob["names"] == ["kM", "hill_n"] and prob["bounds"] == [[0.005, 0.02], [2.0, 8.0]]
    args = sobol_job.parser().parse_args(["--problem", str(path), "--samples", "32", "--parameters", "kF"])
    protocol, prob = sobol_job._check(args)
    assert args.samples == 32 and prob["names"] == ["kF"] and prob["bounds"] == [[0.5 * 0.019, 2 * 0.019]]
    # N at a time is N of the run that ends there
    X = np.array([[0.01, 0.019]])
    early = models.final_N(X, names=["kM", "kF"], protocol=protocols.named("mwf"), at=336.0)
    mwf = protocols.named("mwf")
    short = protocols.Protocol(tuple(s for s in mwf.sessions if s.end <= 336.0), 336.0, "two-weeks")
    assert 0 < len(short.sessions) < len(mwf.sessions)
    assert early == pytest.approx(models.final_N(X, names=["kM", "kF"], protocol=short), rel=1e-14)


@pytest.mark.parametrize("text, message", [
    ('names = ["kM"]\nbounds = [[0.02, 0.01]]\n', "bounds: kM: expected 0 < lower < upper"),
    ('names = ["kX"]\n', "expected distinct parameters of"),
    ('names = ["kM", "kF"]\nbounds = [[0.01, 0.02]]\n', "one [lower, upper] pair per parameter (2), got 1"),
    ('names = ["kM"]\nnum_vars = 3\n', "num_vars: 3 does not count names (1)"),
    ('bounds = [[1, 2]]\n', "bounds: give the names they belong to"),
    ('function = "n-at-noon"\n', "function: expected one of signaling, csa-gain, ishigami"),
    ('samples = 1\n', "samples: expected an integer in [2, 10000000]"),
    ('at = 2000\n', "--at: 2000 h is after the end of daily15 (480 h)"),
    ('[sobol]\nsigma = 1\n', "sobol: unknown key(s) sigma; known: function"),
])
def test_bad_problems_are_refused_and_write_nothing(tmp_path, capsys, text, message):
    path = tmp_path / "p.toml"
    path.write_text(text)
    assert sobol_job.main(["--problem", str(path), "--output", str(tmp_path / "out")], comm=MPI.COMM_SELF) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()


def test_an_analysis_of_two_parameters_at_a_time(tmp_path):
    out = tmp_path / "o"
    argv = ["--parameters", "kM", "a10", "--protocol", "mwf", "--at", "168", "--samples", "8", "--output", str(out)]
    assert sobol_job.main(argv, comm=MPI.COMM_SELF) == 0
    with h5py.File(out / "sobol.h5") as f:
        assert [n.decode() for n in f["parameters"][()]] == ["kM", "a10"] and f["X"].shape == (48, 2)
        assert f.attrs["at_h"] == 168.0 and f["settings"].attrs["at_h"] == 168.0
        assert list(f["bounds"].attrs["kM"]) == [0.005, 0.02]
        X, Y = f["X"][()], f["Y"][()]
    assert np.array_equal(Y, models.final_N(X, names=["kM", "a10"], protocol=named("mwf"), at=168.0))


def test_spread_labels_overlap_neither_each_other_nor_a_point():
    rng = np.random.default_rng(3)
    points = np.vstack([rng.normal(100.0, 6.0, (12, 2)), [[400.0, 300.0], [404.0, 302.0]]])  # a cluster, a pair
    sizes = [(20.0 + 3 * k, 13.0) for k in range(len(points))]
    offsets = sobolplot.label_offsets(points, sizes, 8.0)
    boxes = [(x + dx, y + dy, x + dx + w, y + dy + h) for (x, y), (dx, dy), (w, h) in zip(points, offsets, sizes)]
    for i, a in enumerate(boxes):
        for b in boxes[i + 1:]:
            assert not (a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]), (a, b)
        inside = (points[:, 0] > a[0] - 8) & (points[:, 0] < a[2] + 8) & (points[:, 1] > a[1] - 8) & \
            (points[:, 1] < a[3] + 8)
        assert not inside.any()
