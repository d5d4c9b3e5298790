"""A job farm: one MPI communicator, many independent jobs, handed out dynamically.

``run`` splits the communicator into groups of ``ranks_per_job`` consecutive ranks. Each
group runs whole jobs on its own sub-communicator, taking the next job (longest first)
whenever it finishes one, so no group idles while jobs remain and rank 0 works too.

Dispatch. Rank 0 keeps the queue. Its own group takes jobs from it directly; the
leaders (rank 0 of each group) of the other groups ask a small server thread on rank 0
by point-to-point messages on a private duplicate of the communicator. The thread
sleeps between ``Iprobe`` polls, so it costs rank 0 almost no CPU time, and it answers
while rank 0 computes. The obvious alternative, an atomic counter in an MPI window
(``Fetch_and_op``, passive target), was measured with the MPICH used here: a request
waits until the target rank next enters MPI, i.e. up to a whole job of rank 0, unless
MPICH's asynchronous progress thread is enabled, which spins a core per rank. The
server thread needs ``MPI_THREAD_MULTIPLE`` (mpi4py's default) and the GIL: a request
arriving while rank 0 is inside a long C++ call that keeps the GIL waits for that
call (typically well under a second), never for a whole job.

Failures. ``work`` raising on any rank of a group marks the job failed, with the
traceback text of every failing rank; all ranks of the group agree on success by an
allreduce after the job, and the farm goes on with the next job. Each job gets a fresh
duplicate of the group communicator, freed afterwards, so messages a failed job left
unmatched cannot be received by the next one. What the farm cannot repair: a rank that
raises while the other ranks of its group wait in a collective call of the job leaves
them waiting forever. ``work`` must therefore fail collectively (decide on errors with
an allreduce before raising, as PETSc/DOLFINx solvers do with convergence failures),
or raise only outside collective calls.

Cost per job: a few communicator duplications and a full ``gc.collect()`` on every rank
of the group (about 0.1 s with DOLFINx loaded), which frees the communicators that
DOLFINx objects hold (MPICH has about 2000; 2500 DOLFINx jobs in one run were
checked). Bundle work into jobs of seconds or more.

Progress. Rank 0 learns of every job start and end through the queue it keeps (its
server thread hears the other groups' reports), and prints done/running/failed, the
elapsed time and the time left, estimated from the job costs finished so far.
"""

from __future__ import annotations

import gc
import math
import pickle
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from mpi4py import MPI

from hyper.core.log import PROGRESS_EVERY, Progress, info
from hyper.core.params import InputError

_REQUEST, _REPLY = 71, 72
_POLL_S = 0.02  # the server thread's sleep between polls: the latency of a hand-out

PENDING, RUNNING, DONE, FAILED, SKIPPED = range(5)


@dataclass(frozen=True)
class Job:
    key: str  # unique; callers name outputs by it
    cost: float = 1.0  # estimated cost (any unit, e.g. s); longer jobs are handed out first
    payload: Any = None  # anything picklable that ``work`` needs

    def __post_init__(self):
        if not isinstance(self.key, str) or not self.key:
            raise InputError(f"job key must be a non-empty string, got {self.key!r}")
        if not (isinstance(self.cost, (int, float)) and math.isfinite(self.cost) and self.cost > 0):
            raise InputError(f"job {self.key}: cost must be a finite positive number, got {self.cost!r}")


@dataclass(frozen=True)
class JobResult:
    key: str
    status: str  # "done", "failed" or "skipped"
    wall_s: float  # wall time of the job on its group (0 when skipped)
    error: str  # traceback text of the failing rank(s); "" unless failed
    result: dict | None  # what ``work`` returned on the group's rank 0 (None unless done)
    group: int  # index of the group that ran it; -1 when skipped


class _Queue:
    """The job queue on rank 0: hands out jobs and keeps every job's state for progress.

    Used by rank 0's main thread and by its server thread, hence the lock.
    """

    def __init__(self, comm, jobs: Sequence[Job], order: Sequence[int], state, label: str, progress_every: float):
        self.comm = comm
        self.jobs = jobs
        self.order = list(order)
        self.state = state
        self.label = label
        self.lock = threading.Lock()
        self.next = 0
        self.cost_done = 0.0
        self.progress = Progress(comm, sum(jobs[i].cost for i in order), label, every=progress_every)

    def take(self) -> int:
        """The index of the next job to run, or -1 when none is left."""
        with self.lock:
            if self.next >= len(self.order):
                return -1
            index = self.order[self.next]
            self.next += 1
            self.state[index] = RUNNING
            return index

    def finish(self, index: int, failed: bool, last_error_line: str) -> None:
        with self.lock:
            self.state[index] = FAILED if failed else DONE
            self.cost_done += self.jobs[index].cost
            if failed:
                info(self.comm, f"{self.label}: {self.jobs[index].key} failed: {last_error_line}")
            counts = np.bincount(self.state, minlength=5)
            finished = self.next >= len(self.order) and counts[RUNNING] == 0
            self.progress.update(
                self.cost_done,
                f"{counts[DONE]} done, {counts[RUNNING]} running, {counts[FAILED]} failed, "
                f"{counts[PENDING]} waiting, {counts[SKIPPED]} skipped of {len(self.jobs)}",
                force=finished or failed,
            )


