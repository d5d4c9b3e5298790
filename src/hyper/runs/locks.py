"""Output locks: one run at a time writes an output (`OutputLock`, `locked`, `hold`)."""

from __future__ import annotations

import contextlib
import datetime
import errno
import fcntl
import os
import socket
from collections.abc import Iterator
from pathlib import Path

from hyper.core import io, log
from hyper.core.params import InputError


class Busy(RuntimeError):
    """Another process holds the lock of an output."""


class OutputLock:
    """An exclusive lock (fcntl.flock) on ``{output}.lock``, for one process at a time.

    Taken without waiting: a second run on the same output gets `Busy`, with the
    holder's host, pid and start time, which the holder writes into the file. The lock
    file is removed on release; a lock taken on a file that was removed meanwhile is
    taken again on the new file, so the removal never lets two holders in.
    """

    def __init__(self, output: Path):
        self.path = Path(str(output) + ".lock")
        self._fd: int | None = None
        self._made: list[Path] = []  # the folders made for the lock, innermost first

    def acquire(self) -> bool:
        """Take the lock; False where the file system has no locks (then none is held)."""
        missing = self.path.parent
        while not missing.exists():
            self._made.append(missing)
            missing = missing.parent
        self.path.parent.mkdir(parents=True, exist_ok=True)
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.read(fd, 4096).decode(errors="replace").strip() or "unknown process"
                os.close(fd)
                raise Busy(f"{self.path}: another run is writing this output ({holder}); "
                           "wait for it to finish, or choose another --output") from None
            except OSError as err:  # e.g. a Lustre mount without flock support
                if err.errno not in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
                    os.close(fd)
                    raise
                os.close(fd)
                self.path.unlink(missing_ok=True)
                return False
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        started = datetime.datetime.now().isoformat(timespec="seconds")
        try:
            os.ftruncate(fd, 0)
            os.write(fd, f"host {socket.gethostname()}, pid {os.getpid()}, since {started}\n".encode())
        except OSError:  # a full disk: no lock file left behind, no descriptor held open
            self._fd = fd
            self.release()
            raise
        self._fd = fd
        return True

    def release(self) -> None:
        """Let go, and remove the folders made for the lock that nothing else filled: a run
        that stopped on bad input leaves no trace."""
        if self._fd is not None:
            self.path.unlink(missing_ok=True)
            os.close(self._fd)
            self._fd = None
        for folder in self._made:
            try:
                folder.rmdir()
            except OSError:  # not empty: the run wrote there
                break
        self._made = []


@contextlib.contextmanager
def locked(outputs: list[Path]) -> Iterator[list[Path]]:
    """Hold the locks of all ``outputs`` (call on one rank); Busy if any is held.
    Yields the lock files that could not be taken because the file system has no locks."""
    locks = [OutputLock(p) for p in outputs]
    try:
        yield [lock.path for lock in locks if not lock.acquire()]
    finally:
        for lock in reversed(locks):
            lock.release()


@contextlib.contextmanager
def hold(comm, outputs: list[Path]) -> Iterator[None]:
    """Hold the output locks of ``outputs`` on rank 0 while the block runs (collective).

    Raises `Busy` on every rank when another run holds one of them.
    """
    with contextlib.ExitStack() as held:
        busy = unlocked = None
        broken = None
        if comm.rank == 0:
            try:
                unlocked = held.enter_context(locked(list(outputs)))
            except Busy as err:
                busy = str(err)
            except OSError as err:  # e.g. the lock's name is a folder, or its folder unwritable
                full = io.write_failed(Path(str(outputs[0]) + ".lock") if len(outputs) == 1 else "an output lock", err)
                broken = full if full is not None else f"cannot take the output lock: {err}"
        busy, broken = comm.bcast((busy, broken), root=0)
        if isinstance(broken, io.WriteFailed):  # a full disk is no bad input: exit 3, as for any write
            raise broken
        if broken is not None:
            raise InputError(broken)
        if busy is not None:
            raise Busy(busy)
        for path in unlocked or ():
            log.warning(comm, f"{path}: the file system takes no locks; nothing keeps another run from writing "
                          "the same output")
        yield
