"""The mechanisms of issue 37's third round, each tested as a mechanism and through the jobs:
one output check (`io.unwritable`, with the inputs a job declares to `cli.Parser`), one write
path (`io.atomic_path`: a full disk is `io.WriteFailed`, one ``error:`` line, exit 3, no half
file) and a lock per run file (a cohort's run locks its own RESULT.h5, as `hyper grow` does).
"""

from __future__ import annotations

import errno
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from hyper.commands import cli
from hyper.core import io
from hyper.runs import locks

ROOT = Path(__file__).resolve().parents[1]
DATA = str(ROOT / "data" / "defreitas.csv")


# ------------------------------------------------------------------ the output check


def test_an_existing_folder_must_itself_be_writable(tmp_path, monkeypatch):
    folder = tmp_path / "out"
    folder.mkdir()
    assert io.unwritable(folder, folder=True) is None
    real = os.access
    monkeypatch.setattr(io.os, "access", lambda p, mode: False if Path(p) == folder else real(p, mode))
    assert io.unwritable(folder, folder=True) == f"{folder}: the folder is not writable"
    assert io.unwritable(folder, folder=None) == f"{folder}: the folder is not writable"
    assert io.unwritable(folder / "new", folder=True) == f"{folder / 'new'}: {folder} is not writable"


def test_an_output_may_not_be_an_input_nor_a_replaced_folder_hold_one(tmp_path):
    source = tmp_path / "in" / "s.stl"
    source.parent.mkdir()
    source.write_text("x")
    assert "is an input of this job" in io.unwritable(source, folder=None, inputs=[source])
    link = tmp_path / "link.stl"
    link.symlink_to(source)  # the same file by another name
    assert "is an input of this job" in io.unwritable(link, folder=None, inputs=[source])
    assert io.unwritable(source.parent, folder=True, inputs=[source]) is None  # written into, not replaced
    assert "replacing the folder would delete it" in io.unwritable(source.parent, folder=True, inputs=[source],
                                                                   replaces=True)
    assert io.unwritable(tmp_path / "in" / "missing", folder=None, inputs=[tmp_path / "in" / "missing"]) is None


def test_the_parser_checks_every_output_against_the_inputs_it_was_told_of(tmp_path):
    source = tmp_path / "a.csv"
    source.write_text("x")
    p = cli.Parser("test")
    p.add_argument("--data", action="append", type=Path, reads=True)
    p.add_argument("--result", type=Path, reads=lambda r: [r, r.with_suffix(".xdmf")])
    p.add_argument("--output", type=cli.output(folder=False))
    (tmp_path / "r.xdmf").write_text("x")
    assert p.parse_args(["--data", str(source), "--output", str(tmp_path / "b.csv")]).output == tmp_path / "b.csv"
    with pytest.raises(cli.InputError, match=r"argument --output: .*a.csv: is an input of this job"):
        p.parse_args(["--data", str(tmp_path / "z.csv"), "--data", str(source), "--output", str(source)])
    with pytest.raises(cli.InputError, match=r"r.xdmf: is an input of this job"):
        p.parse_args(["--result", str(tmp_path / "r.h5"), "--output", str(tmp_path / "r.xdmf")])


# ------------------------------------------------------------------ the write path


@pytest.fixture
def full_disk(tmp_path, monkeypatch):
    """A folder on a full disk: a small tmpfs filled up where this process may mount one,
    else (saying so) every atomic write's fsync failing with ENOSPC."""
    folder = tmp_path / "full"
    folder.mkdir()
    mounted = os.geteuid() == 0 and subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(folder)], capture_output=True).returncode == 0
    if mounted:
        filler = folder / ".filler"
        with open(filler, "wb", buffering=0) as f:  # unbuffered: nothing left to flush at close
            try:
                while True:
                    f.write(b"\0" * 4096)
            except OSError as err:
                assert err.errno == errno.ENOSPC
    else:
        print("no tmpfs (not root, or mount refused): ENOSPC injected into io.atomic_path's fsync")

        def full(fd):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        monkeypatch.setattr(io.os, "fsync", full)
    yield folder
    if mounted and subprocess.run(["umount", str(folder)]).returncode != 0:
        subprocess.run(["umount", "-l", str(folder)], check=True)  # detached now, freed once nothing holds it
        pytest.fail(f"{folder}: still in use after the job (a file left open)")


def written(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.name != ".filler")


