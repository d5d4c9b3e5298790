"""Sobol analysis benchmark: 1 rank against 2 ranks, and the compiled RK4 against numpy's.

python -m hyper.bench sobol [--samples N] writes results/bench/sobol.json and sobol.png.

- The whole CLI (``python -m hyper.sobol``) on N base samples, N (2D + 2) evaluations, once
  with ``mpirun -n 1`` and once with ``mpirun -n 2``, one after the other, each from scratch
  in its own folder: the evaluation rate (evaluations per second of the farm phase, read
  from the results' attributes), the total wall time, and the speed-up of 2 ranks over 1.
- The per-core throughput of the two RK4 backends on one batch of sampled parameter sets
  over daily15, in this process: member-steps per second and their ratio.

Timings on a machine shared with other work are inflated; the ratios, measured side by
side, are what to read.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from hyper.analysis import sobol
from hyper.analysis import sobolmodels as models
from hyper.commands import cli
from hyper.commands.bench import common
from hyper.core import io, term
from hyper.model import signaling
from hyper.model.protocols import named
from hyper.runs import plot


def _cli(ranks: int, samples: int, chunk: int, folder: Path) -> dict:
    """One run of the CLI under mpirun; its timings from the HDF5 attributes."""
    import h5py

    mpirun = Path(sys.executable).with_name("mpirun")
    cmd = [str(mpirun), "-n", str(ranks), sys.executable, "-m", "hyper.sobol", "--samples", str(samples),
           "--chunk", str(chunk), "--output", str(folder)]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    start = time.perf_counter()
    with term.spawning():
        done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{done.stdout}\n{done.stderr}")
    with h5py.File(folder / "sobol.h5") as f:
        return {
            "ranks": ranks,
            "evaluations": int(f.attrs["evaluations"]),
            "evaluation_wall_s": float(f.attrs["evaluation_wall_s"]),
            "evaluations_per_s": float(f.attrs["evaluations_per_s"]),
            "evaluation_cpu_s": float(f.attrs["evaluation_cpu_s"]),
            "evaluations_per_cpu_s": int(f.attrs["evaluations"]) / float(f.attrs["evaluation_cpu_s"]),
            "cpu_share": float(f.attrs["cpu_share"]),
            "analysis_wall_s": float(f.attrs["wall_s"]),
            "process_wall_s": wall,
            "failures": int(f.attrs["failures"]),
            "S1": f["S1"][()].tolist(),
        }


def _backends(members: int) -> dict:
    X = sobol.sample(sobol.problem(), max(2, -(-members // 30)), seed=11)[:members]
    protocol = named("daily15")
    steps = signaling.step_count(models.sample_params(X[:2]), protocol, 0.0, protocol.end)
    if signaling.c_backend_error() is not None:  # builds or loads the kernel before timing
        raise RuntimeError(f"the C backend is unavailable: {signaling.c_backend_error()}")
    out = {"members": int(X.shape[0]), "steps": steps}
    values = {}
    for backend in ("c", "numpy"):
        start = time.process_time()
        values[backend] = models.final_N(X, backend=backend)
        cpu = time.process_time() - start
        out[backend] = {"cpu_s": cpu, "member_steps_per_s": X.shape[0] * steps / cpu}
    out["identical"] = bool(np.array_equal(values["c"], values["numpy"]))
    out["ratio_c_over_numpy"] = out["c"]["member_steps_per_s"] / out["numpy"]["member_steps_per_s"]
    return out


def parser() -> cli.Parser:
    p = cli.Parser("bench sobol", __doc__)
    p.add_argument("--samples", type=cli.integer(1), default=2048, help="base samples per CLI run")
    p.add_argument("--chunk", type=cli.integer(1), default=4096, help="rows per chunk")
    p.add_argument("--members", type=cli.integer(1), default=4096, help="batch of the backend comparison")
    p.add_argument("--output", type=Path, default=Path("results/bench"), help="output folder")
    return p


def run(comm, args) -> int:

    with tempfile.TemporaryDirectory() as tmp:
        runs = [_cli(ranks, args.samples, args.chunk, Path(tmp) / f"n{ranks}") for ranks in (1, 2)]
    one, two = runs
    backends = _backends(args.members)
    result = {
        "machine": common.machine(),
        "versions": io.versions(),
        "samples": args.samples,
        "runs": runs,
        "speedup_2_over_1": two["evaluations_per_s"] / one["evaluations_per_s"],
        # evaluations per CPU-second of all ranks: 1 when the second rank costs nothing beyond its
        # own work; the wall-clock speed-up is then bounded by the CPU the ranks got
        "cpu_efficiency_2_over_1": two["evaluations_per_cpu_s"] / one["evaluations_per_cpu_s"],
        "same_indices": one["S1"] == two["S1"],
        "backends": backends,
    }
    args.output.mkdir(parents=True, exist_ok=True)
    io.write_json(args.output / "sobol.json", result)

    plt = plot.pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.6))
    a.bar(["1 rank", "2 ranks"], [r["evaluations_per_s"] for r in runs], color=["tab:blue", "tab:orange"])
    a.set_ylabel("evaluations / s")
    a.set_title(f"N = {args.samples}: speed-up {result['speedup_2_over_1']:.2f}x")
    b.bar(["compiled (c)", "numpy"], [backends[k]["member_steps_per_s"] for k in ("c", "numpy")],
          color=["tab:green", "tab:gray"])
    b.set_yscale("log")
    b.set_ylabel("member-steps / s / core")
    b.set_title(f"RK4 backends: {backends['ratio_c_over_numpy']:.1f}x")
    fig.tight_layout()
    plot.save(fig, args.output / "sobol.png", dpi=120)

    print(f"1 rank: {one['evaluations_per_s']:.0f} evaluations/s ({one['evaluation_wall_s']:.1f} s), "
          f"2 ranks: {two['evaluations_per_s']:.0f} evaluations/s ({two['evaluation_wall_s']:.1f} s): "
          f"speed-up {result['speedup_2_over_1']:.2f}; same indices: {result['same_indices']}")
    print(f"share of their cores the ranks got: {100 * one['cpu_share']:.0f} % (1 rank), "
          f"{100 * two['cpu_share']:.0f} % "
          f"(2 ranks); evaluations per CPU-second, 2 ranks over 1: {result['cpu_efficiency_2_over_1']:.2f}")
    print(f"RK4 per core: compiled {backends['c']['member_steps_per_s']:.3g}, numpy "
          f"{backends['numpy']['member_steps_per_s']:.3g} member-steps/s ({backends['ratio_c_over_numpy']:.1f}x), "
          f"identical: {backends['identical']}")
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores; -> {args.output / 'sobol.json'}")
    return 0


# Only its child processes use MPI.
main = cli.entry(parser, run, world=False)
