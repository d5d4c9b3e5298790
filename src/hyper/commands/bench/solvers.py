"""Linear solvers side by side: MUMPS LU against GMRES with a BLR preconditioner, and GAMG.

    python -m hyper.bench solvers [--levels 0 1 2] [--ranks 2] [--parts levels precision gamg amg pmg scaling]

The scene is a growth solve: the resting idealized shape (refined `level` times, every
tetrahedron into eight) takes one transverse growth increment Fg = I + (ϑ - 1)(I - a0⊗a0)
with ϑ = 1.05 (ten default growth steps at once) and Newton finds the grown equilibrium
from the reference state, the Jacobian assembled and factorised at every Newton step.
Every (level, solver) is its own process under mpirun, run one after the other, so each
process's peak memory is its own:

- lu:        MUMPS's exact factorisation (the default);
- iterative: GMRES right-preconditioned by MUMPS's block low-rank factorisation
             (`hyper.fem.mechanics`, precision 1e-4) to a relative residual of 1e-10.

Per run: unknowns, Newton and Krylov iterations, wall time of the solve, the memory
MUMPS used (INFOG 22, summed over ranks), the factor entries of a full-rank and of the
stored factor (INFOG 29 and 35), the peak resident memory summed over ranks, and the
solution; the iterative solution is compared with LU's (max |Δu| / max |u|, max |Δp| /
max |p - p0|, and the volume), which must agree to the solver tolerance.

Where it stalls:
- BLR precision: on level `--precision-level` (default 1) GMRES with the BLR
  preconditioner at precisions 1e-4 … 1e-1 (iterations, or where it fails);
- GAMG: GMRES with a Schur-complement fieldsplit (u | p and the multipliers, selfp,
  Jacobi on the Schur block) and smoothed-aggregation AMG with the rigid-body near null
  space on the displacement block, on the idealized shape and TA_VHF_Left as given; on
  TA_VHF_Left also with tuned GAMG and with an exact (LU) displacement solve, which
  tells the displacement block's preconditioner from the Schur approximation.

- amg: the mechanics' experimental "amg" solver (`hyper.fem.mechanics`: mass-matrix Schur
  preconditioner, the free modes' multiplier Schur taken with the same V-cycle) with one
  GAMG V-cycle and with an exact (LU) displacement solve, on the idealized shape (levels 0
  and 1) and TA_VHF_Left, 1 rank.

- pmg: the experimental "pmg" solver (the same fieldsplit, a P2 → P1 p-multigrid on the
  displacement block: Chebyshev/Jacobi on P2, GAMG on the Galerkin P1 operator) side by
  side with LU and with the exact (LU) displacement solve, on the idealized shape (levels
  0 and 1) and TA_VHF_Left, 1 rank; its solution against LU's.

- scaling: "pmg" on one mesh (`--scaling-level`, default 2: 578k unknowns) on each of
  `--scaling-ranks` (default 1 2), one after the other: the wall time of the growth solve,
  the speed-up over the fewest ranks and the Krylov iterations per Newton step (the
  issue's goal: 1 -> 2 ranks at least 1.7 times as fast).

- weak: "pmg" at `--weak-unknowns` per rank (default 150k) on each of `--scaling-ranks`:
  a cylinder of the idealized shape's length (`weak_cylinder`, meshed by gmsh to the size
  each rank count needs) with the idealized fibres; iterations, time, memory a rank and
  the efficiency T(1) / T(P). From these and the levels part's iteration growth,
  `projection` extrapolates the time to 64-1024 ranks (marked as a projection).

- answers: whole runs with "lu" and with "pmg" on the idealized shape refined
  `--answers-levels` times (default 0 1), 1 rank each, side by side: `hyper grow
  --protocol mwf` (9 weeks) and `hyper contraction` (α to 1); the largest difference of
  the CSA and volume series as a fraction of the growth, and of the end force relative
  to it (the issue's goal: 1e-6 of the growth, 1e-8 of the force).

--parts runs only some of the eight (levels, precision, gamg, amg, pmg, scaling, weak, answers); the others are
kept from an existing OUTPUT/solvers.json. Writes results/bench/solvers.json and solvers.png (memory and time
against unknowns, iterations against unknowns and precision, and the weak-scaling efficiency where it ran).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from hyper.commands import cli
from hyper.commands.bench import common
from hyper.commands.bench.refinement import memory_fit
from hyper.core import io
from hyper.core.params import InputError
from hyper.fem import fibers
from hyper.fem import geometry as geo
from hyper.fem.mechanics import BLR_PRECISION, MechanicsProblem, SolverError
from hyper.model import growth
from hyper.model import material as mat
from hyper.runs import plot

THETA = 1.05
PRECISIONS = (1e-4, 1e-3, 1e-2, 1e-1)
# (geometry, variant): the variant's options go over GAMG_OPTIONS.
GAMG_VARIANTS = {
    "GAMG": {},
    "GAMG, threshold 0.05, 4 smoothing steps": {"fieldsplit_u_pc_gamg_threshold": 0.05,
                                                "fieldsplit_u_mg_levels_ksp_max_it": 4},
    "exact displacement solve (LU)": {"fieldsplit_u_pc_type": "lu", "fieldsplit_u_pc_factor_mat_solver_type": "mumps"},
}
GAMG_CASES = (("idealized", "GAMG"), *(("TA_VHF_Left", variant) for variant in GAMG_VARIANTS))
PARTS = ("levels", "precision", "gamg", "amg", "pmg", "scaling", "weak", "answers")
# The weak-scaling scene: a cylinder of the idealized shape's length and about its mean
# radius, meshed by gmsh at any size (the idealized mesh comes in steps of 8), with the
# idealized shape's analytic fibres, whose turn makes the growth non-uniform (with axial
# fibres its answer is stress-free and linear in X).
WEAK_RADIUS, WEAK_LENGTH = 0.02, 0.2  # m
WEAK_TRIES = 4  # meshes until the unknowns are within WEAK_TOLERANCE of the target
WEAK_TOLERANCE = 0.05
LEVEL_SOLVERS = ("lu", "iterative", "pmg")
# The mechanics' experimental "amg" solver (mass-matrix Schur preconditioner, the free
# modes' multiplier Schur with the same V-cycle): (geometry, level, variant), the variant's
# options over AMG_PETSC_OPTIONS; the exact displacement solve tells its Schur part from its AMG.
AMG_VARIANTS = {
    "GAMG V-cycle": {},
    "exact displacement solve (LU)": {"fieldsplit_u_pc_type": "lu", "fieldsplit_u_pc_factor_mat_solver_type": "mumps"},
}
AMG_CASES = (("idealized", 0, "exact displacement solve (LU)"), ("idealized", 0, "GAMG V-cycle"),
             ("idealized", 1, "GAMG V-cycle"), ("TA_VHF_Left", 0, "exact displacement solve (LU)"),
             ("TA_VHF_Left", 0, "GAMG V-cycle"))
# The p-multigrid part: (geometry, level, solver, variant), the variant's options over the
# solver's own; each case's solution is compared with the LU case's of its mesh.
PMG_VARIANTS = {
    "LU": {},
    "exact displacement solve (LU)": AMG_VARIANTS["exact displacement solve (LU)"],
    "p-multigrid, GAMG coarse": {},
    "p-multigrid, LU coarse": {"fieldsplit_u_mg_coarse_pc_type": "lu",
                               "fieldsplit_u_mg_coarse_pc_factor_mat_solver_type": "mumps"},
}
PMG_SOLVERS = {"LU": "lu", "exact displacement solve (LU)": "amg"}
PMG_CASES = (*((g, lvl, v) for g, lvl in (("idealized", 0), ("idealized", 1), ("TA_VHF_Left", 0))
               for v in ("LU", "exact displacement solve (LU)", "p-multigrid, GAMG coarse")),
             ("idealized", 0, "p-multigrid, LU coarse"), ("TA_VHF_Left", 0, "p-multigrid, LU coarse"))
# The Schur-complement fieldsplit of the GAMG cases; its splits are set in `_fieldsplit`.
GAMG_OPTIONS = {
    "ksp_type": "gmres", "ksp_gmres_restart": 200, "ksp_pc_side": "right", "ksp_rtol": 1e-10,
    "ksp_atol": 0.0, "ksp_max_it": 600,
    "pc_type": "fieldsplit", "pc_fieldsplit_type": "schur", "pc_fieldsplit_schur_fact_type": "upper",
    "pc_fieldsplit_schur_precondition": "selfp",
    "fieldsplit_u_ksp_type": "preonly", "fieldsplit_u_pc_type": "gamg",
    "fieldsplit_u_pc_gamg_aggressive_coarsening": 0, "fieldsplit_u_pc_gamg_threshold": 0.02,
    "fieldsplit_u_mg_levels_ksp_max_it": 3,
    "fieldsplit_p_ksp_type": "preonly", "fieldsplit_p_pc_type": "jacobi",
}


# ------------------------------------------------------------------------------ worker


def _fieldsplit(problem, comm, options: dict) -> None:
    """Displacement | pressure and multipliers splits, with the rigid-body near null space
    on the displacement block (its dofs are xyz triplets in the global order)."""
    from petsc4py import PETSc

    Vu, dofs = problem.W.sub(0).collapse()
    dofs = np.asarray(dofs).ravel()
    first, last = problem.jacobian_matrix.getOwnershipRange()
    owned = np.flatnonzero(dofs < problem.owned_size)
    order = np.argsort(dofs[owned])
    u_rows = (dofs[owned][order] + first).astype(np.int32)
    nodes = (owned[order] // 3)[::3]
    x = Vu.tabulate_dof_coordinates()[nodes]
    other = np.setdiff1d(np.arange(first, last, dtype=np.int32), u_rows).astype(np.int32)
    is_u = PETSc.IS().createGeneral(u_rows, comm=comm)
    is_u.setBlockSize(3)
    is_p = PETSc.IS().createGeneral(other, comm=comm)
    modes = []
    for k in range(6):
        vec = PETSc.Vec().createMPI((len(u_rows), PETSc.DETERMINE), bsize=3, comm=comm)
        values = np.zeros((len(nodes), 3))
        if k < 3:
            values[:, k] = 1.0
        else:
            values[:] = np.cross(np.eye(3)[k - 3], x - x.mean(axis=0))
        vec.getArray()[:] = values.ravel()
        for previous in modes:
            vec.axpy(-vec.dot(previous), previous)
        vec.normalize()
        modes.append(vec)
    is_u.compose("nearnullspace", PETSc.NullSpace().create(vectors=modes, comm=comm))
    ksp = problem.snes.getKSP()
    ksp.getPC().setFieldSplitIS(("u", is_u), ("p", is_p))
    db = PETSc.Options()
    # The sub-solvers read their options when the preconditioner is first set up, inside
    # the first solve: they stay in the database for this one-problem process.
    for key, value in options.items():
        db.setValue(problem.snes.getOptionsPrefix() + key, value)
    ksp.setFromOptions()


def run_case(case: dict, comm, save: Path | None) -> dict:
    import dolfinx_solver  # noqa: F401
    import ufl
    from dolfinx import fem
    from mpi4py import MPI


    geometry = geo.load(case["geometry"], comm, meshes_dir=case.get("meshes_dir"))
    for _ in range(case.get("level", 0)):
        geometry = geo.refine(geometry)
    a0 = fibers.fiber_field(geometry, case.get("fibers", "auto"))
    unit = a0 / ufl.sqrt(ufl.dot(a0, a0))
    theta = fem.Constant(geometry.mesh, 1.0)  # transverse stretch: area growth ϑ²
    Fg = growth.transverse_growth_ufl(theta**2, unit)
    solver = case["solver"]
    kwargs = {}
    if solver == "iterative":
        kwargs = {"linear_solver": "iterative", "blr_precision": case.get("precision", BLR_PRECISION)}
    start = time.perf_counter()
    options = {**GAMG_OPTIONS, **GAMG_VARIANTS[case["variant"]]} if solver == "gamg" else None
    if solver == "pmg" and "pmg_case" not in case:
        kwargs, options = {"linear_solver": "pmg"}, case.get("options") or None
    if solver == "amg":
        kwargs, options = {"linear_solver": "amg"}, AMG_VARIANTS[case["variant"]] or None
    if "pmg_case" in case:
        kwargs = {"linear_solver": PMG_SOLVERS.get(case["variant"], "pmg")}
        options = PMG_VARIANTS[case["variant"]] or None
    problem = MechanicsProblem(geometry, a0, growth=Fg, petsc_options=options, **kwargs)
    if solver == "gamg":
        _fieldsplit(problem, comm, options)
    setup_s = time.perf_counter() - start
    theta.value = THETA
    start = time.perf_counter()
    row = {**case, "unknowns": problem.num_dofs, "cells": geometry.num_cells()}
    try:
        row["newton_iterations"] = problem.solve()
    except SolverError as err:
        row["failed"] = str(err)
    solve_s = comm.allreduce(time.perf_counter() - start, op=MPI.MAX)
    reason = problem.snes.getKSP().getConvergedReason()
    row.update(setup_s=comm.allreduce(setup_s, op=MPI.MAX), solve_s=solve_s,
               krylov_iterations=problem.linear_iterations(), last_ksp_reason=int(reason),
               peak_rss_mb_sum=comm.allreduce(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, op=MPI.SUM) / 1024,
               **problem.mumps_memory())
    if "failed" not in row:
        row["volume_ratio"] = problem.volume() / geometry.reference_volume()
        if save is not None:
            n, p_dofs = problem.owned_size, problem.pressure_dofs
            np.save(save / f"w_{comm.rank}.npy", problem.w.x.array[:n])
            np.save(save / f"p_{comm.rank}.npy", p_dofs[p_dofs < n])
    return row


# ------------------------------------------------------------------------------ driver


def _run_worker(case: dict, ranks: int, timeout: float, save: Path | None) -> dict:
    row = common.run_worker("solvers", case, ranks, timeout, extra=() if save is None else ("--save", str(save)))
    row["ranks"] = ranks
    return row


def compare(reference: Path, other: Path, ranks: int) -> dict:
    """max |Δu| / max |u| and max |Δp| / max |p - p0| between two saved solutions."""

    ref = [np.load(reference / f"w_{r}.npy") for r in range(ranks)]
    new = [np.load(other / f"w_{r}.npy") for r in range(ranks)]
    p_dofs = [np.load(reference / f"p_{r}.npy") for r in range(ranks)]
    p0 = mat.reference_pressure(mat.MaterialParams())
    du = dp = umax = pmax = 0.0
    for a, b, p in zip(ref, new, p_dofs):
        is_u = np.ones(len(a), dtype=bool)
        is_u[p] = False
        du, umax = max(du, np.abs(a - b)[is_u].max()), max(umax, np.abs(a[is_u]).max())
        dp, pmax = max(dp, np.abs(a - b)[p].max()), max(pmax, np.abs(a[p] - p0).max())
    return {"u": du / umax, "p": dp / pmax}


def chart(path: Path, result: dict) -> None:
    plt = plot.pyplot()
    weak = [r for r in result.get("weak", []) if "failed" not in r]
    fig, axes = plt.subplots(1, 4 if weak else 3, figsize=(20 if weak else 15, 4.3))
    styles = {"lu": ("o-", "MUMPS LU"), "iterative": ("s-", "GMRES + BLR LU (1e-4)"),
              "pmg": ("P-", "GMRES + fieldsplit, P2→P1 multigrid (pmg)")}
    ax = axes[0]
    ran = {r["solver"] for r in result["levels"] if "failed" not in r}
    styles = {solver: style for solver, style in styles.items() if solver in ran}  # no empty legend entries
    for solver, (style, label) in styles.items():
        rows = [r for r in result["levels"] if r["solver"] == solver and "failed" not in r]
        n = [r["unknowns"] for r in rows]
        if solver != "pmg":
            ax.loglog(n, [r["mumps_used_mb"] / 1024 for r in rows], style, label=f"{label}: MUMPS memory")
        ax.loglog(n, [r["peak_rss_mb_sum"] / 1024 for r in rows], style.replace("-", ":"), alpha=0.6,
                  color=None if solver == "pmg" else ax.lines[-1].get_color(), label=f"{label}: peak RSS")
    ax.set_xlabel("unknowns")
    ax.set_ylabel("GiB (summed over ranks)")
    ax.set_title(f"memory, {result['ranks']} ranks, idealized refined", fontsize=9)
    ax.legend(fontsize=7)
    ax = axes[1]
    for solver, (style, label) in styles.items():
        rows = [r for r in result["levels"] if r["solver"] == solver and "failed" not in r]
        ax.loglog([r["unknowns"] for r in rows], [r["solve_s"] for r in rows], style, label=label)
    ax.set_xlabel("unknowns")
    ax.set_ylabel("wall time of the growth solve (s)")
    ax.set_title(f"time (ϑ = {THETA:g} at once, Jacobian factorised every Newton step)", fontsize=9)
    ax.legend(fontsize=7)
    ax = axes[2]
    for solver, label in (("iterative", "GMRES + BLR 1e-4"), ("pmg", "pmg")):
        if solver not in styles:
            continue
        rows = [r for r in result["levels"] if r["solver"] == solver and "failed" not in r]
        ax.semilogx([r["unknowns"] for r in rows], [r["krylov_iterations"] / r["newton_iterations"] for r in rows],
                    styles[solver][0], label=f"{label}, idealized refined, against unknowns")
    for r in result.get("amg", []):
        ok = "failed" not in r
        its = r["krylov_iterations"] / max(r.get("newton_iterations") or 1, 1) if ok else 0
        ax.semilogx([r["unknowns"]], [its], "v" if ok else "rx", ms=9,
                    label=f"amg, {r['variant']}, {r['geometry']}" + ("" if ok else ": fails"))
    pmg = {}  # (variant, geometry): its per Newton step against unknowns, over the levels
    for r in result.get("pmg", []):
        if r["solver"] != "lu":
            its = r["krylov_iterations"] / max(r.get("newton_iterations") or 1, 1) if "failed" not in r else 0
            pmg.setdefault((r["variant"], r["geometry"]), []).append((r["unknowns"], its))
    for (variant, geometry), points in pmg.items():
        n, its = zip(*sorted(points))
        ax.semilogx(n, its, "P-", ms=9, label=f"pmg part: {variant}, {geometry} (0: fails)")
    for r in result["gamg"]:
        ok = "failed" not in r
        its = r["krylov_iterations"] / max(r.get("newton_iterations") or 1, 1) if ok else 0
        ax.semilogx([r["unknowns"]], [its], "^" if ok else "rx", ms=9,
                    label=f"{r.get('variant', 'GAMG')} fieldsplit, {r['geometry']}" + ("" if ok else ": breaks down"))
    ax.set_xlabel("unknowns")
    ax.set_ylabel("Krylov iterations per Newton step (0: failed)")
    twin = ax.twiny()
    prec = [r for r in result["precision"]]
    twin.semilogx([r["precision"] for r in prec],
                  [r["krylov_iterations"] / r["newton_iterations"] if "failed" not in r else np.nan for r in prec],
                  "d--", color="tab:purple")
    for r in prec:
        if "failed" in r:
            twin.plot([r["precision"]], [0], "rx", ms=9)
    twin.set_xlabel("BLR precision (purple; red x: GMRES fails)", color="tab:purple", fontsize=8)
    ax.set_title("where it stalls", fontsize=9, pad=28)
    ax.legend(fontsize=7, loc="upper left")
    if weak:
        _weak_chart(axes[3], weak, result.get("projection") or {})
    fig.tight_layout()
    plot.save(fig, path, dpi=120)


def _weak_chart(ax, weak: list[dict], projected: dict) -> None:
    """Weak-scaling efficiency against ranks: measured points, the projection dashed."""
    ranks = [r["ranks"] for r in weak]
    ax.semilogx(ranks, [r.get("efficiency", 1.0) for r in weak], "P-", ms=9, base=2,
                label=f"measured, {weak[0]['unknowns_per_rank'] / 1e3:.0f}k unknowns a rank")
    if projected:
        times = 2.0 ** np.arange(0, 1 + int(np.log2(projected["rows"][-1]["ranks"] / projected["from_ranks"])))
        T = [projected_seconds(projected["from_solve_s"], projected["beta"], projected["gamma"], t) for t in times]
        ax.semilogx(projected["from_ranks"] * times, projected["from_solve_s"] / np.array(T), "--", color="grey",
                    base=2, label=f"projection (not measured): β = {projected['beta']:.3f}, "
                                  f"γ = {projected['gamma']:.3f}")
    for r in weak:
        ax.annotate(f"{r['krylov_per_newton']:.0f} its", (r["ranks"], r.get("efficiency", 1.0)), fontsize=7,
                    textcoords="offset points", xytext=(4, 4))
    ax.set_ylim(0, 1.1)
    ax.set_xlabel("ranks")
    ax.set_ylabel("weak-scaling efficiency T(1) / T(P)")
    ax.set_title("pmg, fixed unknowns a rank (cylinder, growth solve)", fontsize=9)
    ax.legend(fontsize=7)


def parser() -> cli.Parser:
    p = cli.Parser("bench solvers", __doc__)
    p.add_argument("--levels", nargs="+", type=cli.integer(0, 3), metavar="LEVEL", default=[0, 1, 2],
                   help="refinement levels of the idealized shape (0 to 3)")
    p.add_argument("--ranks", type=cli.integer(1), default=2, help="MPI ranks per run")
    p.add_argument("--solvers", nargs="+", choices=LEVEL_SOLVERS, default=list(LEVEL_SOLVERS), metavar="SOLVER",
                   help=f"the levels part's linear solvers ({', '.join(LEVEL_SOLVERS)}), each against lu where lu runs")
    p.add_argument("--scaling-level", type=cli.integer(0, 3), default=2, help="refinement level of the scaling part")
    p.add_argument("--scaling-ranks", nargs="+", type=cli.integer(1), default=[1, 2], metavar="RANKS",
                   help="rank counts of the scaling part")
    p.add_argument("--weak-unknowns", type=cli.integer(1000), default=150_000,
                   help="unknowns a rank of the weak part (on each of --scaling-ranks)")
    p.add_argument("--pmg-option", type=cli.petsc_option, action="append", default=[], metavar="KEY=VALUE",
                   help="a PETSc option of the pmg runs of the levels, scaling and weak parts (repeatable), "
                        "e.g. ksp_gmres_restart=60")
    p.add_argument("--answers-levels", nargs="+", type=cli.integer(0, 3), default=[0, 1], metavar="LEVEL",
                   help="refinement levels of the answers part")
    p.add_argument("--precision-level", type=cli.integer(0, 3), default=1, help="level of the BLR precision ladder")
    p.add_argument("--parts", nargs="+", choices=PARTS, metavar="PART", default=list(PARTS),
                   help=f"which parts to run ({', '.join(PARTS)}); the others are kept from OUTPUT/solvers.json")
    p.add_argument("--timeout", type=cli.number(), default=3600.0, help="seconds per run before it counts as failed")
    p.add_argument("--output", type=Path, default=Path("results/bench"), help="output folder")
    p.add_argument("--replot", action="store_true", help="redraw the chart from OUTPUT/solvers.json, run nothing")
    common.add_worker_options(p)
    p.add_argument("--save", type=Path, help=argparse.SUPPRESS)
    return p


def _pmg_part(args) -> list[dict]:
    """The p-multigrid cases on 1 rank, each solution against LU's on the same mesh."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (name, level, variant) in enumerate(PMG_CASES):
            save = Path(tmp) / str(i)
            save.mkdir()
            print(f"solvers: pmg part, {variant}, on {name} level {level} …", flush=True)
            solver = PMG_SOLVERS.get(variant, "pmg")
            row = _run_worker({"geometry": name, "level": level, "solver": solver, "variant": variant,
                               "pmg_case": True}, 1, args.timeout, save)
            lu = next((j for j, (g, lvl, v) in enumerate(PMG_CASES[:i]) if (g, lvl, v) == (name, level, "LU")), None)
            if lu is not None and "failed" not in row and "failed" not in rows[lu]:
                row["difference_from_lu"] = {**compare(Path(tmp) / str(lu), save, 1),
                                             "volume": abs(row["volume_ratio"] - rows[lu]["volume_ratio"])
                                                       / (rows[lu]["volume_ratio"] - 1)}
            rows.append(row)
            print("  " + ("FAILED " + row["failed"] if "failed" in row else
                          f"{row['unknowns']} unknowns, {row['newton_iterations']} Newton, "
                          f"{row['krylov_iterations']} Krylov its, {row['solve_s']:.1f} s, "
                          f"peak RSS {row['peak_rss_mb_sum']:.0f} MB, vs LU {row.get('difference_from_lu')}"),
                  flush=True)
    return rows


