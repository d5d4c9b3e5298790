"""A SIGTERM at any moment of a job ends it with exit status 143 (hyper.core.term).

The mechanism: every entry point (the ``python -m hyper.JOB`` shims, test_layout.py
checks each; `cli`, the ``hyper`` script's module, on import) calls `term.install` first,
which has PETSc start without its signal handler, ends a job TERMed outside a run at once
with 143, and has a thread of its own take every SIGTERM (blocked in all the others), out
of the reach of METIS, which takes SIGTERM over while it orders MUMPS's factorisation; a
run's own handler (`driver.StopOnTerm`) stops it at a step boundary with 143. Here: the
mechanism alone, TERMs throughout METIS's orderings, then real jobs TERMed at moments of
their start-up (imports, PETSc's start, the mesh, the first steps) through both entry
points and on two ranks.

The moments count from when the process catches SIGTERM (/proc/PID/status): before that
the interpreter itself is starting (some 50 ms) and the TERM ends it as Python's default
does, by the signal, which a shell and srun report as 143 too.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
import types
from pathlib import Path

import pytest

from hyper.commands import cli
from hyper.core import term

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}
NOTE = re.compile(r"hyper: stopped by SIGTERM outside a run's growth steps( \(rank \d of 2: ending them all\))?; "
                  r"exit status 143: nothing unfinished is kept, run the same command again")
# a run of about 15 s (growth steps of 2 h), so that every moment below is before its end
GROW = ["grow", "--geometry", "cylinder", "--protocol", "weekly", "--growth-dt", "2", "--quiet"]
# `hyper grow` is the console script: cli.main with the command line
ENTRIES = {"python -m hyper.grow": ["-m", "hyper.grow", *GROW[1:]],
           "hyper grow": ["-c", "import sys; from hyper.commands import cli; sys.exit(cli.main())", *GROW]}


def catches_term(pid: int) -> bool:
    """Whether process ``pid`` has a handler of its own for SIGTERM."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    caught = int(re.search(r"^SigCgt:\s*([0-9a-f]+)$", status, re.MULTILINE).group(1), 16)
    return bool(caught >> (signal.SIGTERM - 1) & 1)


