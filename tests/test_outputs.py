"""What a run writes for other tools and readers: the fields file (meshio, ParaView),
snapshots by simulated time, the comparison with measured CSA (--data), and progress
lines that suit batch logs."""

import os
import re
import shutil
import subprocess
from pathlib import Path

import dolfinx_solver  # noqa: F401
import h5py
import meshio
import numpy as np
import pytest
from mpi4py import MPI

from hyper.analysis import study
from hyper.commands import cli, grow
from hyper.commands import study as study_job
from hyper.core import io, log
from hyper.core.params import InputError
from hyper.model import protocols
from hyper.runs import driver, measured, runspec
from test_reliability import PROTOCOL  # the short two-session protocol

ROOT = Path(__file__).resolve().parents[1]

# CSA change in percent after 2 and 4 days
DATA = "day,csa_change_percent\n0,0\n2,0.5\n4,1.0\n"


@pytest.fixture(scope="module")
def grown(tmp_path_factory):
    """A 4-day run on the cylinder (growth step 8 h, a snapshot every 24 h), compared with DATA."""
    d = tmp_path_factory.mktemp("grown")
    (d / "short.toml").write_text(PROTOCOL)
    (d / "growing.toml").write_text("thetaM = 0.46\n")  # mTOR above its threshold: growth from the first hour
    (d / "data.csv").write_text(DATA)
    out = d / "run.h5"
    assert grow.main(["--geometry", "cylinder", "--protocol", str(d / "short.toml"), "--params",
                      str(d / "growing.toml"), "--growth-dt", "8", "--snapshot-every", "24", "--data",
                      str(d / "data.csv"), "--output", str(out)]) == 0
    return out


def read_fields(path: Path) -> list[tuple[float, dict, dict]]:
    with meshio.xdmf.TimeSeriesReader(path) as reader:
        points, cells = reader.read_points_cells()
        steps = [reader.read_data(k) for k in range(reader.num_steps)]
    return points, cells, steps


def test_one_grid_holds_every_function_at_every_time(tmp_path):
    from dolfinx import fem, mesh

    m = mesh.create_unit_cube(MPI.COMM_SELF, 2, 2, 2)
    u = fem.Function(fem.functionspace(m, ("Lagrange", 1, (3,))), name="u")
    det = fem.Function(fem.functionspace(m, ("DG", 0)), name="detGbar")
    a0 = fem.Function(fem.functionspace(m, ("Lagrange", 1, (3,))), name="a0")
    a0.x.array[:] = 7.0
    with io.atomic_xdmf(MPI.COMM_SELF, tmp_path / "f.xdmf") as xdmf:
        xdmf.write_mesh(m)
        for t in (0.0, 12.5, 100.0 / 3):
            u.x.array[:] = t
            det.x.array[:] = 1 + t
            for f in (u, det) + ((a0,) if t == 0 else ()):  # the fibres once, as run.Snapshots writes them
                xdmf.write_function(f, t)
    points, cells, steps = read_fields(tmp_path / "f.xdmf")
    assert points.shape == (27, 3) and cells[0].type == "tetra" and len(cells[0].data) == 48
    assert [t for t, _, _ in steps] == pytest.approx([0.0, 12.5, 100.0 / 3], rel=1e-15)
    for t, point_data, cell_data in steps:
        assert sorted(point_data) == ["a0", "u"] and sorted(cell_data) == ["detGbar"]
        assert np.all(point_data["u"] == pytest.approx(t, rel=1e-15))
        assert np.all(cell_data["detGbar"][0] == pytest.approx(1 + t, rel=1e-15))
        assert np.all(point_data["a0"] == 7.0)  # held from t = 0
    # the XML is one temporal collection (no grid of its own for the mesh, no function collections)
    text = (tmp_path / "f.xdmf").read_text()
    assert text.count('GridType="Collection"') == 1 and text.count("<Grid ") == 4


