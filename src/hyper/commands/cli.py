"""The command layer of every job: parsing, logging on rank 0, exit codes, output locks.

A job module defines ``parser()`` (a `Parser`) and ``run(comm, args) -> int`` and ends
with ``main = cli.entry(parser, run)``; ``hyper JOB …`` and ``python -m hyper.JOB …``
then run the same thing. Bad input anywhere (an `InputError`, on any rank) is one
``error:`` line on rank 0 and exit status 2; an output another run holds is exit 4; a full or
failing disk (`io.WriteFailed`) is one ``error:`` line and exit 3; a closed pipe on stdout
ends the job silently with 141, as SIGPIPE ends a Unix tool.

    hyper grow --geometry idealized --protocol mwf
    hyper cohort --help
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import re
import select
import signal
import sys
import traceback
from collections.abc import Callable
from importlib import metadata
from pathlib import Path
from typing import Any

from hyper.core import term

# The `hyper` script's module (and every job's): before the imports below start numpy and
# MPI, whose threads must inherit term's block of SIGTERM. A shim has installed it already.
term.install()
from hyper.core import io  # noqa: E402
from hyper.core.log import PROGRESS_EVERY, error  # noqa: E402
from hyper.core.params import SEED_MAX, InputError, as_float, as_vector, float_text, int_text, shown  # noqa: E402
from hyper.fem import fiberread as fr  # noqa: E402
from hyper.runs.locks import Busy, hold  # noqa: E402
from hyper.runs.runspec import MAX_REFINE  # noqa: E402

EXIT_OK = 0
EXIT_SOME_FAILED = 1
EXIT_INPUT = 2
EXIT_FAILED = 3
EXIT_BUSY = 4
EXIT_TERMINATED = term.EXIT_TERMINATED  # 143, what a shell reports for a TERM-killed job
# 141, what a shell reports for `yes | head -1`'s yes, which SIGPIPE ends: a job whose stdout's
# reader has gone stops as Unix tools do, silently, and a pipeline with pipefail sees the cut
EXIT_PIPE = 128 + signal.SIGPIPE

# `hyper JOB` runs hyper.commands.JOB.main (`python -m hyper.JOB`: the shim hyper/JOB.py); the
# benches keep their own dispatcher (hyper bench NAME).
JOBS = ("grow", "cohort", "ensemble", "signaling", "sobol", "contraction", "fibers", "meshstats", "mesh", "slurm",
        "calibrate", "dose", "design", "predict", "inspect", "demo", "study", "reproduce", "box", "bench")

LOGGER = "hyper"


def version() -> str:
    try:
        return metadata.version("hyper")
    except metadata.PackageNotFoundError:
        return "unknown"


class _HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """The module docstring as written, and every option's default in its help."""


class Parser(argparse.ArgumentParser):
    """argparse for a job: errors are InputErrors (one line on rank 0, exit status 2), every
    default is shown in --help, and --quiet, --verbose and --version are always there."""

    def __init__(self, job: str, description: str | None = None, **kwargs):
        super().__init__(prog=f"hyper {job}", description=description, formatter_class=_HelpFormatter,
                         allow_abbrev=False, **kwargs)
        talk = self.add_argument_group("logging").add_mutually_exclusive_group()
        talk.add_argument("--quiet", action="store_true", help="only warnings and errors")
        talk.add_argument("--verbose", action="store_true", help="also debugging detail")
        self.add_argument("--version", action="version", version=f"hyper {version()}")

    def error(self, message):
        raise InputError(message)

    def add_argument(self, *names, reads=None, **kwargs):
        """argparse's, and ``reads``: the option names files the job reads (True: its value,
        or each of its values; a function: the paths a value stands for), which no output
        of the job may be (`hyper.core.io.unwritable`)."""
        action = super().add_argument(*names, **kwargs)
        if reads is not None:
            self._reads = [*getattr(self, "_reads", []), (action.dest, reads)]
        return action

    def parse_known_args(self, args=None, namespace=None):
        # Every output checked against every input once all options are known: a type sees
        # its own value only. Still before any work: parsing is the job's first step.
        args, rest = super().parse_known_args(args, namespace)
        inputs = [path for dest, reads in getattr(self, "_reads", []) for value in _values(getattr(args, dest, None))
                  for path in ([value] if reads is True else reads(value))]
        if inputs:
            for action in self._actions:
                check = getattr(action.type, "output", None)
                for value in _values(getattr(args, action.dest, None)) if check else ():
                    problem = io.unwritable(value, folder=check["folder"], inputs=inputs, replaces=check["replaces"])
                    if problem is not None:
                        self.error(f"argument {'/'.join(action.option_strings) or action.dest}: {problem}")
        return args, rest


