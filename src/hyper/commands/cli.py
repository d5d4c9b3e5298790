"""The command layer of every job: parsing, logging on rank 0, exit codes, output locks.

A job module defines ``parser()`` (a `Parser`) and ``run(comm, args) -> int`` and ends
with ``main = cli.entry(parser, run)``; ``hyper JOB …`` and ``python -m hyper.JOB …``
then run the same thing. Bad input anywhere (an `InputError`, on any rank) is one
``error:`` line on rank 0 and exit status 2; an output another run holds is exit 4.

    hyper grow --geometry idealized --protocol mwf
    hyper cohort --help
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import math
import re
import sys
import traceback
from collections.abc import Callable
from importlib import metadata
from pathlib import Path

from hyper.core import io, term
from hyper.core.log import PROGRESS_EVERY, error
from hyper.core.params import InputError
from hyper.runs.locks import Busy, hold

EXIT_OK = 0
EXIT_SOME_FAILED = 1
EXIT_INPUT = 2
EXIT_FAILED = 3
EXIT_BUSY = 4
EXIT_TERMINATED = term.EXIT_TERMINATED  # 143, what a shell reports for a TERM-killed job

# `hyper JOB` runs hyper.commands.JOB.main (`python -m hyper.JOB`: the shim hyper/JOB.py); the
# benches keep their own dispatcher (hyper bench NAME).
JOBS = ("grow", "cohort", "ensemble", "signaling", "sobol", "contraction", "fibers", "meshstats", "mesh", "slurm",
        "calibrate", "dose", "inspect", "demo", "study", "reproduce", "box", "bench")

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


def integer(least: int, most: int | None = None) -> Callable[[str], int]:
    """An argparse type: an integer in [least, most], checked where the option is defined
    (argparse names the option in the message)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < least or (most is not None and value > most):
            bounds = f">= {least}" if most is None else f"in [{least}, {most}]"
            raise argparse.ArgumentTypeError(f"expected an integer {bounds}, got {value}")
        return value

    parse.__name__ = "integer"  # what argparse calls the type in its messages
    return parse


def positive(unit: str) -> Callable[[str], float]:
    """An argparse type: a finite number > 0 of ``unit`` (hours, seconds)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number of {unit}, got {text!r}") from None
        if not (math.isfinite(value) and value > 0):
            raise argparse.ArgumentTypeError(f"expected a finite number of {unit} > 0, got {text}")
        return value

    parse.__name__ = "number"
    return parse


def progress_option(p: Parser) -> None:
    """--progress-every of a long job (its progress lines, on rank 0; --quiet: none)."""

    p.add_argument("--progress-every", type=positive("seconds"), default=PROGRESS_EVERY, metavar="SECONDS",
                   help="seconds of wall time between progress lines (the first and last always come)")


def output(*, folder: bool | None = None, suffixes: tuple[str, ...] = ()) -> Callable[[str], Path]:
    """An argparse type for a path the job will write: a file (``folder`` False, with one
    of ``suffixes`` if given), a folder (True) or either (None). Every rank checks the same
    path alike, so a bad one stops every rank before any work."""

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


def entry(parser: Callable[[], Parser], run: Callable[..., int], *, world: bool = True,
          locks: Callable[[argparse.Namespace], list[Path]] | None = None) -> Callable[..., int]:
    """The ``main(argv=None)`` of a job: parse, set up logging, run, map errors to exit codes.

    ``run(comm, args)`` gets MPI.COMM_WORLD (``world=False``: ``run(None, args)``, for
    jobs that never start MPI) and returns the exit status. ``locks(args)`` names the
    outputs whose locks the job holds while it runs (`hold`): a second job on the same
    output stops at once (exit 4) instead of writing over the first.
    """

    def main(argv=None, comm=None) -> int:

        argv = sys.argv[1:] if argv is None else list(argv)
        if comm is None and world:
            from mpi4py import MPI

            comm = MPI.COMM_WORLD
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
    term.install()  # before the job's imports (PETSc): from here on a TERM ends in exit status 143
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in JOBS:
        return importlib.import_module(f"hyper.commands.{argv[0]}").main(argv[1:]) or 0
    p = argparse.ArgumentParser(prog="hyper", description="Exercise-driven muscle hypertrophy: one command per job; "
                                "`hyper JOB --help` shows a job's options.")
    p.add_argument("job", choices=JOBS, help="the job to run")
    p.add_argument("--version", action="version", version=f"hyper {version()}")
    p.parse_args(argv)  # only reached for --help, --version or a bad job name
    return EXIT_INPUT
