"""Chunked evaluation of the rows of a sample matrix, farmed over MPI ranks.

The rows are evaluated in chunks, jobs of ``hyper.runs.farm``. Each finished chunk is
written atomically to ``<folder>/<digest>/``, the digest (`digest`) covering the sample
matrix and every setting, so a rerun skips finished chunks and never reuses chunks of a
different run (`remove_stale` removes those).
"""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from mpi4py import MPI

from hyper.core import io
from hyper.core.log import PROGRESS_EVERY
from hyper.runs import farm
from hyper.runs.farm import Job


def digest(X: np.ndarray, settings: dict) -> str:
    """What a chunk's outputs depend on: the sample matrix and every setting."""
    h = hashlib.sha256(np.ascontiguousarray(X, dtype=float).tobytes())
    h.update(json.dumps(settings, sort_keys=True, default=str).encode())
    return h.hexdigest()[:16]


def chunk_jobs(rows: int, chunk: int):
    return [Job(f"rows_{a:09d}_{min(a + chunk, rows):09d}", cost=float(min(a + chunk, rows) - a),
                payload=(a, min(a + chunk, rows))) for a in range(0, rows, chunk)]


def _chunk_ok(path: Path, key: str, start: int, stop: int) -> bool:
    try:
        with np.load(path) as f:
            return (bool(f["complete"]) and str(f["digest"]) == key and int(f["start"]) == start
                    and int(f["stop"]) == stop and f["Y"].shape == (stop - start,))
    except Exception:  # noqa: BLE001 - unreadable in any way (truncated, not a zip, ...) means not done
        return False


def run_chunks(comm, X: np.ndarray, evaluate: Callable[[np.ndarray], np.ndarray], folder: Path, key: str,
               chunk: int, label: str = "sobol", stop: Callable[[], bool] | None = None,
               progress_every: float = PROGRESS_EVERY):
    """Evaluate every row of X in chunks farmed over ``comm``; collective.

    Each chunk is written atomically to ``folder/<key>/<job key>.npz`` with its row range,
    the digest ``key`` and a complete mark; chunks already there are skipped. Once
    ``stop()`` turns true (SIGTERM) the chunks in progress finish and are written, and the
    others are not started: their results are ``{"interrupted": True}``. Returns (Y, farm
    results): Y, all outputs in row order, on rank 0 (None elsewhere, and None on rank 0
    too if a chunk failed or was not computed).
    """
    where = Path(folder) / key
    jobs = chunk_jobs(X.shape[0], chunk)

    def path(job):
        return where / f"{job.key}.npz"

    def is_done(job):
        return _chunk_ok(path(job), key, *job.payload)

    def work(subcomm, job):
        if subcomm.allreduce(bool(stop is not None and stop()), op=MPI.LOR):
            return {"interrupted": True}
        first, last = job.payload
        Y = np.asarray(evaluate(X[first:last]), dtype=float)
        if Y.shape != (last - first,):
            raise ValueError(f"the evaluator returned shape {Y.shape} for {last - first} rows")
        with io.atomic_path(path(job)) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, Y=Y, start=first, stop=last, digest=key, complete=True)
        return {"failed": int((~np.isfinite(Y)).sum())}

    results = farm.run(comm, jobs, work, is_done=is_done, label=label, progress_every=progress_every)
    Y = None
    if comm.rank == 0 and all(r.status != "failed" and not interrupted(r) for r in results):
        Y = np.empty(X.shape[0])
        for job in jobs:
            with np.load(path(job)) as f:
                Y[job.payload[0]:job.payload[1]] = f["Y"]
    return Y, results


def interrupted(result) -> bool:
    """A chunk that a SIGTERM kept from starting."""
    return result.status == "done" and bool(result.result) and bool(result.result.get("interrupted"))


def remove_stale(folder: Path, key: str) -> list[str]:
    """Remove the chunk folders of other runs (other digests) under ``folder``; their names."""
    stale = sorted(p.name for p in Path(folder).glob("*") if p.is_dir() and p.name != key)
    for name in stale:
        shutil.rmtree(Path(folder) / name, ignore_errors=True)
    return stale


def idle_barrier(comm) -> None:
    """A barrier at which waiting ranks sleep: MPICH's blocking calls spin, and a spinning rank
    would take a core from rank 0 while it samples or analyses alone."""
    request = comm.Ibarrier()
    while not request.Test():
        time.sleep(0.02)
