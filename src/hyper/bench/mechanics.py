"""Mechanics benchmark: quadrature degree, Newton cost, 1 against 2 ranks.

    python -m hyper.bench mechanics [--geometries idealized,BFLH_VHF_Left] [--ranks 1,2]

1. One Jacobian assembly of the mechanics problem with the fixed quadrature degree (4)
   against the degree UFL estimates for the same form, on the same mesh (idealized);
   form compilation is timed separately. The estimated-degree run is a subprocess with
   a time limit (--estimated-timeout): if it does not finish, the limit is reported.
2. A contraction α = 0 → 1 (6 steps) per geometry and rank count, each in its own
   `mpirun -n R` subprocess: time per solve, per Newton iteration, unknowns.

Writes results/bench/mechanics.json and mechanics.png.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ALPHAS = (0.1, 0.2, 0.35, 0.55, 0.8, 1.0)


# ------------------------------------------------------------------ workers (subprocesses)


def _worker_jacobian(geometry_name: str, degree: str) -> dict:
    import dolfinx_solver  # noqa: F401

    import ufl
    from dolfinx import fem
    from mpi4py import MPI
    from ufl.algorithms import expand_derivatives
    from ufl.algorithms.estimate_degrees import estimate_total_polynomial_degree

    from hyper import geometry as geo
    from hyper.mechanics import MechanicsProblem

    comm = MPI.COMM_WORLD
    geometry = geo.load(geometry_name, comm)
    problem = MechanicsProblem(geometry, geo.fiber_field(geometry))
    problem.alpha.value = 0.5
    jacobian = expand_derivatives(problem.jacobian)
    if degree == "estimated":
        jacobian = ufl.Form([itg.reconstruct(metadata={}) for itg in jacobian.integrals()])
    degrees = sorted({estimate_total_polynomial_degree(itg.integrand()) if degree == "estimated" else 4
                      for itg in jacobian.integrals()})
    start = time.perf_counter()
    form = fem.form(jacobian)
    compile_s = time.perf_counter() - start
    A = fem.petsc.create_matrix(form)
    times = []
    for _ in range(3):
        start = time.perf_counter()
        A.zeroEntries()
        fem.petsc.assemble_matrix(A, form)
        A.assemble()
        times.append(time.perf_counter() - start)
    return {"degree": degree, "quadrature_degrees": degrees, "compile_s": compile_s,
            "assemble_s": min(times), "cells": geometry.num_cells(), "unknowns": problem.num_dofs}


def _worker_newton(geometry_name: str) -> dict:
    import dolfinx_solver  # noqa: F401

    from mpi4py import MPI

    from hyper import geometry as geo
    from hyper.mechanics import MechanicsProblem

    comm = MPI.COMM_WORLD
    start = time.perf_counter()
    geometry = geo.load(geometry_name, comm)
    problem = MechanicsProblem(geometry, geo.fiber_field(geometry))
    setup_s = comm.allreduce(time.perf_counter() - start, op=MPI.MAX)
    solves = []
    for alpha in ALPHAS:
        problem.alpha.value = alpha
        comm.barrier()
        start = time.perf_counter()
        iterations = problem.solve()
        solves.append((alpha, iterations, comm.allreduce(time.perf_counter() - start, op=MPI.MAX)))
    iterations = sum(s[1] for s in solves)
    solve_s = sum(s[2] for s in solves)
    return {"geometry": geometry_name, "ranks": comm.size, "cells": geometry.num_cells(),
            "unknowns": problem.num_dofs, "setup_s": setup_s, "solves": solves,
            "newton_iterations": iterations, "solve_s_total": solve_s,
            "s_per_solve": solve_s / len(solves), "s_per_newton_iteration": solve_s / iterations,
            "reaction_force": problem.reaction_force()}


def _run_worker(args: list[str], ranks: int, timeout: float) -> dict | None:
    """Run this module as a worker under mpirun; its JSON result, or None on timeout."""
    mpirun = Path(sys.executable).parent / "mpirun"
    launcher = [str(mpirun) if mpirun.exists() else shutil.which("mpirun"), "-n", str(ranks)]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "result.json"
        cmd = launcher + [sys.executable, "-m", "hyper.bench", "mechanics", "--worker", *args, "--json", str(out)]
        env = dict(os.environ, OMP_NUM_THREADS="1")
        try:
            subprocess.run(cmd, check=True, timeout=timeout, env=env, stdout=subprocess.DEVNULL)
        except subprocess.TimeoutExpired:
            return None
        return json.loads(out.read_text())


# ------------------------------------------------------------------------------- main


def chart(path: Path, result: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    q = result["jacobian_assembly"]
    labels, values, colors = [], [], []
    for key, color in (("fixed", "tab:blue"), ("estimated", "tab:red")):
        entry = q[key]
        degree = ",".join(str(d) for d in entry["quadrature_degrees"]) if entry.get("quadrature_degrees") else "?"
        labels.append(f"{key}\n(degree {degree})")
        values.append(entry["assemble_s"] if entry.get("assemble_s") else q["estimated_timeout_s"])
        colors.append(color)
    bars = ax1.bar(labels, values, color=colors)
    ax1.set_yscale("log")
    ax1.set_ylabel("one Jacobian assembly (s)")
    ax1.set_title(f"{q['geometry']}, {q['fixed']['cells']} cells")
    for bar, entry in zip(bars, (q["fixed"], q["estimated"])):
        text = f"{entry['assemble_s']:.3g} s" if entry.get("assemble_s") else "timed out"
        ax1.annotate(text, (bar.get_x() + bar.get_width() / 2, bar.get_height()), ha="center", va="bottom")

    runs = result["newton"]
    names = list(dict.fromkeys(r["geometry"] for r in runs))
    ranks = sorted({r["ranks"] for r in runs})
    width = 0.8 / max(len(ranks), 1)
    for i, nr in enumerate(ranks):
        xs, ys = [], []
        for j, name in enumerate(names):
            match = [r for r in runs if r["geometry"] == name and r["ranks"] == nr]
            if match:
                xs.append(j + (i - (len(ranks) - 1) / 2) * width)
                ys.append(match[0]["s_per_newton_iteration"])
        ax2.bar(xs, ys, width=width, label=f"{nr} rank(s)")
    ax2.set_xticks(range(len(names)))
    ax2.set_xticklabels([f"{n}\n{next(r['unknowns'] for r in runs if r['geometry'] == n)} unknowns" for n in names])
    ax2.set_ylabel("time per Newton iteration (s)")
    ax2.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m hyper.bench mechanics", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--geometries", default="idealized,BFLH_VHF_Left")
    parser.add_argument("--ranks", default="1,2")
    parser.add_argument("--quadrature-geometry", default="idealized")
    parser.add_argument("--estimated-timeout", type=float, default=900.0, help="seconds")
    parser.add_argument("--output-dir", default="results/bench")
    parser.add_argument("--worker", nargs="+", help=argparse.SUPPRESS)
    parser.add_argument("--json", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)

    if args.worker:
        kind, *rest = args.worker
        result = _worker_jacobian(*rest) if kind == "jacobian" else _worker_newton(*rest)
        from mpi4py import MPI

        if MPI.COMM_WORLD.rank == 0:
            Path(args.json).write_text(json.dumps(result))
        return 0

    from hyper.geometry import GEOMETRIES

    geometries = args.geometries.split(",")
    unknown = [g for g in geometries + [args.quadrature_geometry] if g not in GEOMETRIES]
    if unknown:
        print(f"error: unknown geometry {unknown[0]!r}; known: {', '.join(GEOMETRIES)}", file=sys.stderr)
        return 2
    ranks = [int(r) for r in args.ranks.split(",")]

    started = time.perf_counter()
    print(f"Jacobian assembly, fixed degree 4 vs UFL estimate, on {args.quadrature_geometry}", flush=True)
    fixed = _run_worker(["jacobian", args.quadrature_geometry, "4"], 1, args.estimated_timeout)
    estimated = _run_worker(["jacobian", args.quadrature_geometry, "estimated"], 1, args.estimated_timeout)
    quadrature = {"geometry": args.quadrature_geometry, "fixed": fixed,
                  "estimated": estimated or {"timed_out": True}, "estimated_timeout_s": args.estimated_timeout}
    if estimated:
        quadrature["assembly_ratio_estimated_over_fixed"] = estimated["assemble_s"] / fixed["assemble_s"]
        quadrature["compile_ratio_estimated_over_fixed"] = estimated["compile_s"] / fixed["compile_s"]
    print(json.dumps(quadrature, indent=1), flush=True)

    newton = []
    for name in geometries:
        for nr in ranks:
            print(f"contraction {name} on {nr} rank(s)", flush=True)
            run = _run_worker(["newton", name], nr, 3600)
            newton.append(run)
            print(f"  {run['unknowns']} unknowns, {run['newton_iterations']} Newton iterations, "
                  f"{run['s_per_newton_iteration']:.3f} s per iteration, {run['s_per_solve']:.2f} s per solve",
                  flush=True)
    for run in newton:
        serial = [r for r in newton if r["geometry"] == run["geometry"] and r["ranks"] == 1]
        if serial and run["ranks"] > 1:
            run["speedup_per_iteration_vs_1_rank"] = serial[0]["s_per_newton_iteration"] / run["s_per_newton_iteration"]

    result = {
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                    "note": "shared 2-core machine: absolute times vary, ratios measured side by side"},
        "jacobian_assembly": quadrature,
        "newton": newton,
        "alphas": ALPHAS,
        "wall_s": time.perf_counter() - started,
    }
    out = Path(args.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "mechanics.json").write_text(json.dumps(result, indent=1))
    chart(out / "mechanics.png", result)
    print(f"wrote {out / 'mechanics.json'} and {out / 'mechanics.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
