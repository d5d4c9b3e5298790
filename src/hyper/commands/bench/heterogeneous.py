"""Heterogeneous signaling benchmark: per-cell RK4 throughput and the signaling share of a coupled run.

python -m hyper.bench heterogeneous [--geometry BFLH_VHF_Left] [--end 336] writes
results/bench/heterogeneous.json and heterogeneous.png. Runs on any number of ranks
(each rank integrates its own cells); run it with OMP_NUM_THREADS=1.

- Throughput: the per-cell ODEs of the mesh's owned cells (uniform noise, ε = 0.01) over
  one training week of ``mwf`` (168 h to 336 h, three sessions), on the numpy and the
  compiled backend side by side, in cell-steps per CPU-second of the rank (CPU time, so
  the number stands on a shared machine), and whether both give the same bits.
- Shares: one heterogeneous coupled run (ε = 0.01) of ``mwf`` cut at --end hours, with
  the wall time of its signaling, of the Newton solves, of the CSA and volume measures
  and of the growth-tensor updates (the model's phases, timed by its monitor), as
  shares of the run's wall time.
  The goal is signaling under 10 %.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
import numpy as np
from mpi4py import MPI

from hyper.commands import cli
from hyper.commands.bench import common
from hyper.core import io
from hyper.core.log import info
from hyper.fem.coupled import GrowthSettings
from hyper.model import heterogeneity, protocols, signaling
from hyper.runs import plot
from hyper.runs.driver import build
from hyper.runs.runspec import RunSpec

WINDOW = (168.0, 336.0)  # h: the first training week of mwf


def throughput(comm, params, y0, window=WINDOW) -> dict:
    protocol = protocols.named("mwf")
    n = params.size
    steps = signaling.step_count(params, protocol, *window)
    if signaling.c_backend_error() is not None:  # builds or loads the kernel before timing
        raise RuntimeError(f"the C backend is unavailable: {signaling.c_backend_error()}")
    out = {"cells_per_rank": comm.allgather(n), "steps": steps, "window_h": list(window)}
    finals = {}
    for backend in ("c", "numpy"):
        comm.barrier()
        start = time.process_time()
        _, ys = signaling.integrate(params, protocol, y0, *window, backend=backend)
        cpu = time.process_time() - start
        finals[backend] = ys[-1]
        rates = comm.allgather(n * steps / cpu)
        out[backend] = {"cpu_s": comm.allgather(cpu), "cell_steps_per_cpu_s_per_rank": rates,
                        "mean": float(np.mean(rates))}
    out["identical"] = bool(comm.allreduce(bool(np.array_equal(finals["c"], finals["numpy"])), op=MPI.LAND))
    out["ratio_c_over_numpy"] = out["c"]["mean"] / out["numpy"]["mean"]
    return out


def mwf_until(end: float) -> protocols.Protocol:
    """``mwf`` cut at ``end`` hours."""
    mwf = protocols.named("mwf")
    return protocols.Protocol(tuple(s for s in mwf.sessions if s.start < end), end=end, name=f"mwf_to_{end:g}h")


def shares(comm, model, clock: common.Timings) -> dict:
    """Run ``model`` (built with the monitor ``clock``) to its protocol's end."""
    comm.barrier()
    cpu0, start = time.process_time(), time.perf_counter()
    reports = list(model.run())
    wall = time.perf_counter() - start
    cpu = time.process_time() - cpu0
    parts = {"signaling": clock.seconds["signaling"], "newton": clock.seconds["mechanics"],
             "measures": clock.seconds["measures"], "growth": clock.seconds["growth update"]}
    parts["other"] = wall - sum(parts.values())
    # the slowest rank sets the pace: report rank 0's split with the max wall over ranks
    return {
        "protocol_end_h": model.protocol.end,
        "growth_steps": model.step,
        "solves": clock.calls["mechanics"],
        "newton_iterations": int(sum(r.newton_iterations for r in reports)),
        "signaling_calls": clock.calls["signaling"],
        "wall_s": wall,
        "wall_s_max_over_ranks": comm.allreduce(wall, op=MPI.MAX),
        "cpu_share": cpu / wall,
        "seconds": parts,
        "shares": {k: v / wall for k, v in parts.items()},
        "csa_ratio": reports[-1].csa_ratio,
        "volume_ratio": reports[-1].volume_ratio,
    }


