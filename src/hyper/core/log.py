"""Progress on rank 0 only: every other rank stays silent.

Messages go to the ``hyper`` logger (`hyper.commands.cli.setup_logging` sends them to stdout,
filtered to rank 0 of the communicator each message names).
"""

from __future__ import annotations

import logging
import sys
import time

_logger = logging.getLogger("hyper")

# s of wall time between progress lines of a long job: an hour-long run writes about 60
PROGRESS_EVERY = 60.0


def info(comm, *args) -> None:
    _logger.info(" ".join(str(a) for a in args), extra={"rank": 0 if comm is None else comm.rank})


def debug(comm, *args) -> None:
    _logger.debug(" ".join(str(a) for a in args), extra={"rank": 0 if comm is None else comm.rank})


def hms(seconds: float) -> str:
    seconds = int(round(max(seconds, 0.0)))
    h, rem = divmod(seconds, 3600)
    m, s = divmod(rem, 60)
    return f"{h:d}:{m:02d}:{s:02d}"


class Progress:
    """Prints "label: done/total, elapsed, time left" on rank 0, at most every ``every`` s."""

    def __init__(self, comm, total: float, label: str, every: float = PROGRESS_EVERY):
        self.comm = comm
        self.total = float(total)
        self.label = label
        self.every = every
        self.start = time.perf_counter()
        self._last = -float("inf")

    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def update(self, done: float, detail: str = "", force: bool = False) -> None:
        now = time.perf_counter()
        if not force and now - self._last < self.every:
            return
        self._last = now
        elapsed = now - self.start
        frac = done / self.total if self.total > 0 else 1.0
        left = elapsed * (1 - frac) / frac if frac > 0 else float("nan")
        left_txt = hms(left) if frac > 0 else "?"
        info(
            self.comm,
            f"{self.label}: {100 * frac:5.1f}% {detail} | elapsed {hms(elapsed)}, left {left_txt}",
        )


def error(comm, message: str) -> None:
    """The one line a bad input gets: on rank 0 of ``comm``, on stderr."""
    if comm is None or comm.rank == 0:
        print(f"error: {message}", file=sys.stderr, flush=True)


def warning(comm, message: str) -> None:
    if comm is None or comm.rank == 0:
        print(f"warning: {message}", file=sys.stderr, flush=True)