def test_a_full_disk_is_one_write_failed_line_and_leaves_no_half_file(full_disk):
    with pytest.raises(io.WriteFailed) as caught:
        with io.atomic_path(full_disk / "a.json") as tmp:
            tmp.write_text("{}" * 10_000)
    assert caught.value.errno == errno.ENOSPC and "\n" not in str(caught.value)
    assert str(caught.value).startswith(f"{full_disk / 'a.json'}: cannot write: No space left on device")
    with pytest.raises(io.WriteFailed) as caught:  # h5py's OSError, whose HDF5 text spans lines
        io.write_series(full_disk / "s.h5", {"t": np.zeros(100_000)})
    assert "\n" not in str(caught.value) and "s.h5: cannot write" in str(caught.value)
    assert written(full_disk) == []


def test_other_errors_pass_the_write_path_unchanged(tmp_path):
    with pytest.raises(KeyError):
        with io.atomic_path(tmp_path / "a.txt") as tmp:
            tmp.write_text("half")
            raise KeyError("not a disk fault")
    assert io.write_failed(tmp_path, OSError(errno.EACCES, "denied")) is None
    assert list(tmp_path.iterdir()) == []


# job -> its command, {out} the full disk's folder; small and fast: the write fails at once
WRITERS = {
    "slurm": ["slurm", "cohort", "-o", "{out}/cohort.sbatch"],
    "dose": ["dose", "--checks", "0", "--output", "{out}"],
    "calibrate": ["calibrate", "--data", DATA, "--protocol", "mwf", "--fit", "kM", "--no-check", "--output", "{out}"],
    "signaling": ["signaling", "--protocol", "mwf", "--output", "{out}/mwf.h5"],
    "meshstats": ["meshstats", "--geometries", "cylinder", "--output", "{out}/stats.csv"],
    # these take their output locks first: the lock file is their first write
    "grow": ["grow", "--geometry", "cylinder", "--protocol", "weekly", "--output", "{out}/g"],
    "contraction": ["contraction", "--geometry", "cylinder", "--steps", "1", "--output", "{out}/c.h5"],
    "cohort": ["cohort", "--geometries", "cylinder", "--protocols", "weekly", "--output", "{out}/co"],
    "ensemble": ["ensemble", "--geometry", "cylinder", "--protocol", "weekly", "--samples", "1", "--output", "{out}/e"],
    "sobol": ["sobol", "--samples", "8", "--output", "{out}/s"],
    "fibers": ["fibers", "--geometries", "cylinder", "--output", "{out}/f"],
    "reproduce": ["reproduce", "--cases", "signaling", "--output", "{out}/r"],
    "demo": ["demo", "--output", "{out}/d"],
    "study": ["study", str(ROOT / "studies" / "custom.toml"), "--output", "{out}/st"],
    "mesh": ["mesh", str(ROOT / "tests" / "data" / "TA_VHF_Right_coarse.stl"), "--output", "{out}/m"],
}


@pytest.mark.parametrize("job", sorted(WRITERS))
def test_every_writing_job_on_a_full_disk_exits_3_with_one_error_line_and_no_half_file(full_disk, capsys, job):
    assert cli.main([a.format(out=full_disk) for a in WRITERS[job]]) == cli.EXIT_FAILED
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "No space left on device" in lines[0], err
    assert written(full_disk) == []


def test_entry_reports_a_write_failed_anywhere_in_a_job_as_exit_3(capsys):
    def run(comm, args):
        raise io.WriteFailed(errno.EIO, "x.h5: cannot write: Input/output error;\nsecond line")

    main = cli.entry(lambda: cli.Parser("test"), run, world=False)
    assert main([]) == cli.EXIT_FAILED
    assert capsys.readouterr().err == "error: x.h5: cannot write: Input/output error; second line\n"


# ------------------------------------------------------------------ a lock per run file


def test_grow_on_a_run_of_a_running_cohort_stops_at_once(tmp_path, capsys):
    """The cohort holds its folder's lock and, inside the farm, its run's own lock
    (`hyper.analysis.cohort.run_cohort`'s work): grow on that run's file exits 4."""
    from hyper.analysis import cohort

    out = tmp_path / "cohort"
    run = cohort.Run("cylinder", cohort.protocols.resolve("mwf"))
    result = cohort.series_path(out, run)
    with locks.locked([out]), locks.locked([result]):
        status = cli.main(["grow", "--geometry", "cylinder", "--protocol", "mwf", "--output", str(result)])
    assert status == cli.EXIT_BUSY
    assert "another run is writing this output" in capsys.readouterr().err
    assert not result.exists() and not runs_files(out)