def descendants(pid: int) -> list[int]:
    try:
        children = [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []
    return children + [d for c in children for d in descendants(c)]


def command_line(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:  # ended meanwhile
        return b""


def term_at(command: list[str], after_s: float, ready, cwd: Path) -> subprocess.CompletedProcess:
    """Run ``command``, send it SIGTERM ``after_s`` seconds after its start, or as soon as
    ``ready(pid)`` once that is later; wait for it to end."""
    job = subprocess.Popen(command, cwd=cwd, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        start, end = time.monotonic(), time.monotonic() + 60
        while not ready(job.pid):
            assert job.poll() is None, f"ended before its TERM handler was installed: {job.communicate()}"
            assert time.monotonic() < end, "no TERM handler after 60 s"
            time.sleep(0.005)
        time.sleep(max(0.0, start + after_s - time.monotonic()))
        assert job.poll() is None, f"ended before the TERM at {after_s} s: {job.communicate()}"
        job.send_signal(signal.SIGTERM)
        out, err = job.communicate(timeout=90)
    finally:
        job.kill()
    return subprocess.CompletedProcess(command, job.returncode, out, err)


def assert_stopped(done: subprocess.CompletedProcess, when: str) -> None:
    """Exit status 143; on stderr no PETSc abort and no traceback, at most the note."""
    assert done.returncode == cli.EXIT_TERMINATED, f"{when}: exit status {done.returncode}\n{done.stderr}"
    assert "PETSC ERROR" not in done.stderr and "Traceback" not in done.stderr, f"{when}:\n{done.stderr}"
    # MPICH reports the abort that ends the other ranks in a line of its own
    lines = [line for line in done.stderr.splitlines() if not line.startswith("Abort(143)")]
    assert all(NOTE.fullmatch(line) for line in lines), f"{when}: stderr\n{done.stderr}"


# ------------------------------------------------------------------------- the mechanism


def test_petsc_is_kept_off_signals_alongside_other_options(monkeypatch):
    monkeypatch.setenv("PETSC_OPTIONS", "-log_view")
    term.keep_petsc_off_signals()
    term.keep_petsc_off_signals()
    assert os.environ["PETSC_OPTIONS"] == "-log_view -no_signal_handler"
    monkeypatch.delenv("PETSC_OPTIONS")
    term.keep_petsc_off_signals()
    assert os.environ["PETSC_OPTIONS"] == "-no_signal_handler"


def test_a_term_after_petsc_started_ends_in_143_not_petscs_abort():
    """What the installed handler does with PETSc started after it (as DOLFINx starts it):
    without -no_signal_handler, PETSc's handler prints 'PETSC ERROR: Caught signal' and
    exits with 15. A handler installed before term.install stays."""
    code = ("import os, signal, time\nfrom hyper.core import term\nterm.install()\n"
            "import dolfinx_solver\nfrom petsc4py import PETSc\n"
            "os.kill(os.getpid(), signal.SIGTERM)\ntime.sleep(30)\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env={k: v for k, v in ENV.items()
                          if k != "PETSC_OPTIONS"}, capture_output=True, text=True, timeout=120)
    assert_stopped(done, "after PETSc started")
    assert NOTE.fullmatch(done.stderr.strip()), done.stderr
    # the handler runs in the main thread once term's thread has taken the TERM: soon, not at once
    kept = ("import os, signal, time\ntaken = []\n"
            "signal.signal(signal.SIGTERM, lambda *a: taken.append(print('mine')))\n"
            "from hyper.core import term\nterm.install()\nos.kill(os.getpid(), signal.SIGTERM)\n"
            "while not taken:\n    time.sleep(0.01)\n")
    done = subprocess.run([sys.executable, "-c", kept], cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=60)
    assert (done.returncode, done.stdout) == (0, "mine\n"), done.stderr


def test_no_native_handler_sees_a_term_every_thread_blocks_it_but_terms_own():
    """METIS (MUMPS's ordering) takes SIGTERM over with signal() for each call and longjmps
    out of itself on one: the TERM was lost, or MUMPS crashed on an ordering never made.
    Here a native library's SIG_IGN stands for METIS's handler: the TERM still ends the job
    with 143, since term's thread takes it with sigwait (unblocked in it only while it
    waits). A thread started after install (as MPI's, OpenMP's and BLAS's are) blocks
    SIGTERM; a child started within term.spawning does not (one started outside would
    ignore a TERM: mpirun does)."""
    code = """import ctypes, os, signal, subprocess, threading, time
from hyper.core import term
term.install()
later = threading.Thread(target=time.sleep, args=(30,), daemon=True)
later.start()
def blocks(tid):
    status = open(f"/proc/self/task/{tid}/status").read()
    return int(status.split("SigBlk:")[1].split()[0], 16) >> (signal.SIGTERM - 1) & 1
def child_blocks():
    status = subprocess.run(["cat", "/proc/self/status"], capture_output=True, text=True).stdout
    return int(status.split("SigBlk:")[1].split()[0], 16) >> (signal.SIGTERM - 1) & 1
outside = child_blocks()
with term.spawning():
    within = child_blocks()
tids = sorted(int(t) for t in os.listdir("/proc/self/task"))
print(len(tids), blocks(os.getpid()), blocks(later.native_id), blocks(term._taker.native_id), outside, within,
      blocks(os.getpid()), flush=True)
ctypes.CDLL(None).signal(signal.SIGTERM, ctypes.c_void_p(1))  # SIG_IGN, as a library sets its own
os.kill(os.getpid(), signal.SIGTERM)
time.sleep(30)
"""
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=120)
    # 3 threads: main and the later one block SIGTERM, term's waits for it (sigwait unblocks it
    # meanwhile); a child started outside spawning blocks it, one within does not; main still does
    assert done.stdout.split() == ["3", "1", "1", "0", "1", "0", "1"], done.stderr
    assert_stopped(done, "a TERM with a library's own disposition for SIGTERM")
    assert NOTE.fullmatch(done.stderr.strip()), done.stderr


def test_terms_throughout_mumps_factorisations_with_metis_are_taken_not_crashes():
    """The defect itself: TERMs sent throughout the symbolic factorisations of MUMPS with
    METIS's ordering (as in the first solve of every run) reach the run's handler, and
    every solve is right; before, one landing inside METIS ended it by SIGSEGV (exit -11)
    or was lost. Whether one lands there depends on the timing; that none does harm, not."""
    code = """import signal, sys
from hyper.core import term
term.install()
import dolfinx_solver
from petsc4py import PETSc

taken = []
signal.signal(signal.SIGTERM, lambda *a: taken.append(1))  # as driver.StopOnTerm's flag
n = 22  # the 7-point Laplacian on an n³ grid
A = PETSc.Mat().createAIJ([n**3, n**3], nnz=7)
for i in range(n):
    for j in range(n):
        for k in range(n):
            row = (i * n + j) * n + k
            A.setValue(row, row, 6.0)
            for di, dj, dk in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)):
                if 0 <= i + di < n and 0 <= j + dj < n and 0 <= k + dk < n:
                    A.setValue(row, ((i + di) * n + j + dj) * n + k + dk, -1.0)
A.assemble()
x, b = A.createVecs()
b.set(1.0)
PETSc.Options()["mat_mumps_icntl_7"] = 5  # METIS's ordering
print("ready", flush=True)
worst = 0.0
for _ in range(30):
    ksp = PETSc.KSP().create()
    ksp.setOperators(A)
    ksp.setType("preonly")
    ksp.getPC().setType("lu")
    ksp.getPC().setFactorSolverType("mumps")
    ksp.getPC().setFromOptions()
    ksp.setUp()
    ksp.solve(b, x)
    r = b.duplicate()
    A.mult(x, r)
    r.axpy(-1.0, b)
    worst = max(worst, r.norm() / b.norm())
    ksp.destroy()
signal.signal(signal.SIGTERM, signal.SIG_IGN)  # the TERMs still on their way
print("done", len(taken), worst, flush=True)
"""
    job = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, env=ENV, stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True)
    try:
        assert job.stdout.readline() == "ready\n", job.communicate()
        end = time.monotonic() + 300  # some 5 s; before, a TERM could also leave it hanging
        while job.poll() is None:
            assert time.monotonic() < end, "still running after 300 s of TERMs"
            job.send_signal(signal.SIGTERM)
            time.sleep(0.002)
        out, err = job.communicate(timeout=60)
    finally:
        job.kill()
    assert job.returncode == 0, f"exit status {job.returncode}\n{err}"
    word, taken, worst = out.split()
    assert word == "done" and int(taken) > 0
    assert float(worst) < 1e-12


