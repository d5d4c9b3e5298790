"""Mesh refinement benchmark: the reaction force's convergence and the direct solver's memory.

    python -m hyper.bench refinement [--levels 3] [--output results/bench]

The idealized shape at full activation (α = 1) on the given mesh and its uniform
refinements (every tetrahedron into eight, h → h/2). Level 0 ramps α in 6 steps; each
finer level starts from the coarser solution (nested iteration) and needs a few
Newton steps. Per level: unknowns, the end force on Γ1 (the axial resultant d·∫ P N dA,
the headline of `hyper contraction`), the tendon spring's axial resultant (equal to it
by equilibrium), the reaction forces as the original code defined it (∫ (σN)·N dA,
MODEL.md §9) and along the current normal, Newton iterations, wall time, and
what MUMPS reports about its LU factors: the memory its analysis estimated and the
memory the factorisation used (INFOG 17 and 22, summed over ranks), and the factor's
entries (INFOG 29).

From three levels, the observed order of each force, p = log2(|R1 - R0| / |R2 - R1|),
and its Richardson limit. From the memory at each level, a power law m = a n^b in the
unknowns n, and the n at which the factorisation would need the machine's memory
(--memory-gib, default 24 GiB less 2 GiB for the rest): the mesh size beyond which LU
runs out of memory, estimated from measured growth rather than by crashing the machine.

Level 2 has 578k unknowns; its factorisation takes about 12 GB and minutes on one
rank. Writes results/bench/refinement.json and refinement.png.
"""

from __future__ import annotations

import resource
import time
from pathlib import Path

import numpy as np

from hyper.commands import cli
from hyper.commands.bench import common
from hyper.core import io
from hyper.core.log import info
from hyper.core.params import InputError
from hyper.fem import fibers
from hyper.fem import geometry as geo
from hyper.fem.mechanics import MechanicsProblem
from hyper.runs import plot

ALPHAS = (0.1, 0.2, 0.35, 0.55, 0.8, 1.0)
FORCES = ("end_force", "spring_force", "reaction_force_original", "reaction_force_current")


def run_levels(comm, levels: int, log=print) -> list[dict]:
    import dolfinx_solver  # noqa: F401
    from mpi4py import MPI


    geometry = geo.load("idealized", comm)
    rows, previous = [], None
    for level in range(levels):
        start = time.perf_counter()
        problem = MechanicsProblem(geometry, fibers.fiber_field(geometry))
        setup_s = time.perf_counter() - start
        start = time.perf_counter()
        if previous is None:
            iterations = 0
            for alpha in ALPHAS:
                problem.alpha.value = alpha
                iterations += problem.solve()
        else:
            problem.start_from(previous)
            iterations = problem.solve()
        solve_s = time.perf_counter() - start
        rss_mb = comm.allreduce(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, op=MPI.SUM) / 1024
        row = {"level": level, "cells": geometry.num_cells(), "unknowns": problem.num_dofs,
               "end_force": problem.end_force(), "spring_force": problem.spring_force(),
               "reaction_force_original": problem.reaction_force_original(),
               "reaction_force_current": problem.reaction_force_current(), "newton_iterations": iterations,
               "setup_s": comm.allreduce(setup_s, op=MPI.MAX), "solve_s": comm.allreduce(solve_s, op=MPI.MAX),
               "peak_rss_mb_sum": rss_mb, **problem.mumps_memory()}
        rows.append(row)
        log(f"level {level}: {row['unknowns']} unknowns, end force {row['end_force']:.6f} N, "
            f"spring {row['spring_force']:.6f} N, original R {row['reaction_force_original']:.6f} N, "
            f"R along n {row['reaction_force_current']:.6f} N, "
            f"{iterations} Newton its in {row['solve_s']:.0f} s, MUMPS {row['mumps_used_mb']} MB")
        previous = problem
        if level + 1 < levels:
            geometry = geo.refine(geometry)
    return rows


def observed_orders(rows: list[dict], key: str) -> dict:
    """Order and Richardson limit from the last three levels (h halves each level)."""
    values = [r[key] for r in rows]
    out = {"values": values}
    if len(values) >= 3:
        d1, d2 = values[-2] - values[-3], values[-1] - values[-2]
        order = float(np.log2(abs(d1 / d2)))
        out.update(order=order, richardson_limit=values[-1] + d2 / (2.0**order - 1.0),
                   changes=[float(d1), float(d2)])
    return out