def _serve(fcomm, queue: _Queue, n_leaders: int) -> None:
    """Answer the other groups' leaders until each has been told that no job is left."""
    try:
        status = MPI.Status()
        left = n_leaders
        while left:
            if not fcomm.iprobe(source=MPI.ANY_SOURCE, tag=_REQUEST, status=status):
                time.sleep(_POLL_S)
                continue
            source = status.Get_source()
            report = fcomm.recv(source=source, tag=_REQUEST)
            if report is not None:
                queue.finish(*report)
            index = queue.take()
            fcomm.send(index, dest=source, tag=_REPLY)
            left -= index < 0
    except BaseException:
        # The other leaders would wait forever for an answer: stop the run loudly.
        traceback.print_exc()
        fcomm.Abort(1)


def _check_ranks_per_job(comm, ranks_per_job) -> None:
    if isinstance(ranks_per_job, bool) or not isinstance(ranks_per_job, (int, np.integer)):
        raise InputError(f"ranks per job must be an integer, got {ranks_per_job!r}")
    if ranks_per_job < 1 or comm.size % ranks_per_job:
        raise InputError(
            f"ranks per job must be >= 1 and divide the number of MPI ranks ({comm.size}), "
            f"got {ranks_per_job}"
        )


def _skipped(comm, jobs: Sequence[Job], is_done) -> list[bool]:
    """Which jobs are already done, decided on rank 0 once so that all ranks agree."""
    answer: Any = None
    if comm.rank == 0:
        try:
            answer = [bool(is_done(job)) if is_done else False for job in jobs]
        except Exception as err:  # noqa: BLE001 - re-raised on every rank below
            answer = err
    answer = comm.bcast(answer, root=0)
    if isinstance(answer, Exception):
        raise answer
    return answer


# Groups compile the same forms at the same time: one compiles, the others wait for its
# cache file, which on a loaded machine took longer than DOLFINx's 10 s (a full
# `hyper reproduce` lost a contraction run to "JIT compilation timed out").
JIT_WAIT_S = 600


def _wait_for_compiles() -> None:
    try:
        import dolfinx_solver  # noqa: F401  (must precede dolfinx)
        from dolfinx import jit
    except ImportError:  # a farm of jobs without DOLFINx
        return
    value, doc = jit.DOLFINX_DEFAULT_JIT_OPTIONS["timeout"]
    jit.DOLFINX_DEFAULT_JIT_OPTIONS["timeout"] = (max(value, JIT_WAIT_S), doc)


