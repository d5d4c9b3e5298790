"""Restart and failure handling of `python -m hyper.grow` (issue 8).

A short coupled run on the cylinder (two sessions, 96 h, Δtg = 8 h: 14 growth steps)
is killed midway, by SIGKILL and by SIGTERM, and run again with the same command: its
CSA and volume series equal those of an uninterrupted run to 1e-12 (in fact bit for
bit), also when 2 ranks resume what 1 rank wrote (1e-8). A Newton solve limited to
too few iterations makes steps cut in halves; allowed no cut, the run stops with the
state of its last step saved and the reason recorded, and resumes from there.
"""

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from hyper.commands import cli, grow
from hyper.core import io
from hyper.runs import checkpoint as ckpt
from hyper.runs import driver, locks, runspec
from hyper.runs.status import read_status

ROOT = Path(__file__).resolve().parents[1]
PYTHON = sys.executable
MPIRUN = str(Path(PYTHON).parent / "mpirun")

PROTOCOL = """
name = "short"
end = 96.0
[[session]]
start = 0.0
duration = 1.0
intensity = 0.8
[[session]]
start = 48.0
duration = 1.0
intensity = 0.8
"""
STEPS = 14  # growth steps of the short protocol at Δtg = 8 h


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("inputs")
    (d / "short.toml").write_text(PROTOCOL)
    # mTOR starts just above its threshold, so the muscle grows from the first hour.
    (d / "growing.toml").write_text("thetaM = 0.46\n")
    return d


def command(inputs, output, *extra):
    return ["--geometry", "cylinder", "--protocol", str(inputs / "short.toml"),
            "--params", str(inputs / "growing.toml"), "--growth-dt", "8", "--snapshot-every", "4",
            "--output", str(output), *extra]


def env():
    return {**os.environ, "OMP_NUM_THREADS": "1"}


@pytest.fixture(scope="module")
def reference(inputs, tmp_path_factory):
    """The uninterrupted run (its own checkpoints every 5 steps change nothing)."""
    out = tmp_path_factory.mktemp("reference") / "run.h5"
    assert grow.main(command(inputs, out, "--checkpoint-every", "5")) == 0
    return out