def memory_fit(rows: list[dict], key: str = "mumps_used_mb") -> dict | None:
    """m = a n^b through the two largest runs that have ``key`` (the asymptotic slope)."""
    rows = sorted((r for r in rows if key in r and "failed" not in r), key=lambda r: r["unknowns"])
    if len(rows) < 2:
        return None
    n = np.log([rows[-2]["unknowns"], rows[-1]["unknowns"]])
    m = np.log([rows[-2][key], rows[-1][key]])
    b = (m[1] - m[0]) / (n[1] - n[0])
    return {"exponent": float(b), "coefficient_mb": float(np.exp(m[1] - b * n[1]))}


def memory_limit(rows: list[dict], memory_gib: float) -> dict:
    """Fit m = a n^b to the measured factorisation memory and solve m(n) = memory."""
    fit = memory_fit(rows)
    limit_mb = memory_gib * 1024.0
    return {**fit, "memory_gib": memory_gib,
            "unknowns_at_limit": float((limit_mb / fit["coefficient_mb"]) ** (1.0 / fit["exponent"]))}


def chart(path: Path, result: dict) -> None:
    plt = plot.pyplot()
    rows = result["levels"]
    h = np.array([2.0 ** -r["level"] for r in rows])
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    for key, label in (("end_force", "end force d·∫ P N dA (resultant)"),
                       ("reaction_force_original", "∫ (σN)·N dA (original)"),
                       ("reaction_force_current", "R along the current normal")):
        info = result["forces"][key]
        ax1.plot(h, info["values"], "o-", label=label + (f", order {info['order']:.2f}" if "order" in info else ""))
        if "richardson_limit" in info:
            ax1.axhline(info["richardson_limit"], ls=":", color=ax1.lines[-1].get_color(), lw=1)
    ax1.set_xscale("log", base=2)
    ax1.invert_xaxis()
    ax1.set_xlabel("mesh size h / h0")
    ax1.set_ylabel("force at α = 1 (N)")
    ax1.set_title("idealized shape, uniform refinement (dotted: Richardson limits)")
    ax1.legend(fontsize=8)
    fit = result["lu_memory"]
    common.plot_lu_memory(ax2, rows, fit)
    ax2.annotate(f"{fit['memory_gib']:.0f} GiB at ≈ {fit['unknowns_at_limit'] / 1e3:.0f}k unknowns",
                 (fit["unknowns_at_limit"], fit["memory_gib"]), textcoords="offset points", xytext=(-150, 10),
                 fontsize=8)
    ax2.set_ylabel("LU memory (GiB)")
    ax2.set_title(f"direct solver memory ({result['ranks']} rank(s))")
    ax2.legend(fontsize=8)
    fig.tight_layout()
    plot.save(fig, path, dpi=130)


def parser() -> cli.Parser:
    p = cli.Parser("bench refinement", __doc__)
    p.add_argument("--levels", type=cli.integer(1), default=3, help="meshes: the given one and LEVELS-1 refinements")
    p.add_argument("--memory-gib", type=cli.number(), default=22.0,
                   help="memory available to the factorisation, GiB (22: a 24 GiB machine less 2)")
    p.add_argument("--output", type=Path, default=Path("results/bench"), help="output folder")
    return p


def run(comm, args) -> int:
    if not 2 <= args.levels <= 4:
        raise InputError("--levels must be 2, 3 or 4")

    import dolfinx_solver  # noqa: F401


    rows = run_levels(comm, args.levels, log=lambda msg: info(comm, msg))
    result = {"benchmark": "refinement", "ranks": comm.size, "machine": common.machine(), "levels": rows,
              "forces": {k: observed_orders(rows, k)
                         for k in FORCES},
              "lu_memory": memory_limit(rows, args.memory_gib), "versions": io.versions()}
    if comm.rank == 0:
        args.output.mkdir(parents=True, exist_ok=True)
        io.write_json(args.output / "refinement.json", result)
        chart(args.output / "refinement.png", result)
        for key, value in result["forces"].items():
            if "order" in value:
                info(comm, f"{key}: observed order {value['order']:.2f}, "
                           f"Richardson limit {value['richardson_limit']:.6f} N")
        fit = result["lu_memory"]
        info(comm, f"LU memory ∝ n^{fit['exponent']:.2f}: {fit['memory_gib']:g} GiB at "
                   f"{fit['unknowns_at_limit']:.3g} unknowns; wrote {args.output / 'refinement.json'}")
    return 0


main = cli.entry(parser, run)