def chart(result: dict, path: Path) -> None:
    plt = plot.pyplot()
    t, s = result["throughput"], result["coupled"]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.8))
    a.bar(["compiled (c)", "numpy"], [t["c"]["mean"], t["numpy"]["mean"]], color=["tab:green", "tab:gray"])
    a.set_yscale("log")
    a.set_ylabel("cell-steps / CPU-s / rank")
    a.set_title(f"per-cell RK4, {sum(t['cells_per_rank'])} cells: {t['ratio_c_over_numpy']:.0f}x")
    names = list(s["shares"])
    b.barh(names, [100 * s["shares"][k] for k in names], color="tab:blue")
    b.set_xlabel("share of the coupled run's wall time (%)")
    b.set_title(f"heterogeneous coupled run to {s['protocol_end_h']:g} h ({s['wall_s']:.0f} s)")
    for i, k in enumerate(names):
        b.text(100 * s["shares"][k], i, f" {100 * s['shares'][k]:.1f} %", va="center", fontsize=8)
    fig.tight_layout()
    plot.save(fig, path, dpi=120)


def parser() -> cli.Parser:
    p = cli.Parser("bench heterogeneous", __doc__)
    p.add_argument("--geometry", default="BFLH_VHF_Left", help="the mesh")
    p.add_argument("--end", type=cli.number(), default=336.0, help="end of the cut mwf protocol (h)")
    p.add_argument("--growth-dt", type=cli.positive("hours"), default=GrowthSettings.growth_dt, help="growth step (h)")
    p.add_argument("--output", type=Path, default=Path("results/bench"), help="output folder")
    return p


def run(comm, args) -> int:
    host = common.machine()
    load_start = host["load_average_at_start"]
    spec = RunSpec(args.geometry, mwf_until(args.end), settings=GrowthSettings(growth_dt=args.growth_dt),
                   heterogeneity=heterogeneity.Heterogeneity(epsilon=0.01), seed=1)
    clock = common.Timings()
    model = build(comm, spec, monitor=clock)[0]
    # the throughput integrates the per-cell parameters of the coupled run
    y0 = np.repeat(signaling.rest_state()[:, None], model.params.size, axis=1)
    result = {
        "machine": {**host, "ranks": comm.size},
        "versions": io.versions(),
        "geometry": args.geometry,
        "throughput": throughput(comm, model.params, y0),
        "coupled": shares(comm, model, clock),
    }
    result["machine"]["load_average_at_end"] = os.getloadavg()
    if comm.rank == 0:
        args.output.mkdir(parents=True, exist_ok=True)
        io.write_json(args.output / "heterogeneous.json", result)
        chart(result, args.output / "heterogeneous.png")
    t, s = result["throughput"], result["coupled"]
    info(comm, f"per-cell RK4 on {sum(t['cells_per_rank'])} cells ({comm.size} rank(s)): compiled "
               f"{t['c']['mean']:.3g}, numpy {t['numpy']['mean']:.3g} cell-steps/CPU-s/rank "
               f"({t['ratio_c_over_numpy']:.0f}x), identical: {t['identical']}")
    info(comm, f"coupled run to {args.end:g} h: {s['wall_s']:.1f} s, " + ", ".join(
        f"{k} {100 * v:.1f} %" for k, v in s["shares"].items()) + f" (CPU share {100 * s['cpu_share']:.0f} %)")
    info(comm, f"load average {load_start[0]:.2f} -> {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores; "
               f"-> {args.output / 'heterogeneous.json'}")
    return 0


main = cli.entry(parser, run)