def test_snapshot_due_by_simulated_time():
    assert driver.snapshot_due([], 0.0, 24.0)
    assert not driver.snapshot_due([0.0], 23.9, 24.0)
    assert driver.snapshot_due([0.0], 8.0 + 8.0 + 8.0 - 1e-12, 24.0)  # a sum of steps a hair short of 24 h
    assert driver.snapshot_due([0.0], 30.0, 24.0)
    assert not driver.snapshot_due([25.0], 47.0, 24.0) and driver.snapshot_due([25.0], 48.0, 24.0)
    assert not driver.snapshot_due([24.0], 24.0 + 23.0, 24.0)


def test_grow_fields_are_read_whole_by_meshio(grown):
    series = io.read_series(grown)
    points, cells, steps = read_fields(runspec.Outputs(grown).fields)
    times = [t for t, _, _ in steps]
    # the first state, the first growth step on or after each 24 h, and the last state
    kept = []
    for t in series["t"]:
        if driver.snapshot_due(kept, t, 24.0) or t == series["t"][-1]:
            kept.append(float(t))
    assert times == pytest.approx(kept, rel=1e-14) and times[0] == 0.0 and times[-1] == 96.0
    assert len(times) == 5
    ncells = len(cells[0].data)
    for _, point_data, cell_data in steps:
        assert sorted(point_data) == ["a0", "u"] and sorted(cell_data) == ["detGbar"]
        assert point_data["u"].shape == points.shape and cell_data["detGbar"][0].shape == (ncells, 1)
        assert np.allclose(np.linalg.norm(point_data["a0"], axis=1), 1.0, atol=1e-12)  # unit fibres
    first, last = steps[0], steps[-1]
    assert np.all(first[1]["u"] == 0.0) and np.all(first[2]["detGbar"][0] == 1.0)
    # growth is uniform here: det Ḡ is one number, the volume ratio of the last state
    det = last[2]["detGbar"][0]
    assert np.ptp(det) < 1e-12 and float(det[0, 0]) == pytest.approx(series["volume_ratio"][-1], rel=1e-4)
    assert np.abs(last[1]["u"]).max() > 1e-5


def test_grow_compares_with_its_data(grown):
    series = io.read_series(grown)
    model = np.interp([48.0, 96.0], series["t"], series["csa_ratio"])
    diff = 100 * (model - np.array([1.005, 1.01]))
    with h5py.File(grown, "r") as f:
        data = dict(f["data"].attrs)
    assert data["rmse_pp"] == pytest.approx(np.sqrt(np.mean(diff ** 2)), rel=1e-12)
    assert data["last_difference_pp"] == pytest.approx(diff[-1], rel=1e-12)
    assert data["last_time_h"] == 96.0 and list(data["time_h"]) == [48.0, 96.0]
    assert data["measured_csa_ratio"] == pytest.approx([1.005, 1.01], rel=1e-15)
    assert data["label"] == "data" and len(data["file_sha256"]) == 64


@pytest.mark.skipif(shutil.which("pvbatch") is None or shutil.which("xvfb-run") is None,
                    reason="ParaView (pvbatch) and xvfb-run not installed")
def test_pvbatch_renders_the_fields(grown, tmp_path):
    png = tmp_path / "fields.png"
    # a 24-bit screen: the default 8-bit one may offer no OpenGL visual
    # pvbatch sometimes aborts (SIGABRT, exit 134) while it creates its window on a busy
    # Xvfb, before it reads anything; a second start has always worked. Other failures count.
    for _ in range(3):
        done = subprocess.run(["xvfb-run", "-a", "-s", "-screen 0 1280x1024x24", "pvbatch",
                               str(ROOT / "jobs" / "paraview_render.py"), str(runspec.Outputs(grown).fields), str(png)],
                              capture_output=True, text=True, timeout=300)
        if done.returncode != 134 or "snapshots" in done.stdout:
            break
    assert done.returncode == 0, done.stdout + done.stderr
    assert "5 snapshots, t = 0 … 96 h; point data ['a0', 'u'], cell data ['detGbar']" in done.stdout
    assert "colour: u" in done.stdout  # uniform growth: det Ḡ is the same everywhere, |u| is not
    assert png.stat().st_size > 10_000


