"""python -m hyper.cohort: statistics by hand (serial), option errors, and a small cohort
(cylinder and idealized × a 4-day protocol) under mpirun -n 2: summary, failure, rerun."""

import csv
import math
from pathlib import Path

import numpy as np
import pytest
from mpi4py import MPI

from hyper.analysis import cohort, cohortplot, cohortstats, cohortsummary
from hyper.commands import cohort as cohort_job
from hyper.core import io
from hyper.fem.coupled import GrowthSettings
from hyper.runs import driver, runspec

SHORT_PROTOCOL = """name = "short"
end = 96.0
[[session]]
start = 24.0
duration = 1.0
intensity = 0.8
"""


def row(geometry, protocol, csa, volume, status="done"):
    muscle = geometry.split("_")[0]
    return {"geometry": geometry, "muscle": muscle, "subject": "VHF", "side": "Left", "protocol": protocol,
            "csa0_cm2": 10.0, "volume0_cm3": 100.0, "final_csa_ratio": csa, "final_volume_ratio": volume,
            "wall_s": 1.0, "status": status}


def synthetic_rows():
    """Two muscles × the paper's protocols; ratios chosen so that the statistics are easy by hand."""
    rows = []
    for i, (csa, vol) in enumerate([(1.04, 1.08), (1.05, 1.09), (1.06, 1.085), (1.03, 1.095)]):
        g = f"BFLH_M{i}_Left"
        rows += [row(g, "mwf", csa, vol), row(g, "every3days", csa - 0.01, vol - 0.02),
                 row(g, "weekly", csa - 0.02, vol - 0.05)]
    rows += [row("TA_M0_Left", "mwf", 1.02, 1.01), row("TA_M0_Left", "every3days", 1.03, 1.0),
             row("TA_M0_Left", "weekly", math.nan, math.nan, status="failed")]
    return rows


# --- serial ----------------------------------------------------------------------------


def test_standard_error_by_hand():
    # 4, 5, 6, 3: mean 4.5, squared deviations 0.25 + 0.25 + 2.25 + 2.25 = 5, s² = 5/3, se = s/2
    assert cohortstats.standard_error([4.0, 5.0, 6.0, 3.0]) == pytest.approx(math.sqrt(5 / 3) / 2, rel=1e-14)
    assert cohortstats.standard_error([2.0, 2.0]) == 0.0
    assert math.isnan(cohortstats.standard_error([7.0]))


def test_group_statistics_by_hand():
    stats = cohortstats.group_statistics(synthetic_rows(), "csa")
    bflh = stats[("BFLH", "mwf")]
    assert bflh["n"] == 4
    assert bflh["mean"] == pytest.approx(4.5, rel=1e-12)
    assert bflh["se"] == pytest.approx(math.sqrt(5 / 3) / 2, rel=1e-10)
    assert stats[("BFLH", "weekly")]["mean"] == pytest.approx(2.5, rel=1e-12)
    # volume under mwf: 8, 9, 8.5, 9.5 -> mean 8.75, deviations² 0.5625 + 0.0625 + 0.0625 + 0.5625
    vol = cohortstats.group_statistics(synthetic_rows(), "volume")[("BFLH", "mwf")]
    assert vol["mean"] == pytest.approx(8.75, rel=1e-12)
    assert vol["se"] == pytest.approx(math.sqrt(1.25 / 3) / 2, rel=1e-10)
    # one member: no standard error; failed runs are left out
    assert stats[("TA", "mwf")]["n"] == 1 and math.isnan(stats[("TA", "mwf")]["se"])
    assert ("TA", "weekly") not in stats


def test_order_and_mwf_statistics():
    rows = synthetic_rows()
    assert cohortstats.ordered(cohortstats.increases(rows, "BFLH_M0_Left", "csa")) is True
    assert cohortstats.ordered(cohortstats.increases(rows, "TA_M0_Left", "csa")) is None  # weekly failed
    assert cohortstats.ordered({"mwf": 3.0, "every3days": 3.0, "weekly": 1.0}) is False  # strict
    s = cohortstats.mwf_statistics(rows, "volume")
    assert s["n"] == 5
    assert s["mean"] == pytest.approx((8 + 9 + 8.5 + 9.5 + 1) / 5, rel=1e-12)
    assert (s["min"], s["max"]) == pytest.approx((1.0, 9.5), rel=1e-12)
    table = cohortsummary.markdown(rows, GrowthSettings())
    assert "| BFLH_M0_Left | +4.00 % | +3.00 % | +2.00 % | +8.00 % | +6.00 % | +3.00 % | yes | yes |" in table
    assert "| TA_M0_Left | +2.00 % | +3.00 % | failed |" in table
    assert "both CSA and volume: 4 of 5 geometries" in table
    assert "under mwf: 4 of 5" in table  # TA: volume +1 % < CSA +2 %
    assert "| volume increase (n = 5) | +7.20 % | +1.00 % | +9.50 % | +8–9 % |" in table
    assert "Not done: TA_M0_Left/weekly." in table


