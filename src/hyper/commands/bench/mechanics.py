"""Mechanics benchmark: quadrature degree, Newton cost, 1 against 2 ranks.

    python -m hyper.bench mechanics [--geometries idealized BFLH_VHF_Left] [--ranks 1 2]

1. One Jacobian assembly of the mechanics problem with the fixed quadrature degree (4)
   against the degree UFL estimates for the same form, on the same mesh (idealized),
   each in a subprocess with a time limit (--estimated-timeout); compile_s is the
   form compilation (near zero when the JIT cache already holds the form).
   The estimate (what FFCx uses without a degree: 76 on the cells, 132 on the spring
   facets, 59319 and 4489 points) cannot be compiled here: FFCx asks
   for a 26 GiB table. Its failure is recorded, and degrees 4, 8, 12, 16 are timed to
   extrapolate the assembly time linearly in the number of quadrature points.
2. A contraction α = 0 → 1 (6 steps) per geometry and rank count, each in its own
   process (`mpirun -n R` for R > 1): time per solve, per Newton iteration, unknowns.

Writes results/bench/mechanics.json and mechanics.png (--output: another folder).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from hyper.commands import cli
from hyper.commands.bench import common
from hyper.core import io
from hyper.core.params import InputError
from hyper.fem import fibers
from hyper.fem import geometry as geo
from hyper.fem.geometry import GEOMETRIES
from hyper.fem.mechanics import MechanicsProblem
from hyper.runs import plot
from hyper.runs.contraction import advance

ALPHAS = (0.1, 0.2, 0.35, 0.55, 0.8, 1.0)


# ------------------------------------------------------------------ workers (subprocesses)


def estimated_degrees(form) -> dict[str, int]:
    """The quadrature degree FFCx would use per integral type when none is given."""
    import ufl
    from ufl.algorithms import compute_form_data

    bare = ufl.Form([itg.reconstruct(metadata={}) for itg in form.integrals()])
    data = compute_form_data(bare, do_apply_function_pullbacks=True, do_apply_integral_scaling=True,
                             do_apply_geometry_lowering=True, preserve_geometry_types=(ufl.classes.Jacobian,),
                             do_apply_restrictions=True, do_append_everywhere_integrals=False)
    return {d.integral_type: max(i.metadata()["estimated_polynomial_degree"] for i in d.integrals)
            for d in data.integral_data}


def quadrature_points(degree: int, cell: str) -> int:
    import basix

    return len(basix.make_quadrature(getattr(basix.CellType, cell), degree)[1])


def _worker_jacobian(geometry_name: str, degree: str) -> dict:
    import dolfinx_solver  # noqa: F401
    import ufl
    from dolfinx import fem
    from mpi4py import MPI


    comm = MPI.COMM_WORLD
    geometry = geo.load(geometry_name, comm)
    problem = MechanicsProblem(geometry, fibers.fiber_field(geometry))
    problem.alpha.value = 0.5
    estimate = estimated_degrees(problem.jacobian)
    degrees = dict(estimate)
    if degree == "estimated":
        jacobian = ufl.Form([itg.reconstruct(metadata={}) for itg in problem.jacobian.integrals()])
    else:
        degrees = {kind: int(degree) for kind in degrees}
        jacobian = ufl.Form([itg.reconstruct(metadata={"quadrature_degree": int(degree)})
                             for itg in problem.jacobian.integrals()])
    points = {"cell": quadrature_points(degrees["cell"], "tetrahedron"),
              "exterior_facet": quadrature_points(degrees["exterior_facet"], "triangle")}
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
    return {"degree": degree, "quadrature_degrees": degrees, "estimated_degrees": estimate,
            "quadrature_points": points,
            "compile_s": compile_s, "assemble_s": min(times), "cells": geometry.num_cells(),
            "unknowns": problem.num_dofs}


def _worker_newton(geometry_name: str) -> dict:
    import dolfinx_solver  # noqa: F401
    from mpi4py import MPI


    comm = MPI.COMM_WORLD
    start = time.perf_counter()
    geometry = geo.load(geometry_name, comm)
    problem = MechanicsProblem(geometry, fibers.fiber_field(geometry))
    setup_s = comm.allreduce(time.perf_counter() - start, op=MPI.MAX)
    solves = []
    for alpha in ALPHAS:
        comm.barrier()
        start = time.perf_counter()
        iterations, halvings = advance(problem, alpha, 4)
        solves.append((alpha, iterations, halvings, comm.allreduce(time.perf_counter() - start, op=MPI.MAX)))
    iterations = sum(s[1] for s in solves)
    solve_s = sum(s[3] for s in solves)
    return {"geometry": geometry_name, "ranks": comm.size, "cells": geometry.num_cells(),
            "unknowns": problem.num_dofs, "setup_s": setup_s, "solves": solves,
            "newton_iterations": iterations, "solve_s_total": solve_s,
            "s_per_solve": solve_s / len(solves), "s_per_newton_iteration": solve_s / iterations,
            "reaction_force_original": problem.reaction_force_original()}


# ------------------------------------------------------------------------------- main


def chart(path: Path, result: dict) -> None:
    plt = plot.pyplot()
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    q = result["jacobian_assembly"]
    labels, values = [], []
    for degree, run in q["runs"].items():
        if "assemble_s" in run:
            labels.append(f"{degree}\n{run['quadrature_points']['cell']} pts")
            values.append(run["assemble_s"])
    labels.append(f"UFL estimate {q['estimated_degrees']['cell']}\n{q['estimated_cell_points']} pts")
    values.append(q["extrapolated_estimated_assemble_s"])
    bars = ax1.bar(range(len(values)), values, color=["tab:blue"] * (len(values) - 1) + ["tab:red"])
    if not q["estimated_compiled"]:
        bars[-1].set_hatch("//")
        bars[-1].set_alpha(0.5)
    ax1.set_xticks(range(len(values)))
    ax1.set_xticklabels(labels, fontsize=8)
    ax1.set_yscale("log")
    ax1.set_xlabel("quadrature degree (cells)")
    ax1.set_ylabel("one Jacobian assembly (s)")
    ax1.set_title(f"{q['geometry']}: {q['runs']['4']['cells']} cells, {q['runs']['4']['unknowns']} unknowns",
                  fontsize=9)
    for i, v in enumerate(values):
        note = f"{v:.3g} s" + ("\n(extrapolated;\ndoes not compile)"
                               if i == len(values) - 1 and not q["estimated_compiled"] else "")
        ax1.annotate(note, (i, v), ha="center", va="bottom", fontsize=8)

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
    plot.save(fig, path, dpi=120)


def parser() -> cli.Parser:
    p = cli.Parser("bench mechanics", __doc__)
    p.add_argument("--geometries", nargs="+", metavar="ID", default=["idealized", "BFLH_VHF_Left"],
                   help="geometries of the contractions")
    p.add_argument("--ranks", nargs="+", type=cli.integer(1), metavar="N", default=[1, 2],
                   help="rank counts of the contractions")
    p.add_argument("--quadrature-geometry", default="idealized", help="the mesh of the quadrature comparison")
    p.add_argument("--estimated-timeout", type=cli.number(), default=900.0,
                   help="seconds per Jacobian assembly of the quadrature comparison before it counts as failed")
    p.add_argument("--output", type=Path, default=Path("results/bench"), help="output folder")
    common.add_worker_options(p)
    return p


def run(comm, args) -> int:
    if args.worker:
        case = args.worker
        if case["kind"] == "jacobian":
            result = _worker_jacobian(case["geometry"], case["degree"])
        else:
            result = _worker_newton(case["geometry"])
        common.write_worker_result(comm, args.json, result)
        return 0


    unknown = [g for g in args.geometries + [args.quadrature_geometry] if g not in GEOMETRIES]
    if unknown:
        raise InputError(f"unknown geometry {unknown[0]!r}; known: {', '.join(GEOMETRIES)}")
    if min(args.ranks) < 1:
        raise InputError(f"--ranks: expected positive rank counts, got {' '.join(map(str, args.ranks))}")

    started = time.perf_counter()
    host = common.machine()
    print(f"Jacobian assembly, fixed degree 4 vs UFL estimate, on {args.quadrature_geometry}", flush=True)
    runs = {}
    for degree in ("4", "8", "12", "16", "estimated"):
        case = {"kind": "jacobian", "geometry": args.quadrature_geometry, "degree": degree}
        runs[degree] = common.run_worker("mechanics", case, 1, args.estimated_timeout)
        print(f"  degree {degree}: {runs[degree]}", flush=True)
    fixed, estimated = runs["4"], runs["estimated"]
    timed = [r for r in runs.values() if "assemble_s" in r]
    # assembly time ≈ a + b · (cell points): least squares over the degrees that ran
    pts = np.array([r["quadrature_points"]["cell"] for r in timed], dtype=float)
    secs = np.array([r["assemble_s"] for r in timed])
    a, b = np.linalg.lstsq(np.vstack([np.ones_like(pts), pts]).T, secs, rcond=None)[0]
    est_degrees = fixed["estimated_degrees"]
    est_points = quadrature_points(est_degrees["cell"], "tetrahedron")
    quadrature = {
        "geometry": args.quadrature_geometry,
        "timeout_s": args.estimated_timeout,
        "runs": runs,
        "estimated_degrees": est_degrees,
        "estimated_cell_points": est_points,
        "estimated_compiled": "assemble_s" in estimated,
        "fit_seconds_per_cell_point": b,
        "extrapolated_estimated_assemble_s": a + b * est_points,
        "extrapolated_ratio_estimated_over_fixed": (a + b * est_points) / fixed["assemble_s"],
    }
    if "assemble_s" in estimated:
        quadrature["measured_ratio_estimated_over_fixed"] = estimated["assemble_s"] / fixed["assemble_s"]
    print(json.dumps({k: v for k, v in quadrature.items() if k != "runs"}, indent=1), flush=True)

    newton = []
    for name in args.geometries:
        for nr in args.ranks:
            print(f"contraction {name} on {nr} rank(s)", flush=True)
            run = common.run_worker("mechanics", {"kind": "newton", "geometry": name}, nr, 3600)
            newton.append(run)
            print(f"  {run['unknowns']} unknowns, {run['newton_iterations']} Newton iterations, "
                  f"{run['s_per_newton_iteration']:.3f} s per iteration, {run['s_per_solve']:.2f} s per solve",
                  flush=True)
    for run in newton:
        serial = [r for r in newton if r["geometry"] == run["geometry"] and r["ranks"] == 1]
        if serial and run["ranks"] > 1:
            run["speedup_per_iteration_vs_1_rank"] = serial[0]["s_per_newton_iteration"] / run["s_per_newton_iteration"]

    result = {
        "machine": {**host, "note": "shared machine: absolute times vary, ratios measured side by side"},
        "jacobian_assembly": quadrature,
        "newton": newton,
        "alphas": ALPHAS,
        "wall_s": time.perf_counter() - started,
    }
    out = args.output
    out.mkdir(parents=True, exist_ok=True)
    io.write_json(out / "mechanics.json", result)
    chart(out / "mechanics.png", result)
    print(f"wrote {out / 'mechanics.json'} and {out / 'mechanics.png'}")
    return 0


main = cli.entry(parser, run)

if __name__ == "__main__":
    sys.exit(main())