# ------------------------------------------------------------------------- measured data


def test_percent_and_absolute_csa_read_alike(tmp_path):
    (tmp_path / "a.csv").write_text("week,csa\n0,50\n1,51\n3,53.5\n")
    (tmp_path / "p.csv").write_text("hour,csa_change_percent\n0,0\n168,2\n504,7\n")
    a, p = measured.read(tmp_path / "a.csv"), measured.read(tmp_path / "p.csv")
    assert list(a.t) == list(p.t) == [168.0, 504.0]
    assert a.csa_ratio == pytest.approx([1.02, 1.07], rel=1e-15) and p.csa_ratio == pytest.approx(a.csa_ratio)


def test_comparison_numbers():
    data = measured.Measured(Path("x.csv"), "x", np.array([10.0, 20.0]), np.array([1.01, 1.05]))
    c = measured.compare(data, np.array([0.0, 20.0]), np.array([1.0, 1.06]))  # model 1.03 at 10 h
    assert c.difference_pp == pytest.approx([2.0, 1.0], rel=1e-12)
    assert c.rmse_pp == pytest.approx(np.sqrt(2.5), rel=1e-12) and c.last_difference_pp == pytest.approx(1.0)


def test_each_shipped_data_set_belongs_to_its_protocol():
    mwf = measured.of_protocol(protocols.from_option("mwf")[0], "idealized")
    assert mwf.label == "DeFreitas et al. 2011" and len(mwf.t) == 9 and mwf.t[-1] == 9 * 168.0
    damas = measured.of_protocol(protocols.load(ROOT / "data" / "damas.toml"), "idealized")
    assert damas.label == "Damas et al. 2016" and list(damas.t) == [3 * 168.0, 10 * 168.0]
    seynnes = measured.of_protocol(protocols.load(ROOT / "data" / "seynnes.toml"), "idealized")
    assert seynnes.label == "Seynnes et al. 2007" and seynnes.csa_ratio[-1] == pytest.approx(70.65 / 65.81)
    assert measured.of_protocol(protocols.from_option("weekly")[0], "idealized") is None
    # the schedule decides, not the name
    renamed = protocols.Protocol(protocols.from_option("mwf")[0].sessions, protocols.from_option("mwf")[0].end, "x")
    assert measured.of_protocol(renamed, "idealized").label == "DeFreitas et al. 2011"


def test_the_shipped_data_say_their_muscle_and_measure():
    muscles = {name: measured.read(ROOT / "data" / name).muscle for name in measured.SHIPPED}
    assert muscles == {"defreitas.csv": "thigh", "damas.csv": "vastus lateralis", "seynnes.csv": "quadriceps",
                       "narici.csv": "quadriceps", "ogasawara.csv": "triceps brachii",
                       "ogasawara-continuous.csv": "triceps brachii"}
    assert all(measured.read(ROOT / "data" / name).measure for name in measured.SHIPPED)


def test_the_ogasawara_course_is_its_abstracts_phase_changes_on_its_schedule():
    """Issue 35 item 4: a training (6 weeks), detraining (3), retraining (6) course. The files
    compose the abstract's per-phase changes, each relative to its phase's start."""
    week = protocols.WEEK
    rest = protocols.load(ROOT / "data" / "ogasawara.toml")
    starts = np.array([s.start for s in rest.sessions])
    assert len(starts) == 36 and rest.end == 15 * week
    assert not np.any((starts >= 6 * week) & (starts < 9 * week))  # weeks 7-9 without a session
    assert [int(np.sum((starts >= w * week) & (starts < (w + 1) * week))) for w in (0, 5, 9, 14)] == [3] * 4
    continuous = protocols.load(ROOT / "data" / "ogasawara-continuous.toml")
    assert len(continuous.sessions) == 45 and continuous.end == rest.end
    data = measured.read(ROOT / "data" / "ogasawara.csv")
    np.testing.assert_allclose(data.t, [6 * week, 9 * week, 15 * week])
    np.testing.assert_allclose(data.csa_ratio, [1.08, 1.08 * 0.97, 1.08 * 0.97 * 1.07], atol=5e-5)
    steady = measured.read(ROOT / "data" / "ogasawara-continuous.csv")
    np.testing.assert_allclose(steady.csa_ratio, [1.09, 1.09 * 1.04, 1.09 * 1.04 * 1.02], atol=5e-5)
    assert measured.of_protocol(rest, "idealized").label == "Ogasawara et al. 2010"
    assert measured.of_protocol(rest, "TA_VHF_Left") is None  # a triceps is compared on generic shapes only