def _values(value) -> list:
    """An option's value as a list (none, one, or the list nargs or append made)."""
    return [] if value is None else [v for v in value if v is not None] if isinstance(value, list) else [value]


def _option_type(name: str, read: Callable[[str], Any]) -> Callable[[str], Any]:
    """An argparse type from a reader of `hyper.core.params` (the one numeric reader of
    every job): its InputError becomes argparse's error, which names the option."""

    def parse(text: str):
        try:
            return read(text)
        except InputError as err:
            raise argparse.ArgumentTypeError(err.reason) from None

    parse.__name__ = name  # what argparse calls the type in its messages
    return parse


def integer(least: int, most: int | None = None) -> Callable[[str], int]:
    """An argparse type: an integer in [least, most] (and in int64), checked where the
    option is defined (argparse names the option in the message)."""
    return _option_type("integer", lambda text: int_text(text, "", least, most))


def seed() -> Callable[[str], int]:
    """An argparse type: a random seed, in [0, SEED_MAX] as every seed a file gives."""
    return integer(0, SEED_MAX)


def number(least: float | None = None, most: float | None = None, *, above: float | None = None,
           below: float | None = None) -> Callable[[str], float]:
    """An argparse type: a finite number within the bounds given (`as_float`'s)."""
    return _option_type("number", lambda text: float_text(text, "", least, most, above=above, below=below))


