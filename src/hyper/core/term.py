"""A SIGTERM at any moment of a job ends it with exit status 143, the status the Slurm
templates requeue (`install`, called first by every entry point).

Three things stood in the way. Before a job installs its own handler (`driver.StopOnTerm`,
at the start of a run) Python's default ends the process by the signal, without a word.
PETSc, when DOLFINx first starts it, installs a handler of its own that turns a TERM into
"PETSC ERROR: Caught signal" and exit status 15 or 59 (MPI_Abort), which a grow-array task
TERMed in its first seconds died of and was not requeued. So `install` asks PETSc for no
signal handler (``-no_signal_handler`` in PETSC_OPTIONS, which PETSc reads when it starts,
in this process and in those it starts: however late any module first imports petsc4py)
and installs `stop_at_once` until a run installs its own. Without PETSc's handler a crash
(SIGSEGV, SIGFPE) is no longer PETSc's message: `faulthandler` prints Python's traceback
instead.

And METIS (MUMPS's ordering, in the first factorisation of every run) takes SIGTERM over
for the length of each call: GKlib's ``gk_sigtrap`` makes it the signal of its error
exit (SIGERR), whose handler longjmps out of METIS. A TERM then is lost, and MUMPS, which
does not look at METIS's status, goes on with an ordering never computed and crashes
(SIGSEGV in ``mumps_wrap_ginp94``, exit 11); one in the instant before METIS's setjmp
crashes in longjmp itself; and the longjmp out of the handler leaves SIGTERM blocked in
the main thread (once seen: a process hanging in a futex wait). No handler of Python's
can win against a library that calls ``signal()``, so `install` has no thread take
SIGTERM through a handler at all: SIGTERM is blocked in the main thread before anything
heavy starts, so that every thread started later (MPI's, OpenMP's, BLAS's, Python's)
inherits the block, and one thread of its own takes it with ``sigwait`` and hands it to
the Python handler (`_take_terms`). A child process inherits the mask too: start one
within `spawning`.

The standard library only: the shims import this before anything heavy.
"""

from __future__ import annotations

import _thread
import contextlib
import faulthandler
import os
import signal
import sys
import threading
import time

EXIT_TERMINATED = 128 + signal.SIGTERM  # 143, what a shell reports for a TERM-killed job
NO_PETSC_HANDLER = "-no_signal_handler"
TERM = {signal.SIGTERM}

_taker: threading.Thread | None = None  # the thread that takes SIGTERM, once started


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
    Each rank that gets the TERM before the abort reaches it says so. `_take_terms` calls
    it in its own thread, whatever the main thread is doing.
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


# How long a rank of several that takes a TERM before its MPI has started waits for it
# (`_await_mpi`): imports reach MPI_Init within seconds, even on a loaded machine.
MPI_START_WAIT_S = 30.0


def _launched_ranks() -> int:
    """How many ranks the MPI launcher started (MPICH's and Slurm's PMI, Open MPI); 1 if none."""
    for name in ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE"):
        with contextlib.suppress(KeyError, ValueError):
            return int(os.environ[name])
    return 1


def _await_mpi() -> None:
    """On a rank of several whose MPI has not started yet, wait until it has (at most
    MPI_START_WAIT_S), so that `stop_at_once` ends every rank with MPI_Abort.

    Ending at once instead leaves a peer that is inside MPI_Init waiting for this rank for
    ever: mpi4py starts MPI holding the GIL, so the peer's own TERM thread cannot run, and
    mpiexec does not end a job whose rank exits before MPI has started (seen once in about
    40 TERMs in a 2-rank grow's first second, on a loaded machine). Waiting here, this
    rank's imports go on to MPI_Init, which then completes on every rank."""
    if _launched_ranks() <= 1:
        return
    deadline = time.monotonic() + MPI_START_WAIT_S
    while time.monotonic() < deadline:
        mpi = sys.modules.get("mpi4py.MPI")
        with contextlib.suppress(AttributeError):  # a module half made: MPI not started yet
            if mpi is not None and (mpi.Is_initialized() or mpi.Is_finalized()):
                return
        time.sleep(0.01)


def _take_terms() -> None:
    """The thread that takes every SIGTERM (blocked in all the others) and does what the
    Python handler of the moment says: `stop_at_once` here and now (the main thread may be
    deep in native code or waiting for a child); another handler (a run's flag) in the main
    thread, as a signal would; none of Python's (SIG_DFL): the signal's own action."""
    while True:
        signum = signal.sigwait(TERM)
        handler = signal.getsignal(signum)
        if handler is stop_at_once:
            _await_mpi()
            stop_at_once(signum, None)
        elif callable(handler):
            _thread.interrupt_main(signum)
        elif handler != signal.SIG_IGN:
            signal.pthread_sigmask(signal.SIG_UNBLOCK, TERM)  # in this thread only
            signal.raise_signal(signum)
            signal.pthread_sigmask(signal.SIG_BLOCK, TERM)


def _alone() -> bool:
    """Whether the calling thread is the process's only one (no MPI, BLAS or Python thread
    started yet), from Linux's /proc; elsewhere, unknown: False."""
    try:
        return len(os.listdir("/proc/self/task")) == 1
    except OSError:
        return False


def install() -> None:
    """What every entry point does first (the ``python -m hyper.JOB`` shims, `cli`):
    PETSc without its signal handlers, `stop_at_once` for SIGTERM, Python's traceback on
    a crash, and SIGTERM taken by a thread of its own (`_take_terms`). A handler installed
    already (a run's `driver.StopOnTerm`, a test's) stays. The thread only where nothing
    has started threads yet (a thread started earlier, which does not block SIGTERM, would
    take it itself): in a shim and in the ``hyper`` script, not in a test's process that
    calls a job's ``main``."""
    global _taker
    keep_petsc_off_signals()
    if not faulthandler.is_enabled():
        faulthandler.enable()
    if threading.current_thread() is not threading.main_thread():
        return  # signals are the main thread's to take
    if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        signal.signal(signal.SIGTERM, stop_at_once)
    if _taker is None and _alone():
        signal.pthread_sigmask(signal.SIG_BLOCK, TERM)
        _taker = threading.Thread(target=_take_terms, name="hyper-sigterm", daemon=True)
        _taker.start()


@contextlib.contextmanager
def spawning():
    """Start child processes within: a child inherits its parent thread's signal mask, and
    `install` blocks SIGTERM, which a child that never unblocks it (mpirun, git, gmsh)
    would ignore. Meanwhile the calling thread takes a TERM itself, through the Python
    handler: it is starting or waiting for a child, in no METIS."""
    previous = signal.pthread_sigmask(signal.SIG_UNBLOCK, TERM)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)