def _scaling_part(args) -> list[dict]:
    """"pmg" on one mesh on each rank count; each row's speed-up is over the fewest ranks'."""
    rows = []
    for ranks in sorted(args.scaling_ranks):
        print(f"solvers: scaling, pmg on level {args.scaling_level} on {ranks} rank(s) …", flush=True)
        row = _run_worker({"geometry": "idealized", "level": args.scaling_level, "solver": "pmg",
                           "options": dict(args.pmg_option)}, ranks, args.timeout, None)
        if "failed" not in row and rows and "failed" not in rows[0]:
            row["speedup"] = rows[0]["solve_s"] / row["solve_s"]
            row["efficiency"] = row["speedup"] * rows[0]["ranks"] / ranks
        rows.append(row)
        print("  " + ("FAILED " + row["failed"] if "failed" in row else
                      f"{row['unknowns']} unknowns, {row['krylov_iterations'] / row['newton_iterations']:.1f} "
                      f"Krylov its a Newton step, {row['solve_s']:.1f} s, peak RSS {row['peak_rss_mb_sum']:.0f} MB"
                      + (f", speed-up {row['speedup']:.2f}" if "speedup" in row else "")), flush=True)
    return rows


def weak_cylinder(folder: Path, unknowns: int) -> int:
    """Mesh the weak-scaling cylinder with gmsh into ``folder`` as `geo.load` reads a
    cylinder (FOLDER/muscle-cylinder/muscle-cylinder.msh: ends tagged 1 and 2, the
    internal mid disk 3), with about ``unknowns`` P2–P1 unknowns (3 (V + E) + V for V
    vertices and E edges); returns its unknowns. The edge length is rescaled until they
    are within WEAK_TOLERANCE."""
    import gmsh

    path = folder / geo.GEOMETRIES["cylinder"]
    path.parent.mkdir(parents=True, exist_ok=True)
    size = (WEAK_LENGTH * np.pi * WEAK_RADIUS**2 * 33.0 / unknowns) ** (1.0 / 3.0)  # first guess, then measured
    gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        occ = gmsh.model.occ
        halves = [occ.addCylinder(0, 0, z, 0, 0, WEAK_LENGTH / 2, WEAK_RADIUS) for z in (0.0, WEAK_LENGTH / 2)]
        occ.fragment([(3, halves[0])], [(3, halves[1])])
        occ.synchronize()
        disks = {}
        for _, tag in gmsh.model.getEntities(2):
            box = gmsh.model.getBoundingBox(2, tag)
            if box[5] - box[2] < 1e-3 * WEAK_LENGTH:  # flat (boxes carry OCC's tolerance): an end or the mid disk
                disks[round(box[2] / (WEAK_LENGTH / 2))] = tag
        for physical, position in ((1, 0), (2, 2), (3, 1)):
            gmsh.model.addPhysicalGroup(2, [disks[position]], physical)
        gmsh.model.addPhysicalGroup(3, [t for _, t in gmsh.model.getEntities(3)], 1)
        for _ in range(WEAK_TRIES):
            gmsh.model.mesh.clear()
            gmsh.option.setNumber("Mesh.MeshSizeMin", size)
            gmsh.option.setNumber("Mesh.MeshSizeMax", size)
            gmsh.model.mesh.generate(3)
            vertices = len(gmsh.model.mesh.getNodes()[0])
            tets = gmsh.model.mesh.getElementsByType(4)[1].reshape(-1, 4)
            a, b = tets[:, [0, 0, 0, 1, 1, 2]].ravel(), tets[:, [1, 2, 3, 2, 3, 3]].ravel()
            edges = np.unique(np.minimum(a, b) * (tets.max() + 1) + np.maximum(a, b)).size
            made = 3 * (vertices + edges) + vertices
            if abs(made / unknowns - 1.0) <= WEAK_TOLERANCE:
                break
            size *= (made / unknowns) ** (1.0 / 3.0)
        gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
        gmsh.write(str(path))
    finally:
        gmsh.finalize()
    return made