@pytest.mark.parametrize("geometry, compared", [
    ("idealized", True), ("cylinder", True),  # generic shapes, as the paper's idealized muscle
    ("BFLH_VHF_Left", True), ("RF_VHM_Right", True),  # thigh muscles
    ("TA_VHF_Left", False), ("GM_VHM_Left", False), ("my_mesh", False),  # below the knee, or unknown
])
def test_an_mwf_run_is_compared_with_defreitas_only_on_a_thigh_muscle(geometry, compared):
    from types import SimpleNamespace

    from hyper.runs import sequence

    mwf = protocols.from_option("mwf")[0]
    spec = SimpleNamespace(geometry=geometry, protocol=mwf)
    found = sequence.data_of(SimpleNamespace(data=None), spec)
    assert (found is not None and found.label == "DeFreitas et al. 2011") == compared
    asked = measured.read(ROOT / "data" / "defreitas.csv")  # --data: compared whatever the muscle
    assert sequence.data_of(SimpleNamespace(data=asked), spec) is asked


def test_a_quadriceps_head_is_not_compared_with_another():
    damas = protocols.load(ROOT / "data" / "damas.toml")  # vastus lateralis
    assert measured.of_protocol(damas, "VL_VHF_Left") is not None and measured.of_protocol(damas, "RF_VHF_Left") is None
    seynnes = protocols.load(ROOT / "data" / "seynnes.toml")  # quadriceps
    assert measured.of_protocol(seynnes, "VI_VHM_Left") is not None
    assert measured.of_protocol(seynnes, "ST_VHM_Left") is None


def test_data_metadata_are_read_and_checked(tmp_path, monkeypatch):
    (tmp_path / "m.csv").write_text("# digitized by hand\n# muscle: Quadriceps\n# measure: MRI\nweek,csa\n0,1\n1,x\n")
    with pytest.raises(InputError, match="line 6: not a number"):  # line numbers count the metadata
        measured.read(tmp_path / "m.csv")
    (tmp_path / "m.csv").write_text("# muscle: Quadriceps\n# measure: MRI\nweek,csa\n0,1\n1,1.1\n")
    read = measured.read(tmp_path / "m.csv")
    assert (read.muscle, read.measure) == ("quadriceps", "MRI")
    (tmp_path / "m.csv").write_text("# muscle: biceps\nweek,csa\n0,1\n1,1.1\n")
    with pytest.raises(InputError, match="unknown muscle 'biceps'"):
        measured.read(tmp_path / "m.csv")
    monkeypatch.setattr(measured, "DATA_DIR", tmp_path)  # a shipped file must say both
    (tmp_path / "damas.csv").write_text("# muscle: vastus lateralis\nweek,csa\n0,1\n3,1.03\n")
    with pytest.raises(InputError, match="must say its measure"):
        measured.read(tmp_path / "damas.csv")


@pytest.mark.parametrize("text, message", [
    ("week,csa,csa_change_percent\n0,1,0\n1,2,3\n", "not both"),
    ("day,csa_change_percent\n0,0\n1,-100\n", r"> -100 %"),
    ("week,area\n0,1\n1,2\n", "missing column 'csa'"),
])
def test_bad_data_files(tmp_path, text, message):
    (tmp_path / "d.csv").write_text(text)
    with pytest.raises(InputError, match=message):
        measured.read(tmp_path / "d.csv")