def runs_files(out: Path) -> list[Path]:
    return [p for p in out.rglob("*") if p.suffix in (".h5", ".json", ".xdmf")]


def test_a_cohort_run_takes_the_lock_of_its_own_result(tmp_path, monkeypatch):
    """A run of a cohort whose result file another run holds fails, with the other run's
    lock named, instead of sharing its checkpoint."""
    from mpi4py import MPI

    from hyper.analysis import cohort

    out = tmp_path / "cohort"
    run = cohort.Run("cylinder", cohort.protocols.resolve("mwf"))
    seen = []
    monkeypatch.setattr(cohort.driver, "execute", lambda *a, **k: seen.append(a) or (_ for _ in ()).throw(
        AssertionError("the run started although its file is held")))
    with locks.locked([cohort.series_path(out, run)]):
        [result] = cohort.run_cohort(MPI.COMM_WORLD, [run], out)
    assert result.status == "failed" and "another run is writing this output" in result.error and not seen


def test_an_xdmf_write_without_room_is_refused_before_hdf5_sees_it(tmp_path, monkeypatch):
    """DOLFINx's HDF5 aborts the process on a failed write; the room check refuses it first."""
    from dolfinx import fem
    from dolfinx import mesh as dmesh
    from mpi4py import MPI

    mesh = dmesh.create_unit_cube(MPI.COMM_WORLD, 2, 2, 2)
    u = fem.Function(fem.functionspace(mesh, ("Lagrange", 1, (3,))), name="u")
    disk = shutil.disk_usage(tmp_path)
    room = io.ROOM_FACTOR * MPI.COMM_WORLD.allreduce(u.x.array.nbytes + mesh.geometry.x.nbytes) + io.ROOM_SLACK
    monkeypatch.setattr(io.shutil, "disk_usage", lambda path: disk._replace(free=int(room) - 1))
    with pytest.raises(io.WriteFailed) as caught:
        with io.atomic_xdmf(MPI.COMM_WORLD, tmp_path / "f.xdmf") as xdmf:
            xdmf.write_function(u, 0.0)
    assert "f.xdmf: cannot write: No space left on device" in str(caught.value)
    assert list(tmp_path.iterdir()) == []
    monkeypatch.setattr(io.shutil, "disk_usage", lambda path: disk._replace(free=int(2 * room)))
    with io.atomic_xdmf(MPI.COMM_WORLD, tmp_path / "f.xdmf") as xdmf:
        xdmf.write_mesh(mesh)
        xdmf.write_function(u, 0.0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.h5", "f.xdmf"]


SHORT = "end = 48.0\n[[session]]\nstart = 10\nduration = 1\nintensity = 1.0\n"
# job -> its command, {p} a short protocol file, {s} a one-run study file of it, {out} the output
ONE_RUN = {
    "grow": ["grow", "--geometry", "cylinder", "--protocol", "{p}", "--growth-dt", "12", "--output", "{out}"],
    "study": ["study", "{s}", "--output", "{out}"],
}


@pytest.mark.parametrize("job", sorted(ONE_RUN))
def test_a_run_whose_fields_do_not_fit_exits_3_in_one_line(tmp_path, capsys, job):
    """A disk with room for the lock and the first writes, not for the fields: one line, exit 3,
    nothing left (before the room check: pages of HDF5-DIAG, then exit 134)."""
    folder = tmp_path / "small"
    folder.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=600k", "tmpfs", str(folder)],
                                           capture_output=True).returncode != 0:
        pytest.skip("needs a small tmpfs (root and mount)")
    try:
        (folder / ".filler").write_bytes(b"\0" * 540_000)
        protocol, study = tmp_path / "short.toml", tmp_path / "study.toml"
        protocol.write_text(SHORT)
        study.write_text('geometries = ["cylinder"]\n[[protocol]]\nname = "short"\n'
                         + SHORT.replace("[[session]]", "[[protocol.session]]") + "[numerics]\ngrowth_dt = 12\n")
        paths = {"p": protocol, "s": study, "out": folder / "out"}
        code = cli.main([a.format(**paths) for a in ONE_RUN[job]] + ["--quiet"])
        err = capsys.readouterr().err
        lines = [line for line in err.splitlines() if line.strip()]
        assert code == cli.EXIT_FAILED and len(lines) == 1 and "No space left on device" in lines[0], err
        assert "_fields.xdmf: cannot write" in lines[0]
        assert written(folder) == []
    finally:
        subprocess.run(["umount", str(folder)], check=True)