# ------------------------------------------------------------------------ the jobs


@pytest.mark.parametrize("entry", ENTRIES)
def test_a_term_at_any_moment_of_a_grow_start_up_ends_in_143(entry, tmp_path):
    # 0.05 s: importing hyper's modules; 0.3: numpy and the model; 0.6: DOLFINx, PETSc's
    # start; 1: the mesh and the forms; 2: the first growth steps (StopOnTerm's stop)
    for after_s in (0.05, 0.3, 0.6, 1.0, 2.0):
        command = [sys.executable, *ENTRIES[entry], "--output", str(tmp_path / f"at_{after_s}")]
        assert_stopped(term_at(command, after_s, catches_term, ROOT), f"{entry}, TERM at {after_s} s")


def test_a_term_at_any_moment_of_a_grow_start_up_on_two_ranks_ends_in_143(tmp_path):
    """mpirun passes the TERM on to both ranks; the moments count from when both catch it
    (mpirun TERMed before it started them reports the signal, 15: MPICH's, not ours)."""
    mpirun = str(Path(sys.executable).parent / "mpirun")

    def ranks_ready(pid):
        ranks = [p for p in descendants(pid) if b"hyper.grow" in command_line(p)]
        return len(ranks) == 2 and all(catches_term(p) for p in ranks)

    for after_s in (0.3, 1.0, 2.0, 3.0):
        command = [mpirun, "-n", "2", sys.executable, *ENTRIES["python -m hyper.grow"],
                   "--output", str(tmp_path / f"at_{after_s}")]
        assert_stopped(term_at(command, after_s, ranks_ready, ROOT), f"2 ranks, TERM at {after_s} s")


def test_a_rank_of_several_waits_for_its_mpi_to_start_before_it_ends(monkeypatch):
    """A rank that ends before its MPI has started leaves a peer inside MPI_Init (which
    mpi4py enters holding the GIL, so the peer's TERM thread cannot run) waiting for ever:
    the TERM waits for MPI to start, then MPI_Abort ends them all; alone, it ends at once."""
    class FakeMPI(types.ModuleType):
        asked = 0

        def Is_initialized(self):
            FakeMPI.asked += 1
            return FakeMPI.asked >= 3  # MPI starts while the rank waits

        def Is_finalized(self):
            return False

    monkeypatch.delenv("PMI_SIZE", raising=False)
    monkeypatch.delenv("OMPI_COMM_WORLD_SIZE", raising=False)
    monkeypatch.setitem(sys.modules, "mpi4py.MPI", FakeMPI("mpi4py.MPI"))
    term._await_mpi()
    assert FakeMPI.asked == 0  # one rank: nothing to wait for
    monkeypatch.setenv("PMI_SIZE", "2")
    term._await_mpi()
    assert FakeMPI.asked == 3
    # MPI never started (a job that does not use it): the wait ends at its limit
    monkeypatch.setattr(term, "MPI_START_WAIT_S", 0.05)
    monkeypatch.delitem(sys.modules, "mpi4py.MPI")
    term._await_mpi()