def test_csv_round_trip(tmp_path):
    rows = synthetic_rows()
    cohortsummary.write_csv(rows, tmp_path / "s.csv")
    back = cohortsummary.read_csv(tmp_path / "s.csv")
    assert list(back[0]) == list(cohortsummary.COLUMNS)
    assert back[0]["final_csa_ratio"] == rows[0]["final_csa_ratio"]
    assert back[-1]["status"] == "failed" and math.isnan(back[-1]["final_csa_ratio"])


def test_boundary_faces_of_a_cube_point_outwards():
    from dolfinx import mesh

    m = mesh.create_unit_cube(MPI.COMM_SELF, 2, 3, 2)
    x = m.geometry.x
    cells = m.geometry.dofmaps[0].astype(np.int64)
    faces, owner = cohortplot.boundary_faces(x, cells)
    assert len(faces) == 2 * (2 * 3 + 3 * 2 + 2 * 2) * 2
    a, b, c = (x[faces[:, i]] for i in range(3))
    n = np.cross(b - a, c - a) / 2
    assert np.sum(np.linalg.norm(n, axis=1)) == pytest.approx(6.0, rel=1e-13)
    # divergence theorem: the outward surface integral of x/3 is the volume
    assert np.sum(np.einsum("ij,ij->i", (a + b + c) / 3, n)) / 3 == pytest.approx(1.0, rel=1e-13)
    assert np.all(np.isin(faces, cells[owner]).reshape(-1, 3))


def test_final_fields_reads_the_last_snapshot(tmp_path):
    from dolfinx import fem, io, mesh

    m = mesh.create_unit_cube(MPI.COMM_SELF, 1, 1, 1)
    u = fem.Function(fem.functionspace(m, ("Lagrange", 1, (3,))), name="u")
    det = fem.Function(fem.functionspace(m, ("DG", 0)), name="detGbar")
    with io.XDMFFile(MPI.COMM_SELF, str(tmp_path / "f.xdmf"), "w") as xdmf:
        xdmf.write_mesh(m)
        for t in (0.0, 12.5, 2.25, 100.0 / 3):  # stored as "12_5", "33_333333333333336", …
            u.x.array[:] = t
            det.x.array[:] = 1 + t
            xdmf.write_function(u, t)
            xdmf.write_function(det, t)
    f = cohortplot.final_fields(tmp_path / "f.xdmf")
    assert f["t"] == pytest.approx(100.0 / 3, rel=1e-14)
    assert np.all(f["u"] == pytest.approx(100.0 / 3)) and np.all(f["detGbar"] == pytest.approx(1 + 100.0 / 3))
    assert f["cells"].shape == (6, 4) and f["x"].shape == (8, 3)


def test_stale_checkpoint_is_dropped(tmp_path):
    path = tmp_path / "run.ckpt.h5"
    path.write_text("not a checkpoint")
    cohort.drop_stale_checkpoint(path, "0" * 64)
    assert not path.exists()
    cohort.drop_stale_checkpoint(path, "0" * 64)  # nothing there: nothing to do