def run(
    comm,
    jobs: Sequence[Job],
    work: Callable[[Any, Job], dict | None],
    *,
    ranks_per_job: int = 1,
    is_done: Callable[[Job], bool] | None = None,
    label: str = "jobs",
    progress_every: float = PROGRESS_EVERY,
) -> list[JobResult]:
    """Run every job once on a group of ``ranks_per_job`` ranks; collective over ``comm``.

    ``work(subcomm, job)`` is called by all ranks of a group with a communicator of the
    group's ranks (a fresh one per job) and returns a picklable dict (or None); the
    value on the group's rank 0 is recorded. ``is_done(job)``, called on rank 0 only,
    marks jobs whose complete results already exist: they are skipped. Returns the
    results of all jobs, in the order of ``jobs``, on every rank. Rank 0 prints the
    farm's progress as jobs end, at most every ``progress_every`` s (and at the last).
    """
    _check_ranks_per_job(comm, ranks_per_job)
    if comm.size // ranks_per_job > 1:
        _wait_for_compiles()
    keys = [job.key for job in jobs]
    if len(set(keys)) != len(keys):
        dup = sorted({k for k in keys if keys.count(k) > 1})
        raise InputError(f"job keys must be unique; repeated: {', '.join(dup)}")

    skipped = _skipped(comm, jobs, is_done)
    todo = [i for i in range(len(jobs)) if not skipped[i]]
    order = sorted(todo, key=lambda i: -jobs[i].cost)  # stable: ties keep the given order
    n_groups = comm.size // ranks_per_job
    group = comm.rank // ranks_per_job
    if n_groups > 1 and MPI.Query_thread() < MPI.THREAD_MULTIPLE:
        raise RuntimeError("hyper.runs.farm with several groups needs MPI_THREAD_MULTIPLE")

    fcomm = comm.Dup()  # farm messages never meet the jobs' own traffic
    subcomm = comm.Split(color=group, key=comm.rank)
    leader = subcomm.rank == 0
    queue = server = None
    try:
        if comm.rank == 0:
            state = np.where(skipped, SKIPPED, PENDING).astype(np.int64)
            queue = _Queue(comm, jobs, order, state, label, progress_every)
            info(
                comm,
                f"{label}: {len(todo)} to run, {len(jobs) - len(todo)} skipped (done before), "
                f"{n_groups} group(s) of {ranks_per_job} rank(s)",
            )
            if n_groups > 1:
                server = threading.Thread(
                    target=_serve, args=(fcomm, queue, n_groups - 1), daemon=True
                )
                server.start()

        mine: list[tuple[int, JobResult]] = []
        report = None  # (index, failed, last error line) of the job this group just ran
        while True:
            index = None
            if leader:
                if queue is not None:
                    if report is not None:
                        queue.finish(*report)
                    index = queue.take()
                else:
                    fcomm.send(report, dest=0, tag=_REQUEST)
                    index = fcomm.recv(source=0, tag=_REPLY)
            index = subcomm.bcast(index, root=0)
            if index < 0:
                break
            result = _run_one(subcomm, jobs[index], work, group)
            if leader:
                mine.append((index, result))
                report = (index, result.status == "failed", _last_line(result.error))

        if server is not None:
            server.join()
        gathered = fcomm.allgather(mine)
    finally:
        subcomm.Free()
        fcomm.Free()

    results: list[JobResult | None] = [
        JobResult(job.key, "skipped", 0.0, "", None, -1) if skip else None
        for job, skip in zip(jobs, skipped)
    ]
    for part in gathered:
        for index, result in part:
            results[index] = result
    return results  # type: ignore[return-value]


def _run_one(subcomm, job: Job, work, group: int) -> JobResult:
    """Run one job on all ranks of a group; every rank returns the same status."""
    jobcomm = subcomm.Dup()
    start = time.perf_counter()
    value, error = None, ""
    try:
        value = work(jobcomm, job)
    except Exception:  # noqa: BLE001 - a failed job is recorded, the farm goes on
        error = traceback.format_exc()
    ok = subcomm.allreduce(not error, op=MPI.LAND)
    errors = subcomm.gather(error, root=0)
    wall = time.perf_counter() - start
    value_error = ""
    if subcomm.rank == 0 and ok:
        value_error = _check_value(value)
    else:
        value = None  # only the group's rank 0 records a value
    # DOLFINx objects of the job hold duplicated communicators; MPICH has ~2000 ids.
    gc.collect()
    jobcomm.Free()
    if subcomm.rank != 0:
        return JobResult(job.key, "done" if ok else "failed", wall, "", None, group)
    if not ok:
        text = (
            errors[0]
            if subcomm.size == 1
            else "".join(f"[rank {r} of group {group}] {e}" for r, e in enumerate(errors) if e)
        )
        return JobResult(job.key, "failed", wall, text, None, group)
    if value_error:
        return JobResult(job.key, "failed", wall, value_error, None, group)
    return JobResult(job.key, "done", wall, "", value, group)


def _check_value(value) -> str:
    """Why ``work``'s return value cannot be recorded ("" when it can)."""
    if value is not None and not isinstance(value, dict):
        return f"work returned {type(value).__name__}; expected a dict or None"
    try:
        pickle.dumps(value)
    except Exception as err:  # noqa: BLE001 - any pickling failure is reported the same way
        return f"work returned a result that cannot be pickled: {err}"
    return ""


def _last_line(text: str) -> str:
    lines = [line for line in text.strip().splitlines() if line.strip()]
    return lines[-1].strip() if lines else ""


def summary_line(results: Sequence[JobResult]) -> str:
    """One line for the end of a CLI run: counts by status and the failed keys."""
    count = {s: sum(r.status == s for r in results) for s in ("done", "failed", "skipped")}
    line = (
        f"{len(results)} jobs: {count['done']} done, {count['failed']} failed, "
        f"{count['skipped']} skipped (done before)"
    )
    failed = [r.key for r in results if r.status == "failed"]
    return line + (f"; failed: {', '.join(failed)}" if failed else "")