def test_grow_refuses_data_beyond_the_run(tmp_path, capsys):
    (tmp_path / "d.csv").write_text("week,csa\n0,1\n20,1.1\n")
    assert grow.main(["--geometry", "cylinder", "--protocol", "weekly", "--data", str(tmp_path / "d.csv"),
                      "--output", str(tmp_path / "out")]) == cli.EXIT_INPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.search(r"--data .*d.csv: measured up to 3360 h, beyond the end of protocol weekly",
                                       err[0]), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.csv"]


GOOD_STUDY = 'geometries = ["cylinder"]\nprotocols = ["weekly"]\n'


@pytest.mark.parametrize("text, message", [
    (GOOD_STUDY + "[data]\n", r"data.file: expected the path of a CSV file"),
    (GOOD_STUDY + '[data]\nfile = "none.csv"\n', r"data.file: .*none.csv: no such file"),
    (GOOD_STUDY + '[data]\nfile = "d.csv"\nweight = 2\n', r"data: unknown key\(s\) weight; known: file"),
    (GOOD_STUDY + 'data = "d.csv"\n', r"data: expected a table \(\[data\]\)"),
    (GOOD_STUDY + '[data]\nfile = "long.csv"\n', r"data.file .*long.csv: measured up to 3360 h, beyond the end"),
    (GOOD_STUDY + '[data]\nfile = "bad.csv"\n', r"data.file: .*bad.csv: missing column 'csa'"),
    (GOOD_STUDY + "[output]\nsnapshot_every = 0\n", r"output.snapshot_every: expected a finite number of hours > 0"),
])
def test_study_data_and_snapshots_are_checked(tmp_path, capsys, monkeypatch, text, message):
    (tmp_path / "d.csv").write_text("week,csa\n0,1\n8,1.1\n")
    (tmp_path / "long.csv").write_text("week,csa\n0,1\n20,1.1\n")
    (tmp_path / "bad.csv").write_text("week,area\n0,1\n8,1.1\n")
    (tmp_path / "s.toml").write_text(text)
    monkeypatch.chdir(tmp_path)
    before = sorted(tmp_path.rglob("*"))
    assert study_job.main([str(tmp_path / "s.toml"), "--output", str(tmp_path / "out")]) == cli.EXIT_INPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.search(message, err[0]), err
    assert sorted(tmp_path.rglob("*")) == before


def test_study_data_file_and_option(tmp_path):
    (tmp_path / "d.csv").write_text("week,csa\n0,1\n8,1.1\n")
    (tmp_path / "e.csv").write_text("day,csa_change_percent\n0,0\n7,1\n")
    path = tmp_path / "s.toml"
    path.write_text(GOOD_STUDY + '[data]\nfile = "d.csv"\n[output]\nsnapshot_every = 168\n')
    s = study.load(path)
    assert s.data.path == tmp_path / "d.csv" and s.data.csa_ratio == pytest.approx([1.1])
    assert s.output.snapshot_every == 168.0
    assert study.load(path, data_path=tmp_path / "e.csv").data.t == pytest.approx([168.0])  # --data wins
    assert study.load(tmp_path / "s.toml", {"snapshot_every": ("--snapshot-every", 6.0)}).output.snapshot_every == 6.0
    path.write_text(GOOD_STUDY)
    assert study.load(path).data is None


# ------------------------------------------------------------------------- progress


class Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


class Lines(log.logging.Handler):
    def __init__(self):
        super().__init__()
        self.lines = []

    def emit(self, record):
        self.lines.append(record.getMessage())


def count_lines(monkeypatch, every=None, seconds=3600, step=1.0) -> int:
    """Progress lines of a job of ``seconds`` that reports every ``step`` s (a fake clock)."""
    clock = Clock()
    monkeypatch.setattr(log.time, "perf_counter", clock)
    logger = log.logging.getLogger("hyper")
    lines = Lines()
    logger.addHandler(lines)
    monkeypatch.setattr(logger, "level", log.logging.INFO)
    try:
        progress = log.Progress(None, seconds, "job", **({} if every is None else {"every": every}))
        while clock.now < seconds:
            clock.now += step
            progress.update(clock.now, force=clock.now >= seconds)
    finally:
        logger.removeHandler(lines)
    return len(lines.lines)