@pytest.mark.parametrize("argv, message", [
    (["--growth-dt", "-1"], "--growth-dt"),
    (["--max-halvings", "-1"], "--max-halvings"),
    (["--geometries", "nowhere"], "unknown nowhere"),
    (["--protocols", "daily"], "unknown protocol"),
    (["--snapshot-every", "0"], "--snapshot-every"),
    (["--ranks-per-job", "0"], "--ranks-per-job"),
    (["--plot-geometry", "nowhere"], "--plot-geometry"),
])
def test_bad_options_exit_2_and_write_nothing(tmp_path, capsys, argv, message):
    out = tmp_path / "out"
    assert cohort_job.main([*argv, "--output", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


# --- mpirun -n 2 -------------------------------------------------------------------------


def shared_tmp(comm, tmp_path):
    return Path(comm.bcast(str(tmp_path) if comm.rank == 0 else None, root=0))


def failing_for(geometry):
    """run.execute, except that it fails (on every rank of the group) for one geometry."""
    real = driver.execute

    def execute(comm, spec, *args, **kwargs):
        if spec.geometry == geometry:
            raise RuntimeError(f"injected failure for {spec.geometry}")
        return real(comm, spec, *args, **kwargs)

    return execute


def read_rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.mpi
def test_mpi_small_cohort_failure_rerun_and_skip(tmp_path, monkeypatch):
    comm = MPI.COMM_WORLD
    folder = shared_tmp(comm, tmp_path)
    protocol = folder / "short.toml"
    if comm.rank == 0:
        protocol.write_text(SHORT_PROTOCOL)
    comm.barrier()
    out = folder / "cohort"
    argv = ["--geometries", "cylinder", "idealized", "--protocols", str(protocol), "--output", str(out),
            "--plot-geometry", "cylinder", "--snapshot-every", "2"]

    # 1. two groups of one rank; the idealized run fails, the cylinder run finishes
    with monkeypatch.context() as m:
        m.setattr(driver, "execute", failing_for("idealized"))
        assert cohort_job.main(argv) == 1
    rows = read_rows(out / "summary.csv")
    assert list(rows[0]) == list(cohortsummary.COLUMNS)
    assert [(r["geometry"], r["protocol"], r["status"]) for r in rows] == [
        ("cylinder", "short", "done"), ("idealized", "short", "failed")]
    assert rows[1]["final_csa_ratio"] == ""
    assert "injected failure for idealized" in (out / "failures.txt").read_text()
    cylinder = out / "runs" / "cylinder_short.h5"
    stamp = cylinder.stat().st_mtime_ns

    # 2. the rerun, on one group of two ranks, runs only the failed run
    assert cohort_job.main([*argv, "--ranks-per-job", "2"]) == 0
    assert cylinder.stat().st_mtime_ns == stamp
    assert not (out / "failures.txt").exists()
    assert not list((out / "runs").glob("*.ckpt.h5"))  # stored runs delete their checkpoints
    rows = read_rows(out / "summary.csv")
    assert [r["status"] for r in rows] == ["done", "done"]
    for r in rows:
        series = io.read_series(out / "runs" / f"{r['geometry']}_short.h5")
        assert float(r["final_csa_ratio"]) == series["csa_ratio"][-1]
        assert float(r["final_volume_ratio"]) == series["volume_ratio"][-1]
        assert float(r["final_csa_ratio"]) > 1.0005  # one session grows by about 0.09 %
    # uniform growth of the cylinder is exact: CSA and volume grow alike
    assert float(rows[0]["final_csa_ratio"]) == pytest.approx(float(rows[0]["final_volume_ratio"]), rel=1e-9)
    # the cylinder (length 10 cm) is a prism: its cross-section is its volume over its length
    assert float(rows[0]["csa0_cm2"]) == pytest.approx(float(rows[0]["volume0_cm3"]) / 10.0, rel=0.01)
    for name in ("ratios.png", "shape.png", "table.md", "runs/idealized_short_fields.xdmf",
                 "runs/idealized_short_fields.h5", "runs/idealized_short.log"):
        assert (out / name).is_file(), name
    first = (out / "summary.csv").read_text()

    # 3. nothing left to do: the same summary, read back from the files
    assert cohort_job.main(argv) == 0
    assert (out / "summary.csv").read_text() == first
    assert cylinder.stat().st_mtime_ns == stamp

    # 4. another growth step is another result: the runs are done again
    assert cohort_job.main([*argv, "--growth-dt", "48"]) == 0
    assert cylinder.stat().st_mtime_ns != stamp


class StopAfter:
    """A stop() that turns true at its n-th call (run_one asks at each step boundary)."""

    def __init__(self, n):
        self.n = n
        self.calls = 0

    def __call__(self):
        self.calls += 1
        return self.calls >= self.n


@pytest.mark.mpi
def test_mpi_interrupted_run_resumes_to_the_uninterrupted_result(tmp_path):
    from hyper.model import protocols

    comm = MPI.COMM_WORLD
    folder = shared_tmp(comm, tmp_path)
    if comm.rank == 0:
        (folder / "short.toml").write_text(SHORT_PROTOCOL)
    comm.barrier()
    entry = cohort.Run("cylinder", protocols.load(folder / "short.toml"))
    whole = cohort.run_cohort(comm, [entry], folder / "whole", ranks_per_job=2)
    assert whole[0].status == "done"

    # stopped after its 2nd growth step (stop() is asked at the start and after each step):
    # a checkpoint, no result
    out = folder / "cut"
    stopped = cohort.run_cohort(comm, [entry], out, ranks_per_job=2, stop=StopAfter(3))
    assert stopped[0].status == "done"
    h5 = cohort.series_path(out, entry)
    assert not h5.exists() and runspec.Outputs(h5).checkpoint.is_file()
    # a run that has not started when the stop comes is not started at all
    other = cohort.Run("idealized", entry.protocol)
    never = cohort.run_cohort(comm, [other], out, stop=lambda: True)
    assert not (out / "runs" / "idealized_short.log").exists()
    if comm.rank == 0:
        assert stopped[0].result == {"interrupted": True}
        assert never[0].result == {"interrupted": True}
        rows = cohortsummary.summarize(out, [entry, other], {}, {entry.key, other.key})
        assert [r["status"] for r in rows] == ["interrupted", "interrupted"]

    # resumed on two groups of one rank: the result of the entry that was never stopped
    resumed = cohort.run_cohort(comm, [entry], out, ranks_per_job=1)
    assert resumed[0].status == "done"
    assert not runspec.Outputs(h5).checkpoint.exists()
    assert "resuming from" in (out / "runs" / "cylinder_short.log").read_text()
    a = io.read_series(cohort.series_path(folder / "whole", entry))
    b = io.read_series(h5)
    assert np.array_equal(a["t"], b["t"])
    np.testing.assert_allclose(b["csa_ratio"], a["csa_ratio"], rtol=1e-12, atol=0)
    np.testing.assert_allclose(b["volume_ratio"], a["volume_ratio"], rtol=1e-12, atol=0)
