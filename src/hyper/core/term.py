"""A SIGTERM at any moment of a job ends it with exit status 143, the status the Slurm
templates requeue (`install`, called first by every entry point).

Two things stood in the way. Before a job installs its own handler (`driver.StopOnTerm`,
at the start of a run) Python's default ends the process by the signal, without a word;
and PETSc, when DOLFINx first starts it, installs a handler of its own that turns a TERM
into "PETSC ERROR: Caught signal" and exit status 15 or 59 (MPI_Abort), which a grow-array
task TERMed in its first seconds died of and was not requeued. So `install` asks PETSc
for no signal handler (``-no_signal_handler`` in PETSC_OPTIONS, which PETSc reads when it
starts, in this process and in those it starts: however late any module first imports
petsc4py) and installs `stop_at_once` until a run installs its own. Without PETSc's
handler a crash (SIGSEGV, SIGFPE) is no longer PETSc's message: `faulthandler` prints
Python's traceback instead.

The standard library only: the shims import this before anything heavy.
"""

from __future__ import annotations

import contextlib
import faulthandler
import os
import signal
import sys

EXIT_TERMINATED = 128 + signal.SIGTERM  # 143, what a shell reports for a TERM-killed job
NO_PETSC_HANDLER = "-no_signal_handler"



def keep_petsc_off_signals() -> None:
    """Have PETSc start without its signal handlers, in this process and its children.

    PETSc reads PETSC_OPTIONS when it is initialised (the first ``from petsc4py import
    PETSc``, which importing DOLFINx does), so this must come before that; a PETSc
    already started keeps the handler it installed.
    """
    options = os.environ.get("PETSC_OPTIONS", "").split()
    if NO_PETSC_HANDLER not in options:
        os.environ["PETSC_OPTIONS"] = " ".join([*options, NO_PETSC_HANDLER])


def _world():
    """MPI's COMM_WORLD where this process has started MPI with other ranks, else None.

    Never imports mpi4py itself: a job that has not started MPI has no other rank to stop.
    """
    mpi = sys.modules.get("mpi4py.MPI")
    # a TERM while mpi4py.MPI is being imported finds the module half made: no MPI yet
    if mpi is None or not hasattr(mpi, "COMM_WORLD"):
        return None
    if not mpi.Is_initialized() or mpi.Is_finalized() or mpi.COMM_WORLD.size == 1:
        return None
    return mpi.COMM_WORLD


def stop_at_once(signum, frame) -> None:
    """The SIGTERM handler outside a run: one note on stderr, exit status 143.

    At once, as Python's default would, without unwinding: the work under way has no
    checkpoint to save, and with several ranks another one may wait in a collective for
    this one for ever, so MPI_Abort ends them all (MPICH then reports exit status 143).
    Each rank that gets the TERM before the abort reaches it says so.
    """
    world = _world()
    rank = "" if world is None else f" (rank {world.rank} of {world.size}: ending them all)"
    note = (f"hyper: stopped by SIGTERM outside a run's growth steps{rank}; exit status {EXIT_TERMINATED}: "
            "nothing unfinished is kept, run the same command again\n")
    with contextlib.suppress(OSError):  # stderr closed: the exit status says it
        os.write(2, note.encode())
    if world is not None:
        world.Abort(EXIT_TERMINATED)
    os._exit(EXIT_TERMINATED)


def install() -> None:
    """What every entry point does first (the ``python -m hyper.JOB`` shims, `cli.main`):
    PETSc without its signal handlers, `stop_at_once` for SIGTERM, Python's traceback on
    a crash. A handler installed already (a run's `driver.StopOnTerm`, a test's) stays."""
    keep_petsc_off_signals()
    if not faulthandler.is_enabled():
        faulthandler.enable()
    with contextlib.suppress(ValueError):  # not the main thread: signals are not ours to take
        if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
            signal.signal(signal.SIGTERM, stop_at_once)