def test_an_hour_long_run_writes_about_60_progress_lines(monkeypatch):
    # the first at 1 s, then every 60 s (61 s … 3541 s), and the last, forced, at 3600 s
    assert count_lines(monkeypatch) == 61
    assert count_lines(monkeypatch, every=600.0) == 7
    assert count_lines(monkeypatch, every=1.0) == 3600


@pytest.mark.parametrize("job, base", [
    ("grow", ["--geometry", "cylinder"]), ("cohort", ["--geometries", "cylinder"]),
    ("ensemble", ["--geometry", "cylinder"]), ("sobol", []), ("study", ["s.toml"]),
])
def test_progress_every_is_checked_on_every_long_job(tmp_path, capsys, monkeypatch, job, base):
    import importlib

    monkeypatch.chdir(tmp_path)
    main = importlib.import_module(f"hyper.{job}").main
    for bad, shown in (("0", "0"), ("nan", "nan"), ("soon", "'soon'")):
        assert main([*base, "--progress-every", bad, "--output", str(tmp_path / "out")]) == cli.EXIT_INPUT
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"--progress-every: expected a {'finite ' if bad != 'soon' else ''}number of " \
                                  f"seconds" in err[0] and shown in err[0], err
    assert not (tmp_path / "out").exists()


def test_quiet_grow_prints_nothing(grown, tmp_path, capfd):
    d = grown.parent
    assert grow.main(["--geometry", "cylinder", "--protocol", str(d / "short.toml"), "--params",
                      str(d / "growing.toml"), "--growth-dt", "48", "--output", str(tmp_path / "q.h5"),
                      "--quiet"]) == 0
    out, err = capfd.readouterr()
    assert out == "" and err == ""
    assert os.path.getsize(tmp_path / "q.h5") > 0


# ------------------------------------------------------------------------- two ranks


def by_position(points: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Point values in the order of their coordinates (the ranks number points each their way)."""
    return values[np.lexsort(points.T[::-1])]


@pytest.mark.mpi
def test_mpi_fields_on_two_ranks_equal_the_serial_ones(tmp_path):
    comm = MPI.COMM_WORLD
    assert comm.size == 2
    d = Path(comm.bcast(str(tmp_path) if comm.rank == 0 else None, root=0))
    if comm.rank == 0:
        (d / "short.toml").write_text(PROTOCOL)
        (d / "growing.toml").write_text("thetaM = 0.46\n")
    comm.barrier()
    options = ["--geometry", "cylinder", "--protocol", str(d / "short.toml"), "--params", str(d / "growing.toml"),
               "--growth-dt", "8", "--snapshot-every", "24", "--quiet"]
    assert grow.main([*options, "--output", str(d / "two.h5")]) == 0
    if comm.rank == 0:
        assert grow.main([*options, "--output", str(d / "one.h5")], comm=MPI.COMM_SELF) == 0
        p1, c1, one = read_fields(d / "one_fields.xdmf")
        p2, c2, two = read_fields(d / "two_fields.xdmf")
        assert p1.shape == p2.shape and len(c1[0].data) == len(c2[0].data)
        assert [t for t, _, _ in one] == [t for t, _, _ in two] and len(one) == 5
        for (_, pd1, cd1), (_, pd2, cd2) in zip(one, two):
            assert sorted(pd2) == ["a0", "u"] and sorted(cd2) == ["detGbar"]
            for name in ("u", "a0"):
                np.testing.assert_allclose(by_position(p2, pd2[name]), by_position(p1, pd1[name]), rtol=0,
                                           atol=1e-9 * max(1e-30, np.abs(pd1[name]).max()))
            np.testing.assert_allclose(np.sort(cd2["detGbar"][0].ravel()), np.sort(cd1["detGbar"][0].ravel()),
                                       rtol=1e-10)
    comm.barrier()