def start(inputs, output, *extra):
    return subprocess.Popen([PYTHON, "-m", "hyper.grow", *command(inputs, output, *extra)], cwd=ROOT, env=env(),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def wait_for(path: Path, proc, timeout=120.0) -> None:
    end = time.monotonic() + timeout
    while not path.exists():
        assert proc.poll() is None, f"the run ended before {path} appeared:\n{proc.stdout.read()}"
        assert time.monotonic() < end, f"no {path} after {timeout} s"
        time.sleep(0.01)


def same_series(a: Path, b: Path, rtol: float) -> None:
    sa, sb = io.read_series(a), io.read_series(b)
    assert len(sa["t"]) == len(sb["t"]) == STEPS + 1
    np.testing.assert_array_equal(sa["t"], sb["t"])
    for name in ("csa_ratio", "volume_ratio", "kM", "N"):
        np.testing.assert_allclose(sb[name], sa[name], rtol=rtol, atol=0, err_msg=name)


def fields(path: Path) -> dict:
    import h5py

    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def attrs(path: Path) -> dict:
    with h5py.File(path, "r") as f:
        return dict(f.attrs)


@pytest.fixture(scope="module")
def killed(inputs, tmp_path_factory):
    """A run killed by SIGKILL once its first checkpoint (step 3) exists, and a copy of
    that checkpoint for the tests that resume it elsewhere."""
    out = tmp_path_factory.mktemp("killed") / "run.h5"
    proc = start(inputs, out, "--checkpoint-every", "3")
    try:
        wait_for(runspec.Outputs(out).checkpoint, proc)
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(60) == -signal.SIGKILL
    finally:
        proc.kill()
        proc.wait()
    assert not out.exists()
    pristine = tmp_path_factory.mktemp("pristine") / "one_rank.ckpt.h5"
    shutil.copy(runspec.Outputs(out).checkpoint, pristine)
    return out, pristine


def test_sigkill_then_rerun_continues_bit_for_bit(inputs, reference, killed):
    out, _ = killed
    saved = attrs(runspec.Outputs(out).checkpoint)
    assert saved["step"] == 3 and saved["status"] == "running" and saved["ranks"] == 1 and saved["complete"]

    assert grow.main(command(inputs, out, "--checkpoint-every", "3")) == 0
    same_series(reference, out, rtol=1e-12)
    np.testing.assert_array_equal(io.read_series(out)["csa_ratio"], io.read_series(reference)["csa_ratio"])
    # the resumed run's XDMF holds every snapshot, the same as the uninterrupted run's
    ref_fields = fields(runspec.Outputs(reference).fields.with_suffix(".h5"))
    new_fields = fields(runspec.Outputs(out).fields.with_suffix(".h5"))
    assert sorted(ref_fields) == sorted(new_fields) and len(ref_fields) > 6
    for name in ref_fields:
        np.testing.assert_array_equal(new_fields[name], ref_fields[name])
    # what the kill left (checkpoint, stale lock file, XDMF staging folder) is gone
    assert sorted(p.name for p in out.parent.iterdir()) == ["run.h5", "run.png", "run_fields.h5", "run_fields.xdmf"]


def test_sigterm_saves_at_the_next_step_boundary_and_exits_143(inputs, reference, tmp_path):
    out = tmp_path / "run.h5"
    proc = start(inputs, out, "--checkpoint-every", "3")
    try:
        wait_for(runspec.Outputs(out).checkpoint, proc)
        proc.send_signal(signal.SIGTERM)
        log = proc.communicate(timeout=120)[0]
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == cli.EXIT_TERMINATED == 143, log
    status = read_status(runspec.Outputs(out).status)
    assert status["state"] == "interrupted" and status["reason"] == "SIGTERM"
    with h5py.File(runspec.Outputs(out).checkpoint, "r") as f:
        assert f.attrs["status"] == "interrupted" and f.attrs["complete"]
        assert f.attrs["step"] == status["step"] > 3  # after the periodic checkpoint at step 3
        assert len(f["series/t"]) == status["step"] + 1
    assert not out.exists() and not runspec.Outputs(out).fields.exists()

    assert grow.main(command(inputs, out, "--checkpoint-every", "3")) == 0
    same_series(reference, out, rtol=1e-12)
    assert not runspec.Outputs(out).status.exists() and not runspec.Outputs(out).checkpoint.exists()
    assert attrs(out)["segments"] == 2


@pytest.mark.skipif(not Path(MPIRUN).exists(), reason="needs the venv's mpirun")
def test_two_ranks_resume_what_one_rank_wrote(inputs, reference, killed, tmp_path):
    out = tmp_path / "run.h5"
    shutil.copy(killed[1], runspec.Outputs(out).checkpoint)
    result = subprocess.run([MPIRUN, "-n", "2", PYTHON, "-m", "hyper.grow", *command(inputs, out)],
                            cwd=ROOT, env=env(), capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "at step 3" in result.stdout and "written on 1 rank(s)" in result.stdout
    same_series(reference, out, rtol=1e-8)
    assert attrs(out)["ranks"] == 2


def test_failed_newton_solves_cut_the_step(inputs, reference, tmp_path):
    """Two Newton iterations are not enough for a 24 h step: it is cut. Uniform growth of
    the cylinder with axial fibres is stress-free and exact for any step, so the cut run
    must land on the uncut Δtg = 8 h reference (whose times include these)."""
    out = tmp_path / "cut.h5"
    assert grow.main(command(inputs, out, "--growth-dt", "24", "--petsc-option", "snes_max_it=2")) == 0
    s, ref = io.read_series(out), io.read_series(reference)
    assert s["halvings"].max() >= 1 and ref["halvings"].max() == 0
    assert s["newton_iterations"].max() <= 8  # at most two per (sub)solve
    at = np.searchsorted(ref["t"], s["t"])
    np.testing.assert_array_equal(ref["t"][at], s["t"])
    for name in ("csa_ratio", "volume_ratio"):
        np.testing.assert_allclose(s[name], ref[name][at], rtol=1e-8)


def test_unrecoverable_failure_saves_the_last_step_and_the_reason(inputs, tmp_path, capsys):
    out = tmp_path / "run.h5"
    failing = command(inputs, out, "--growth-dt", "24", "--petsc-option", "snes_max_it=2", "--max-halvings", "0")
    assert grow.main(failing) == cli.EXIT_FAILED == 3
    err = capsys.readouterr().err
    assert "Newton did not converge" in err and "run.status.json" in err
    status = read_status(runspec.Outputs(out).status)
    assert status["state"] == "failed"
    # step 1 is the first session (0-1 h), step 2 the first half of the rest after it
    assert status["failed_step"] == 2 and status["from_h"] == 1.0 and status["to_h"] == 24.5
    assert "DIVERGED_MAX_IT" in status["reason"]
    assert status["settings"]["growth_dt"] == 24.0 and status["petsc_options"] == {"snes_max_it": "2"}
    saved = attrs(runspec.Outputs(out).checkpoint)
    assert saved["status"] == "failed" and saved["step"] == 1 and saved["t"] == 1.0
    assert not out.exists() and not runspec.Outputs(out).fields.exists()
    assert not Path(str(out) + ".lock").exists()

    # Allowed to cut the step, the same run goes on from the saved step 1.
    assert grow.main(failing[:-1] + ["4"]) == 0
    assert "resuming" in capsys.readouterr().out
    s = io.read_series(out)
    assert s["halvings"][2] >= 1
    assert not runspec.Outputs(out).status.exists() and not runspec.Outputs(out).checkpoint.exists()


def test_a_full_disk_stops_the_run_in_one_line_and_keeps_the_previous_checkpoint(inputs, tmp_path, capsys,
                                                                                   monkeypatch):
    out = tmp_path / "run.h5"
    real, calls = ckpt.write, []

    def fills_the_disk(comm, path, *args):
        calls.append(path)
        if len(calls) > 1:  # raised on every rank, as checkpoint.write raises its errors
            raise OSError(f"{path}: cannot write the checkpoint: [Errno 28] No space left on device")
        real(comm, path, *args)

    monkeypatch.setattr(ckpt, "write", fills_the_disk)
    assert grow.main(command(inputs, out, "--checkpoint-every", "3")) == cli.EXIT_FAILED
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and "No space left on device; the previous checkpoint is kept" in lines[0], lines
    status = read_status(runspec.Outputs(out).status)
    assert status["state"] == "failed" and status["step"] == 6 and "No space left" in status["reason"]
    assert attrs(runspec.Outputs(out).checkpoint)["step"] == 3  # the one written before the disk filled
    assert not out.exists() and not runspec.Outputs(out).fields.exists()

    monkeypatch.setattr(ckpt, "write", real)  # room again: the same command finishes from step 3
    assert grow.main(command(inputs, out, "--checkpoint-every", "3")) == 0
    assert "resuming" in capsys.readouterr().out and io.is_complete(out)


def test_a_second_run_on_the_same_output_stops_at_once(inputs, tmp_path, capsys):
    out = tmp_path / "results" / "run.h5"
    lock = locks.OutputLock(out)
    lock.acquire()
    try:
        assert grow.main(command(inputs, out)) == cli.EXIT_BUSY == 4
    finally:
        lock.release()
    err = capsys.readouterr().err
    assert "another run is writing this output" in err and f"pid {os.getpid()}" in err
    assert not out.parent.exists()  # nothing left: the folder made for the lock goes with it


def test_checkpoint_of_other_settings_is_refused(inputs, killed, tmp_path, capsys):
    out = tmp_path / "run.h5"
    shutil.copy(killed[1], runspec.Outputs(out).checkpoint)
    before = sorted((p.name, p.stat().st_mtime_ns) for p in tmp_path.iterdir())
    assert grow.main(command(inputs, out, "--growth-dt", "12")) == 2
    assert "belongs to another run" in capsys.readouterr().err
    assert sorted((p.name, p.stat().st_mtime_ns) for p in tmp_path.iterdir()) == before
    # the same run with more cuts allowed may resume it (checked without running)
    grow.plan(MPI.COMM_WORLD, command(inputs, out, "--max-halvings", "6"))


def test_grow_array_script_stops_requeues_and_resumes(inputs, tmp_path):
    """The Slurm array script with stand-ins that behave as Slurm's (srun runs the command
    here and kills it on a TERM of its own; scancel --signal signals the task; scontrol
    records): Slurm's warning (USR1 to the batch shell) stops the run at a step boundary with
    its checkpoint, the task is requeued, and the requeued script resumes the run to the end."""
    from hyper.commands import slurm

    fake = tmp_path / "fake"
    fake.mkdir()
    (fake / "srun").write_text('#!/bin/bash\nshift\n"$@" &\nTASK=$!\necho "$TASK" > "$FAKE/task.pid"\n'
                               "trap 'kill -KILL \"$TASK\"; exit 137' TERM\nwait \"$TASK\"\n")  # drops --mpi=...
    (fake / "scancel").write_text('#!/bin/bash\nkill -"${1#--signal=}" "$(cat "$FAKE/task.pid")"\n')
    (fake / "scontrol").write_text('#!/bin/bash\necho "$@" >> "$FAKE/scontrol.args"\n')
    for tool in ("srun", "scancel", "scontrol"):
        (fake / tool).chmod(0o755)
    script = tmp_path / "array.sbatch"
    assert slurm.main(["grow-array", "-o", str(script), "--workdir", str(tmp_path), "--geometries", "cylinder",
                       "--protocols", "weekly", "--output", "results",
                       f"--args=--params {inputs / 'growing.toml'} --growth-dt 168 --checkpoint-every 100"]) == 0
    env = {**os.environ, "PATH": f"{fake}:{os.environ['PATH']}", "FAKE": str(fake), "OMP_NUM_THREADS": "1",
           "SLURM_JOB_ID": "4242", "SLURM_JOB_NODELIST": "node1", "SLURM_ARRAY_TASK_ID": "0"}
    env.pop("SLURM_RESTART_COUNT", None)
    result = tmp_path / "results" / "cylinder_weekly.h5"

    job = subprocess.Popen(["bash", str(script)], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, text=True)
    try:
        wait_for(Path(str(result) + ".lock"), job)  # inputs checked, TERM handler installed
        job.send_signal(signal.SIGUSR1)  # what --signal=B:USR1@WARN does before the time limit
        log = job.communicate(timeout=120)[0]
    finally:
        job.kill()
        job.wait()
    assert job.returncode == 143, log
    assert "stopped on request" in log and (fake / "scontrol.args").read_text() == "requeue 4242\n"
    assert runspec.Outputs(result).checkpoint.exists() and not result.exists()

    requeued = subprocess.run(["bash", str(script)], cwd=tmp_path, env={**env, "SLURM_RESTART_COUNT": "1"},
                              capture_output=True, text=True, timeout=300)
    assert requeued.returncode == 0, requeued.stdout + requeued.stderr
    assert "resuming from" in requeued.stdout
    s = io.read_series(result)
    assert attrs(result)["segments"] == 2 and s["t"][-1] == 9 * 168.0 and np.all(np.diff(s["t"]) > 0)
    assert s["csa_ratio"][-1] > 1.01
    assert not runspec.Outputs(result).checkpoint.exists()


# ----------------------------------------------------------------- heterogeneous state


def heterogeneous_model(comm):
    """The cylinder with a per-cell synthesis rate (a field over the mesh file's cells):
    growth, Ḡ, A and the stress then differ from cell to cell and point to point."""
    from hyper.fem import fibers
    from hyper.fem import geometry as geo
    from hyper.fem.coupled import GrowthSettings, build_model
    from hyper.model import protocols, signaling

    g = geo.load("cylinder", comm)
    original = np.asarray(g.mesh.topology.original_cell_index)[: g.mesh.topology.index_map(3).size_local]
    params = signaling.SignalingParams(thetaM=0.46, kM=0.01 * (1.0 + 0.5 * np.sin(original)))
    protocol = protocols.Protocol((protocols.Session(0.0, 1.0, 0.8),), end=25.0, name="one")  # 4 steps
    return build_model(g, fibers.fiber_field(g), protocol, params=params, settings=GrowthSettings(growth_dt=8.0))


def measures(model, until=None) -> list:
    out = []
    for r in model.run():
        out.append((r.t, r.csa_ratio, r.volume_ratio, *r.states))
        if r.step == until:
            break
    return out


def save_state(comm, model, path):
    state = model.state()
    ckpt.write(comm, path, state.original, state.per_cell, state.glob, series={}, attrs={"run_digest": "test"})


def resumed(comm, path) -> list:
    model = heterogeneous_model(comm)
    model.restore(ckpt.read(comm, path, "test", model.local_original_cells()))
    return measures(model)


def test_heterogeneous_state_resumes_bit_for_bit(tmp_path):
    comm = MPI.COMM_SELF
    reference = measures(heterogeneous_model(comm))
    model = heterogeneous_model(comm)
    first = measures(model, until=2)
    assert model.growth.Gbar.std(axis=(0, 1)).max() > 1e-4  # Ḡ differs between points
    save_state(comm, model, tmp_path / "state.h5")
    assert first + resumed(comm, tmp_path / "state.h5") == reference


@pytest.mark.mpi
def test_heterogeneous_state_of_one_rank_resumes_on_two(tmp_path_factory):
    world = MPI.COMM_WORLD
    assert world.size == 2
    reference = np.array(measures(heterogeneous_model(MPI.COMM_SELF)))
    path = Path(world.bcast(str(tmp_path_factory.mktemp("state") / "state.h5") if world.rank == 0 else None))
    if world.rank == 0:
        model = heterogeneous_model(MPI.COMM_SELF)
        first = measures(model, until=2)
        save_state(MPI.COMM_SELF, model, path)
    first = world.bcast(first if world.rank == 0 else None)
    both = np.array(first + resumed(world, path))
    np.testing.assert_array_equal(both[:, 0], reference[:, 0])
    np.testing.assert_allclose(both[:, 1:], reference[:, 1:], rtol=1e-8)


def test_lock_without_file_system_locks_is_reported_not_fatal(tmp_path, monkeypatch):
    import errno

    def no_locks(fd, operation):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(locks.fcntl, "flock", no_locks)
    with locks.locked([tmp_path / "a.h5", tmp_path / "b.h5"]) as unlocked:
        assert unlocked == [tmp_path / "a.h5.lock", tmp_path / "b.h5.lock"]
    assert list(tmp_path.iterdir()) == []


def test_iterative_linear_solver_run_lands_on_the_lu_run(inputs, reference, tmp_path):
    """--linear-solver iterative changes the cost, not the answer; the choice is recorded."""
    out = tmp_path / "iterative.h5"
    assert grow.main(command(inputs, out, "--linear-solver", "iterative")) == 0
    s, ref = io.read_series(out), io.read_series(reference)
    for name in ("csa_ratio", "volume_ratio"):
        np.testing.assert_allclose(s[name], ref[name], rtol=1e-10)
    with h5py.File(out) as f, h5py.File(reference) as g:
        assert f.attrs["linear_solver"] == "iterative" and g.attrs["linear_solver"] == "lu"
        assert f.attrs["unknowns"] == g.attrs["unknowns"] > 1000


def test_pmg_linear_solver_run_lands_on_the_lu_run(inputs, reference, tmp_path):
    """--linear-solver pmg: each kept-factor iteration a GMRES solve with the kept multigrid;
    the CSA and volume series within 1e-6 of the growth of LU's (the issue's tolerance)."""
    out = tmp_path / "pmg.h5"
    assert grow.main(command(inputs, out, "--linear-solver", "pmg")) == 0
    s, ref = io.read_series(out), io.read_series(reference)
    for name in ("csa_ratio", "volume_ratio"):
        growth = ref[name][-1] - 1.0
        assert growth > 5e-3
        assert np.max(np.abs(np.asarray(s[name]) - ref[name])) < 1e-6 * growth
    with h5py.File(out) as f:
        assert f.attrs["linear_solver"] == "pmg"


def test_a_pmg_run_killed_and_rerun_continues_bit_for_bit(inputs, tmp_path):
    """The multigrid is rebuilt on resume from the Newton matrix at the checkpoint's point,
    as the uninterrupted run built it: the same series to the last bit, on one rank."""
    whole = tmp_path / "whole.h5"
    assert grow.main(command(inputs, whole, "--linear-solver", "pmg")) == 0
    out = tmp_path / "run.h5"
    proc = start(inputs, out, "--linear-solver", "pmg", "--checkpoint-every", "3")
    try:
        wait_for(runspec.Outputs(out).checkpoint, proc)
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(60) == -signal.SIGKILL
    finally:
        proc.kill()
        proc.wait()
    assert attrs(runspec.Outputs(out).checkpoint)["step"] == 3
    assert grow.main(command(inputs, out, "--linear-solver", "pmg", "--checkpoint-every", "3")) == 0
    for name in ("csa_ratio", "volume_ratio", "newton_iterations"):
        np.testing.assert_array_equal(io.read_series(out)[name], io.read_series(whole)[name], err_msg=name)


def test_accuracy_takes_lu_while_it_fits_and_pmg_when_memory_is_short(inputs, tmp_path, monkeypatch):
    runs = {}
    for name, available in (("roomy", None), ("short", 1.0)):
        if available is not None:
            monkeypatch.setattr(driver, "available_memory_mb", lambda comm: available)  # MB
        out = tmp_path / f"{name}.h5"
        assert grow.main(command(inputs, out, "--accuracy", "1e-3")) == 0
        with h5py.File(out) as f:
            runs[name] = (f.attrs["linear_solver"], f.attrs["linear_solver_reason"])
            # the one fidelity record holds the steps and the solver it chose
            chosen = dict(f["fidelity"].attrs)
            assert (chosen["linear_solver"], chosen["linear_solver_reason"]) == runs[name]
            assert chosen["growth_dt"] > 0 and chosen["signaling_dt"] > 0 and chosen["accuracy"] == 1e-3
        runs[name] += (io.read_series(out)["csa_ratio"],)
    assert runs["roomy"][0] == "lu" and "MUMPS LU" in runs["roomy"][1]
    assert runs["short"][0] == "pmg" and "may not fit" in runs["short"][1]
    growth = runs["roomy"][2][-1] - 1.0  # pmg: GMRES to 1e-10, so the series agree to 1e-6 of the growth
    assert growth > 5e-3 and np.max(np.abs(runs["short"][2] - runs["roomy"][2])) < 1e-6 * growth