def _weak_part(args) -> list[dict]:
    """"pmg" at `--weak-unknowns` per rank on each of `--scaling-ranks`: the cylinder of
    `weak_cylinder` meshed anew for each rank count; efficiency = fewest ranks' time / this one's."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for ranks in sorted(args.scaling_ranks):
            folder = Path(tmp) / str(ranks)
            print(f"solvers: weak scaling, pmg at {args.weak_unknowns} unknowns a rank on {ranks} rank(s) …",
                  flush=True)
            meshed = weak_cylinder(folder, ranks * args.weak_unknowns)
            row = _run_worker({"geometry": "cylinder", "meshes_dir": str(folder), "fibers": "idealized",
                               "solver": "pmg", "options": dict(args.pmg_option)}, ranks, args.timeout, None)
            row.pop("meshes_dir", None)  # a folder gone with this run
            row["meshed_unknowns"] = meshed
            if "failed" not in row:
                row["unknowns_per_rank"] = row["unknowns"] / ranks
                row["krylov_per_newton"] = row["krylov_iterations"] / row["newton_iterations"]
                row["peak_rss_mb_per_rank"] = row["peak_rss_mb_sum"] / ranks
                # time per Krylov iteration and unknown a rank: the cost the projection carries
                row["solve_s_per_iteration_and_unknown_a_rank"] = (row["solve_s"] / row["krylov_iterations"]
                                                                   / row["unknowns_per_rank"])
                if rows and "failed" not in rows[0]:
                    row["efficiency"] = rows[0]["solve_s"] / row["solve_s"]
            rows.append(row)
            print("  " + ("FAILED " + row["failed"] if "failed" in row else
                          f"{row['unknowns']} unknowns ({row['unknowns_per_rank']:.0f} a rank), "
                          f"{row['krylov_per_newton']:.1f} Krylov its a Newton step, {row['solve_s']:.1f} s, "
                          f"peak RSS {row['peak_rss_mb_per_rank']:.0f} MB a rank"
                          + (f", efficiency {row['efficiency']:.2f}" if "efficiency" in row else "")), flush=True)
    return rows


PROJECTED_RANKS = (64, 128, 256, 512, 1024)


def projection(weak: list[dict], levels: list[dict]) -> dict:
    """A projection (not a measurement) of the weak-scaling time to PROJECTED_RANKS from
    the measured per-rank costs: T(P) = T(1) (N_P / N_1)^β (1 + γ log₂ P), with β the
    growth of pmg's Krylov iterations a Newton step with the unknowns (fitted on the
    levels part), and γ the growth of the time per iteration and per-rank unknown from 1
    to 2 ranks (its halo exchange and shared memory bandwidth; inter-node networks and the
    coarse grid's growing share are not in it). Empty without two weak rows and two pmg levels."""
    done = sorted((r for r in weak if "failed" not in r), key=lambda r: r["ranks"])
    pmg = sorted((r for r in levels if r["solver"] == "pmg" and "failed" not in r), key=lambda r: r["unknowns"])
    if len(done) < 2 or len(pmg) < 2:
        return {}
    small, large = pmg[0], pmg[-1]
    beta = float(np.log((large["krylov_iterations"] / large["newton_iterations"])
                        / (small["krylov_iterations"] / small["newton_iterations"]))
                 / np.log(large["unknowns"] / small["unknowns"]))
    first, second = done[0], done[1]
    key = "solve_s_per_iteration_and_unknown_a_rank"
    gamma = float((second[key] / first[key] - 1.0) / np.log2(second["ranks"] / first["ranks"]))
    per_rank = first["unknowns_per_rank"]
    rows = [{"ranks": ranks, "unknowns": per_rank * ranks,
             "solve_s": projected_seconds(first["solve_s"], beta, gamma, ranks / first["ranks"])}
            for ranks in PROJECTED_RANKS]
    for row in rows:
        row["efficiency"] = first["solve_s"] / row["solve_s"]
    return {"kind": "projection, not measured", "model": "T(P) = T(1) (N_P / N_1)^beta (1 + gamma log2 P)",
            "beta": beta, "gamma": gamma, "unknowns_per_rank": per_rank, "from_ranks": first["ranks"],
            "from_solve_s": first["solve_s"], "rows": rows}


def projected_seconds(seconds: float, beta: float, gamma: float, times: float) -> float:
    """`projection`'s T(P) for ``times`` the measured ranks and unknowns."""
    return float(seconds * times**beta * (1.0 + gamma * np.log2(times)))


def _answers_part(args) -> list[dict]:
    """Whole grow and contraction runs with lu and pmg, each in its own process (1 rank),
    the two solvers of a level at once; their series against each other."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for level in args.answers_levels:
            for job in ("grow", "contraction"):
                print(f"solvers: answers, {job} on level {level}, lu and pmg …", flush=True)
                outputs = {s: Path(tmp) / f"{job}_{level}_{s}.h5" for s in ("lu", "pmg")}
                extra = ("--protocol", "mwf") if job == "grow" else ()
                procs = {s: subprocess.Popen([sys.executable, "-m", f"hyper.{job}", "--geometry", "idealized",
                                              "--refine", str(level), "--linear-solver", s, "--quiet",
                                              "--output", str(out), *extra],
                                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
                         for s, out in outputs.items()}
                started = time.perf_counter()
                errors = {}
                for s, p in procs.items():
                    try:
                        errors[s] = p.communicate(timeout=args.timeout)[1]
                    except subprocess.TimeoutExpired:  # a failed row, as the workers' timeout gives
                        p.kill()
                        errors[s] = p.communicate()[1] + f"\ntimed out after {args.timeout:g} s"
                row = {"job": job, "level": level, "wall_s": time.perf_counter() - started}
                failed = {s: (errors[s].strip().splitlines() or ["failed"])[-1] for s, p in procs.items()
                          if p.returncode}
                if failed:
                    row["failed"] = "; ".join(f"{s}: {e}" for s, e in failed.items())
                else:
                    lu, pmg = (io.read_series(outputs[s]) for s in ("lu", "pmg"))
                    if job == "grow":
                        for name in ("csa_ratio", "volume_ratio"):
                            growth = lu[name][-1] - 1.0
                            row[f"{name}_difference"] = float(np.max(np.abs(np.asarray(pmg[name]) - lu[name]))
                                                              / growth)
                            row[f"{name}_final"] = {"lu": float(lu[name][-1]), "pmg": float(pmg[name][-1])}
                    else:
                        row["end_force_difference"] = abs(pmg["end_force"][-1] - lu["end_force"][-1]) \
                            / abs(lu["end_force"][-1])
                        row["end_force"] = {"lu": float(lu["end_force"][-1]), "pmg": float(pmg["end_force"][-1])}
                        row["krylov_iterations"] = {"lu": int(np.sum(lu["krylov_iterations"])),
                                                    "pmg": int(np.sum(pmg["krylov_iterations"]))}
                rows.append(row)
                print("  " + ("FAILED " + row["failed"] if "failed" in row else
                              ", ".join(f"{k} {v:.2e}" for k, v in row.items() if k.endswith("_difference"))),
                      flush=True)
    return rows


def _iteration_growth(rows: list[dict]) -> dict:
    """Per solver, Krylov iterations per Newton step at the largest level over those at the
    smallest (the issue's goal for pmg: at most 1.5 from 11k to 578k unknowns)."""
    out = {}
    for solver in ("iterative", "pmg"):
        done = sorted((r for r in rows if r["solver"] == solver and "failed" not in r), key=lambda r: r["unknowns"])
        if len(done) >= 2:
            per = [r["krylov_iterations"] / r["newton_iterations"] for r in (done[0], done[-1])]
            out[solver] = {"unknowns": [done[0]["unknowns"], done[-1]["unknowns"]], "per_newton_step": per,
                           "ratio": per[1] / per[0]}
    return out


def run(comm, args) -> int:
    if args.worker:
        common.write_worker_result(comm, args.json, run_case(args.worker, comm, args.save))
        return 0


    if args.replot:
        chart(args.output / "solvers.png", json.loads((args.output / "solvers.json").read_text()))
        return 0
    if args.ranks < 1:
        raise InputError("--ranks: at least 1")
    previous = json.loads((args.output / "solvers.json").read_text()) if (args.output / "solvers.json").exists() else {}
    kept = {part: previous.get(part, []) for part in PARTS if part not in args.parts}
    if kept and previous.get("ranks", args.ranks) != args.ranks:
        raise InputError(f"--ranks {args.ranks}: the kept parts of {args.output / 'solvers.json'} ran on "
                         f"{previous['ranks']} ranks; run all parts, or the same ranks")

    start = time.perf_counter()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for level in args.levels if "levels" in args.parts else ():
            saved = {}
            for solver in args.solvers:
                saved[solver] = Path(tmp) / f"{solver}_{level}"
                saved[solver].mkdir()
                print(f"solvers: level {level}, {solver} on {args.ranks} rank(s) …", flush=True)
                row = _run_worker({"geometry": "idealized", "level": level, "solver": solver,
                                   **({"options": dict(args.pmg_option)} if solver == "pmg" else {})},
                                  args.ranks, args.timeout, saved[solver])
                rows.append(row)
                print("  " + ("FAILED " + row["failed"] if "failed" in row else
                              f"{row['unknowns']} unknowns, {row['newton_iterations']} Newton, "
                              f"{row['krylov_iterations']} Krylov its, {row['solve_s']:.1f} s, MUMPS "
                              f"{row.get('mumps_used_mb', 0)} MB, peak RSS {row['peak_rss_mb_sum']:.0f} MB"),
                      flush=True)
            level_rows = dict(zip(args.solvers, rows[-len(args.solvers):]))
            lu = level_rows.get("lu")
            for solver, it in level_rows.items():
                if solver == "lu" or lu is None or "failed" in lu or "failed" in it:
                    continue
                it["difference_from_lu"] = {**compare(saved["lu"], saved[solver], args.ranks),
                                            "volume": abs(it["volume_ratio"] - lu["volume_ratio"])
                                                      / (lu["volume_ratio"] - 1)}
                if "mumps_used_mb" in it:
                    it["memory_ratio"] = it["mumps_used_mb"] / lu["mumps_used_mb"]
                it["rss_ratio"] = it["peak_rss_mb_sum"] / lu["peak_rss_mb_sum"]
                it["time_ratio"] = it["solve_s"] / lu["solve_s"]
                print(f"  {solver} - LU: {it['difference_from_lu']}; peak RSS x{it['rss_ratio']:.2f}, "
                      f"time x{it['time_ratio']:.2f}", flush=True)
    precision = []
    for eps in PRECISIONS if "precision" in args.parts else ():
        print(f"solvers: BLR precision {eps:g} on level {args.precision_level} …", flush=True)
        precision.append(_run_worker({"geometry": "idealized", "level": args.precision_level, "solver": "iterative",
                                      "precision": eps}, args.ranks, args.timeout, None))
    gamg = []
    for name, variant in GAMG_CASES if "gamg" in args.parts else ():
        print(f"solvers: {variant} fieldsplit on {name} …", flush=True)
        gamg.append(_run_worker({"geometry": name, "level": 0, "solver": "gamg", "variant": variant}, 1,
                                args.timeout, None))
    amg = []
    for name, level, variant in AMG_CASES if "amg" in args.parts else ():
        print(f"solvers: amg, {variant}, on {name} level {level} …", flush=True)
        amg.append(_run_worker({"geometry": name, "level": level, "solver": "amg", "variant": variant}, 1,
                               args.timeout, None))
    pmg = _pmg_part(args) if "pmg" in args.parts else []
    scaling = _scaling_part(args) if "scaling" in args.parts else []
    weak = _weak_part(args) if "weak" in args.parts else []
    answers = _answers_part(args) if "answers" in args.parts else []
    measured = {"levels": rows, "precision": precision, "gamg": gamg, "amg": amg, "pmg": pmg, "scaling": scaling,
                "weak": weak, "answers": answers}
    rows, precision, gamg, amg, pmg, scaling, weak, answers = ({**measured, **kept}[part] for part in PARTS)
    result = {"benchmark": "solvers", "machine": common.machine(), "ranks": args.ranks, "theta": THETA,
              "levels": rows, "precision": precision, "gamg": gamg, "amg": amg, "pmg": pmg, "scaling": scaling,
              "weak": weak, "projection": projection(weak, rows), "answers": answers, "parts_run": args.parts,
              "memory_fit": {s: memory_fit([r for r in rows if r["solver"] == s]) for s in ("lu", "iterative")},
              "rss_fit": {s: memory_fit([r for r in rows if r["solver"] == s], "peak_rss_mb_sum")
                          for s in LEVEL_SOLVERS},
              "iteration_growth": _iteration_growth(rows),
              "versions": io.versions(), "wall_s": time.perf_counter() - start}
    args.output.mkdir(parents=True, exist_ok=True)
    io.write_json(args.output / "solvers.json", result)
    chart(args.output / "solvers.png", result)
    for r in precision + gamg + amg + pmg:
        print(f"{r.get('variant', r['solver']):40s} {r['geometry']:12s} level {r.get('level', 0)} "
              f"precision {r.get('precision', '-')}: " +
              (f"FAILED {r['failed']}" if "failed" in r else
               f"{r['newton_iterations']} Newton, {r['krylov_iterations']} Krylov its, {r['solve_s']:.1f} s"))
    print(f"wrote {args.output / 'solvers.json'} and solvers.png")
    return 0


main = cli.entry(parser, run)

if __name__ == "__main__":
    sys.exit(main())