def positive(unit: str) -> Callable[[str], float]:
    """An argparse type: a finite number > 0 of ``unit`` (hours, seconds)."""

    def read(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise InputError(f"expected a number of {unit}, got {shown(text)}") from None
        try:
            return as_float(value, "", above=0)
        except InputError:
            raise InputError(f"expected a finite number of {unit} > 0, got {value:g}") from None

    return _option_type("number", read)


class _Vector(argparse.Action):
    """The three components of a direction option, read by `as_vector`: finite,
    not all zero, scaled to unit length."""

    def __call__(self, parser, namespace, values, option_string=None):
        try:
            vector = as_vector([float_text(v, "") for v in values], "")
        except InputError as err:
            raise argparse.ArgumentError(self, err.reason) from None
        setattr(namespace, self.dest, vector)


def vector_option(p: argparse.ArgumentParser, name: str, **kwargs) -> None:
    """A direction option NAME X Y Z (every vector option of every job)."""
    p.add_argument(name, nargs=3, metavar=("X", "Y", "Z"), action=_Vector, **kwargs)


def progress_option(p: Parser) -> None:
    """--progress-every of a long job (its progress lines, on rank 0; --quiet: none)."""

    p.add_argument("--progress-every", type=positive("seconds"), default=PROGRESS_EVERY, metavar="SECONDS",
                   help="seconds of wall time between progress lines (the first and last always come)")


def refine_option(p: Parser, default: int | None = 0) -> None:
    """--refine K, the same in every job that runs a mesh (grow, cohort, study, contraction);
    ``default`` None where a study file may set it."""
    p.add_argument("--refine", type=integer(0, MAX_REFINE), default=default, metavar="K",
                   help=f"refine the mesh uniformly K times (0 to {MAX_REFINE}; each splits every tetrahedron "
                        "into 8 on the same polyhedron); fibres from a formula are evaluated on the refined "
                        "mesh, those of a fibre file or a principal axis carried over from the loaded one"
                        + ("" if default is not None else "; overrides [numerics] refine"))


def fibre_data_options(p: Parser) -> None:
    """The options of --fibers FILE, fibres from data (`hyper.fem.fiberdata`), the same in
    every job that takes one."""
    p.add_argument("--fibers-unit", choices=tuple(fr.UNITS), default="auto",
                   help="length unit of the fibre data's coordinates: auto is a NIfTI header's spatial unit, "
                        "else mm (the world unit of imaging)")
    p.add_argument("--fibers-min-fa", type=number(0, below=1), default=fr.MIN_FA, metavar="FA",
                   help="fractional anisotropy below which an image voxel gives no direction and its nodes are "
                        "filled from their neighbours (tensor images, or with --fibers-fa)")
    p.add_argument("--fibers-radius", type=positive("mm"), metavar="MM",
                   help="how far a streamline or point-cloud sample reaches a mesh node; 1.5 mean edge lengths "
                        "of the mesh by default")
    p.add_argument("--fibers-fa", type=Path, reads=True, metavar="FA.nii",
                   help="an FA image on the grid of an eigenvector image (--fibers-min-fa applies to it)")


def output(*, folder: bool | None = None, suffixes: tuple[str, ...] = (), replaces: bool = False
           ) -> Callable[[str], Path]:
    """An argparse type for a path the job will write: a file (``folder`` False, with one
    of ``suffixes`` if given), a folder (True) or either (None); ``replaces``: a folder the
    job replaces whole, which may not hold an input. Every rank checks the same path alike,
    so a bad one stops every rank before any work; `Parser` checks it against the inputs."""

    def parse(text: str) -> Path:
        if not text or "\0" in text:
            raise argparse.ArgumentTypeError(f"expected a path, got {text!r}")
        path = Path(text)
        if suffixes and path.suffix.lower() not in suffixes:
            raise argparse.ArgumentTypeError(f"{path}: expected a {' or '.join(suffixes)} file")
        problem = io.unwritable(path, folder=folder)
        if problem is not None:
            raise argparse.ArgumentTypeError(problem)
        return path

    parse.__name__ = "path"
    parse.output = {"folder": folder, "replaces": replaces}  # what Parser checks against the inputs
    return parse


# ------------------------------------------------------------------------------ logging


class _Rank0(logging.Filter):
    """Pass records of rank 0 of the communicator they name (``extra={"rank": …}``)."""

    def __init__(self, world_rank: int):
        super().__init__()
        self.world_rank = world_rank

    def filter(self, record: logging.LogRecord) -> bool:
        return getattr(record, "rank", self.world_rank) == 0


class _Stdout(logging.Handler):
    """Writes to the sys.stdout of the moment: a farm group may redirect it into a run's log."""

    def emit(self, record):
        try:
            stream = sys.stdout
            stream.write(self.format(record) + "\n")
            stream.flush()
        except BrokenPipeError:
            raise  # the reader of stdout has gone: `entry` ends the job, as a closed pipe ends a Unix tool
        except Exception:  # noqa: BLE001 - logging's own policy: report, never raise
            self.handleError(record)


def setup_logging(world_rank: int, *, quiet: bool = False, verbose: bool = False) -> logging.Logger:
    logger = logging.getLogger(LOGGER)
    logger.setLevel(logging.WARNING if quiet else logging.DEBUG if verbose else logging.INFO)
    for handler in list(logger.handlers):
        logger.removeHandler(handler)
    handler = _Stdout()
    handler.setFormatter(logging.Formatter("%(message)s"))
    handler.addFilter(_Rank0(world_rank))
    logger.addHandler(handler)
    logger.propagate = False
    return logger


def petsc_option(text: str) -> tuple[str, str]:
    """KEY=VALUE of a --petsc-option, the key without dash or prefix (they are the solver's)."""
    key, sep, value = text.partition("=")
    if not sep or not re.fullmatch(r"[a-z][a-z0-9_]*", key) or not value or re.search(r"\s", value):
        raise InputError(f"--petsc-option {text!r}: expected KEY=VALUE with a PETSc option name without "
                         "its dash and prefix, e.g. snes_max_it=50")
    return key, value


# ---------------------------------------------------------------------------- the entry


def stdout_reader_gone() -> bool:
    """Whether stdout is a pipe whose reader has gone (``| head -0``): poll reports POLLERR on
    the write end of such a pipe, never on a file, a terminal or an open pipe. A BrokenPipeError
    from elsewhere (a subprocess's pipe) is then a failure like any other."""
    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(events & select.POLLERR for _, events in poller.poll(0))
    except (AttributeError, OSError, ValueError):  # no file descriptor: a test's capture, a closed stream
        return False


def quiet_stdout() -> None:
    """Point stdout's file descriptor at /dev/null: what Python still holds for it is flushed
    at exit, and would print "Exception ignored … BrokenPipeError" into a closed pipe."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)


def entry(parser: Callable[[], Parser], run: Callable[..., int], *, world: bool = True,
          locks: Callable[[argparse.Namespace], list[Path]] | None = None) -> Callable[..., int]:
    """The ``main(argv=None)`` of a job: parse, set up logging, run, map errors to exit codes.

    ``run(comm, args)`` gets MPI.COMM_WORLD (``world=False``: ``run(None, args)``, for
    jobs that never start MPI) and returns the exit status. ``locks(args)`` names the
    outputs whose locks the job holds while it runs (`hold`): a second job on the same
    output stops at once (exit 4) instead of writing over the first. A job whose stdout's
    reader has gone (``hyper inspect R.h5 | head -0``) stops quietly with `EXIT_PIPE`, as
    SIGPIPE stops a Unix tool: nothing on stderr (on several ranks: MPI's abort, which
    stops the ranks waiting for rank 0).
    """

    def main(argv=None, comm=None) -> int:
        argv = sys.argv[1:] if argv is None else list(argv)
        if comm is None and world:
            from mpi4py import MPI

            comm = MPI.COMM_WORLD
        # Python ignores SIGPIPE, so that a write into a closed pipe is a BrokenPipeError; PETSc,
        # which a job's imports start, catches it instead and aborts with a page of errors.
        with contextlib.suppress(ValueError):  # not the main thread, whose signals these are
            signal.signal(signal.SIGPIPE, signal.SIG_IGN)
        try:
            try:
                return job(argv, comm)
            finally:
                sys.stdout.flush()  # a reader that has gone shows here, --help's too, not at exit
        except BrokenPipeError:
            if not stdout_reader_gone():
                raise
            quiet_stdout()
            if comm is not None and comm.size > 1:
                comm.Abort(EXIT_PIPE)  # the other ranks may wait in a collective for rank 0
            return EXIT_PIPE

    def job(argv: list[str], comm) -> int:
        rank = comm.rank if comm is not None else 0
        try:
            made = parser()
            args = made.parse_args(argv)
        except InputError as err:
            error(comm, str(err))
            return EXIT_INPUT
        setup_logging(rank, quiet=args.quiet, verbose=args.verbose)

        io.record_command([*made.prog.split(), *argv])
        try:
            with hold(comm, locks(args)) if locks is not None else contextlib.nullcontext():
                return int(run(comm, args))
        except InputError as err:
            error(comm, str(err))
            return EXIT_INPUT
        except Busy as err:
            error(comm, str(err))
            return EXIT_BUSY
        except io.WriteFailed as err:
            # rank 0 writes: the other ranks may wait in a collective for it, so end them too
            error(comm, " ".join(str(err).split()))
            if comm is not None and comm.size > 1:
                sys.stderr.flush()
                comm.Abort(EXIT_FAILED)
            return EXIT_FAILED
        except BrokenPipeError:
            raise  # `main`'s: stdout's reader has gone, no failure to abort with a traceback
        except Exception:
            # A failure on some ranks only would leave the others waiting in a collective
            # for ever: end the whole job instead, after saying why.
            if comm is not None and comm.size > 1:
                traceback.print_exc()
                sys.stderr.flush()
                comm.Abort(EXIT_SOME_FAILED)
            raise

    return main


def main(argv=None) -> int:
    """``hyper JOB [options]``: the job's own ``main`` with the rest of the command line."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in JOBS:
        return importlib.import_module(f"hyper.commands.{argv[0]}").main(argv[1:]) or 0
    p = argparse.ArgumentParser(prog="hyper", description="Exercise-driven muscle hypertrophy: one command per job; "
                                "`hyper JOB --help` shows a job's options.")
    p.add_argument("job", choices=JOBS, help="the job to run")
    p.add_argument("--version", action="version", version=f"hyper {version()}")
    p.parse_args(argv)  # only reached for --help, --version or a bad job name
    return EXIT_INPUT
