"""What the benchmarks share: the machine they ran on, workers in fresh processes, and
a monitor that records where a coupled run spends its time.

A worker is the benchmark's own module started again with ``--worker CASE --json OUT``
(`add_worker_options`): a fresh process has its own PETSc state, CPU clock and peak
memory, so configurations measured one after another do not disturb each other.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from hyper.core import term


def machine() -> dict:
    """The host, its cores and its load now: a shared machine's absolute times vary, so
    every result says where and under what load it was measured."""
    return {"host": platform.node(), "cpus": os.cpu_count(), "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(), "load_average_at_start": os.getloadavg()}


def add_worker_options(parser: argparse.ArgumentParser) -> None:
    """The hidden options a worker process is started with."""
    parser.add_argument("--worker", type=json.loads, help=argparse.SUPPRESS)
    parser.add_argument("--json", type=Path, help=argparse.SUPPRESS)


def write_worker_result(comm, path: Path, result: dict) -> None:
    if comm.rank == 0:
        Path(path).write_text(json.dumps(result, default=float))


def _mpirun() -> str:
    beside = Path(sys.executable).with_name("mpirun")
    return str(beside) if beside.exists() else shutil.which("mpirun") or "mpirun"


def run_worker(bench: str, case: dict, ranks: int, timeout: float, extra: tuple[str, ...] = ()) -> dict:
    """``python -m hyper.bench BENCH --worker CASE --json OUT EXTRA…`` in a fresh process,
    under mpirun for several ranks.

    Returns the result the worker wrote, with the process's wall time and the load
    averages before and after; or the case with ``failed``: the timeout, or the last
    lines of the worker's error output.
    """
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "result.json"
        cmd = [sys.executable, "-m", "hyper.bench", bench, "--worker", json.dumps(case), "--json", str(out), *extra]
        if ranks > 1:
            cmd = [_mpirun(), "-n", str(ranks), *cmd]
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        load = os.getloadavg()
        start = time.perf_counter()
        try:
            with term.spawning():
                subprocess.run(cmd, check=True, timeout=timeout, env=env, stderr=subprocess.PIPE, text=True)
        except subprocess.TimeoutExpired:
            return {**case, "failed": f"no result within {timeout:g} s"}
        except subprocess.CalledProcessError as err:
            return {**case, "failed": "\n".join((err.stderr or "").strip().splitlines()[-5:])}
        result = json.loads(out.read_text())
        result["process_wall_s"] = time.perf_counter() - start
        result["load_average_before"], result["load_average_after"] = load, os.getloadavg()
        return result


class Timings:
    """A `hyper.fem.coupled.CoupledModel` monitor: wall seconds and calls per phase."""

    def __init__(self):
        self.seconds: defaultdict[str, float] = defaultdict(float)
        self.calls: defaultdict[str, int] = defaultdict(int)

    @contextlib.contextmanager
    def track(self, name: str):
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] += time.perf_counter() - start
            self.calls[name] += 1


def plot_lu_memory(ax, levels: list[dict], fit: dict) -> None:
    """MUMPS LU's memory against the unknowns on log axes: the measured levels, the power
    law fitted to them (bench refinement's ``lu_memory``) and where it meets the memory."""

    n = np.array([r["unknowns"] for r in levels], dtype=float)
    m = np.array([r["mumps_used_mb"] for r in levels], dtype=float) / 1024.0
    grid = np.geomspace(n[0], fit["unknowns_at_limit"] * 1.5, 50)
    ax.loglog(n, m, "o", label="MUMPS LU, measured")
    ax.loglog(grid, fit["coefficient_mb"] * grid ** fit["exponent"] / 1024.0, "--",
              label=f"fit ∝ n^{fit['exponent']:.2f}")
    ax.axhline(fit["memory_gib"], color="k", lw=1)
    ax.axvline(fit["unknowns_at_limit"], color="k", ls=":", lw=1)
    ax.set_xlabel("unknowns")
