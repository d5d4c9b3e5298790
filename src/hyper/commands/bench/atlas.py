"""The atlas: error against wall time for every numerical choice, and where methods fail.

    python -m hyper.bench atlas [--geometries idealized BFLH_VHF_Left] [--protocol mwf]

Errors are of what users read: |x - x_ref| / (x_ref - 1) for x = CSA/CSA0 and V/V0 at
the protocol's end (a fraction of the growth), and the relative error of N for the
signaling ODEs. Each dimension is a set of runs measured side by side in one
invocation, every run in its own process (`hyper.bench growth`'s worker), so they
share the machine's state; wall is the time loop's wall time on the slowest rank.

Measured here, for the default `mwf` run (one growth step per period, RK4 at 0.05 h):
- mesh:       the idealized shape as given and once refined (h/2, 8x the cells);
              reference: the refined mesh. Anatomical meshes are as given.
- quadrature: degree 2, 4 (the default) and 6 for every geometry; reference: 6.
- ranks:      one run on 1 and on 2 ranks; reference: 1 rank (the answers agree to
              round-off, so this is a pure speed dimension).
Collected from their own benchmarks, each measured side by side in its own run (run
those first; the atlas says which are missing):
- ode_dt:     `python -m hyper.bench signaling` (RK4 dt against DOP853 at rtol 1e-13)
- growth_dt:  `python -m hyper.bench growth` (Δtg against 0.5 h, and the paper's settings)
- mesh size and LU memory: `python -m hyper.bench refinement` (three levels)
- linear solver: `python -m hyper.bench solvers` (MUMPS LU against GMRES with a BLR
              preconditioner on the idealized shape at 11k, 78k and 578k unknowns,
              2 ranks; error: the largest difference of u and p from LU's, relative)
Failure map (data, not anecdotes):
- RK4 stability limit in dt (from the signaling benchmark);
- the largest growth step Newton converges for: one transverse growth increment
  Fg = I + (ϑ - 1)(I - a0⊗a0) applied at once to the resting idealized muscle, for a
  ladder of ϑ, with no step cutting and with up to 4 halvings (run here); a default
  growth step grows ϑ by at most about 0.5 %;
- the mesh size at which MUMPS's LU needs the machine's memory (from refinement.json);
- the iterative solvers (from solvers.json): GMRES iterations against unknowns and the
  BLR precision (where it stops converging), and GAMG fieldsplit's iterations or breakdown;
  the hand-measured active (α = 1) cases are in `iterative` in the JSON.

Writes results/bench/atlas.json, atlas.png (Pareto charts) and failure_map.png.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from hyper.commands import cli
from hyper.commands.bench import common
from hyper.commands.bench import growth as growth_bench
from hyper.core import io
from hyper.core.params import InputError
from hyper.fem import fibers
from hyper.fem import geometry as geo
from hyper.fem.mechanics import MechanicsProblem, SolverError
from hyper.model import growth, protocols
from hyper.runs import plot

THETAS = (1.005, 1.05, 1.2, 1.5, 2.0, 2.5, 3.0, 4.0, 6.0, 10.0)

# Measured by hand on the active (α = 1) idealized and TA_VHF_Left Jacobians (commit
# message of this file's first version): GMRES with a Schur-complement fieldsplit
# (u | p, rigid-mode multipliers), selfp, Jacobi on the Schur block. The growth solves
# at rest are measured by `python -m hyper.bench solvers`.
ITERATIVE_FINDINGS = {
    "tried": "GMRES(200), right preconditioning, rtol 1e-8; PCFIELDSPLIT Schur (u | p + multipliers), "
             "schur_precondition selfp, Jacobi on the Schur block",
    "cases": [
        {"geometry": "idealized", "unknowns": 11306, "u_block": "GAMG (Chebyshev/Jacobi, rigid near null space)",
         "iterations": 200, "converged": False, "relative_residual": 1.2},
        {"geometry": "idealized", "unknowns": 11306,
         "u_block": "GAMG, threshold 0.02/0.05, 4 smoothing steps, inner CG",
         "iterations": 400, "converged": False, "relative_residual": 1.4},
        {"geometry": "idealized", "unknowns": 11306, "u_block": "GAMG on 2μ ε:ε (+ fibre term) instead of the tangent",
         "iterations": 400, "converged": False, "relative_residual": 0.9},
        {"geometry": "TA_VHF_Left", "unknowns": 48153, "u_block": "GAMG", "iterations": 400,
         "converged": False, "relative_residual": 5.0},
        {"geometry": "TA_VHF_Left", "unknowns": 48153, "u_block": "GAMG with GMRES/SOR smoothing, FGMRES",
         "iterations": 300, "converged": False, "relative_residual": 2.7},
        {"geometry": "TA_VHF_Left", "unknowns": 48153, "u_block": "ILU(0)", "iterations": 200,
         "converged": False, "relative_residual": 3.3},
        {"geometry": "TA_VHF_Left", "unknowns": 48153, "u_block": "exact LU", "iterations": 51,
         "converged": True, "relative_residual": 5.2e-5},
    ],
    "why": "at full activation the displacement block of the tangent is indefinite (active fibre stress "
           "3e5 Pa against a matrix stiffness of 1e4 Pa, and the pressure's geometric term), so "
           "smoothed-aggregation AMG and Chebyshev smoothing, which assume a positive definite block, "
           "diverge; the Schur approximation itself is good (51 iterations with an exact displacement "
           "solve). Not available: hypre (not in the PETSc wheel).",
}


# -------------------------------------------------------------------- cases measured here


def _case(label: str, geometry: str, protocol: str, **extra) -> dict:
    return {"label": label, "geometry": geometry, "protocol": protocol, "signaling": "rk4",
            "settings": {}, **extra}


def dimension_cases(geometries: list[str], protocol: str) -> dict[str, list[tuple[dict, int]]]:
    """(case, ranks) per dimension; the first case of each list is its reference."""
    out: dict[str, list[tuple[dict, int]]] = {}
    if "idealized" in geometries:
        out["mesh"] = [(_case("idealized, refined once", "idealized", protocol, refine=1), 2),
                       (_case("idealized, as given", "idealized", protocol), 2)]
    for name in geometries:
        out[f"quadrature {name}"] = [(_case(f"{name}, degree {d}", name, protocol, quadrature_degree=d), 1)
                                     for d in (6, 4, 2)]
        out[f"ranks {name}"] = [(_case(f"{name}, {r} rank(s)", name, protocol), r) for r in (1, 2)]
    return out


def measure_dimension(cases: list[tuple[dict, int]], timeout: float, log) -> list[dict]:
    rows = []
    for case, ranks in cases:
        log(f"  {case['label']} on {ranks} rank(s) …")
        row = common.run_worker("growth", case, ranks, timeout)
        row.pop("series", None)
        row["ranks"] = ranks
        rows.append(row)
    ref = rows[0]
    for row in rows:
        if "failed" in row or "failed" in ref:
            continue
        row["errors"] = growth_bench.growth_errors(row["csa_ratio"], row["volume_ratio"],
                                                   ref["csa_ratio"], ref["volume_ratio"])
        row["reference"] = row is ref
    return rows


# --------------------------------------------------------------- failure: growth step


def newton_growth_step(thetas=THETAS, halvings: int = 4) -> list[dict]:
    """For each ϑ: does Newton reach the grown equilibrium from the resting reference in
    one step, and with up to ``halvings`` cuts (ϑ approached in 2^k equal increments of
    log ϑ)? Iterations and the state's volume ratio against ϑ² (uniform growth)."""
    import dolfinx_solver  # noqa: F401
    import ufl
    from dolfinx import fem
    from mpi4py import MPI


    comm = MPI.COMM_SELF
    geometry = geo.load("idealized", comm)
    a0 = fibers.fiber_field(geometry)
    unit = a0 / ufl.sqrt(ufl.dot(a0, a0))
    theta = fem.Constant(geometry.mesh, 1.0)  # transverse stretch: area growth ϑ²
    Fg = growth.transverse_growth_ufl(theta**2, unit)
    problem = MechanicsProblem(geometry, a0, growth=Fg, petsc_options={"snes_max_it": 50})
    volume0 = geometry.reference_volume()
    rows = []
    for target in thetas:
        row = {"theta": target}
        for cuts in (0, halvings):
            problem.reset()
            theta.value = 1.0
            iterations, ok, used = 0, True, 0
            pieces = 1
            while True:
                problem.reset()
                steps = np.exp(np.linspace(0.0, math.log(target), pieces + 1)[1:])
                try:
                    start = time.perf_counter()
                    iterations = 0
                    for value in steps:
                        theta.value = float(value)
                        iterations += problem.solve()
                    ok = True
                    break
                except SolverError:
                    ok = False
                    if pieces >= 2**cuts:
                        break
                    pieces *= 2
                    used += 1
            key = "no_cutting" if cuts == 0 else f"up_to_{cuts}_halvings"
            row[key] = {"converged": ok, "halvings": used, "newton_iterations": iterations if ok else None,
                        "wall_s": time.perf_counter() - start,
                        "volume_ratio": problem.volume() / volume0 if ok else None}
        rows.append(row)
    return rows


# -------------------------------------------------------------------- collected results


def _load(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.exists() else None


def collect(bench_dir: Path) -> dict:
    out: dict = {"missing": []}
    signaling = _load(bench_dir / "signaling.json")
    if signaling is None:
        out["missing"].append("python -m hyper.bench signaling")
    else:
        out["ode_dt"] = [{"label": f"RK4 dt {r['dt']:g} h", "dt": r["dt"], "failed": r["failed"],
                          "error_N": r.get("rel_error_N"), "wall_s": r.get("wall_s")}
                         for r in signaling["speed_accuracy"]]
        out["ode_rk45"] = signaling["single_vs_rk45"]
        out["rk4_largest_stable_dt"] = signaling["largest_stable_dt"]
        out["rk4_smallest_failing_dt"] = signaling["smallest_failing_dt"]
    growth = _load(bench_dir / "growth.json")
    if growth is None:
        out["missing"].append("python -m hyper.bench growth")
    else:
        out["growth_dt"] = [{"label": r["label"], "errors": r.get("errors"), "wall_s": r.get("wall_s"),
                             "cpu_s": r.get("cpu_s"), "max_halvings": r.get("max_halvings"),
                             "newton_iterations": r.get("newton_iterations"), "growth_steps": r.get("growth_steps")}
                            for r in growth["sweep"] if "failed" not in r]
        out["paper_settings"] = {k: growth["paper"].get(k) for k in ("label", "errors", "wall_s", "cpu_s")}
        out["default_settings"] = growth["default"]
    refinement = _load(bench_dir / "refinement.json")
    if refinement is None:
        out["missing"].append("python -m hyper.bench refinement")
    else:
        out["refinement"] = {"levels": refinement["levels"], "forces": refinement["forces"],
                             "lu_memory": refinement["lu_memory"]}
    solvers = _load(bench_dir / "solvers.json")
    if solvers is None:
        out["missing"].append("python -m hyper.bench solvers")
    else:
        keep = ("solver", "level", "unknowns", "ranks", "newton_iterations", "krylov_iterations", "solve_s",
                "mumps_used_mb", "peak_rss_mb_sum", "difference_from_lu", "memory_ratio", "time_ratio", "failed",
                "precision", "geometry", "variant", "last_ksp_reason")
        out["solvers"] = {key: [{k: r[k] for k in keep if k in r} for r in solvers[key]]
                          for key in ("levels", "precision", "gamg")}
    return out


# ------------------------------------------------------------------------------ charts


def _error(row: dict) -> float | None:
    errors = row.get("errors")
    if not errors:
        return None
    return max(errors["csa"], errors["volume"])


def matplotlib_ticker():
    import matplotlib.ticker

    return matplotlib.ticker


def pareto_chart(path: Path, result: dict) -> None:
    plt = plot.pyplot()
    panels = [(name, rows) for name, rows in result["dimensions"].items()]
    collected = result["collected"]
    if "ode_dt" in collected:
        panels.append(("ode_dt", None))
    if "growth_dt" in collected:
        panels.append(("growth_dt", None))
    if "solvers" in collected:
        panels.append(("solvers", None))
    cols = 3
    nrows = math.ceil(len(panels) / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(4.6 * cols, 3.6 * nrows), squeeze=False)
    for ax, (name, rows) in zip(axes.flat, panels):
        if name == "ode_dt":
            ok = [r for r in collected["ode_dt"] if not r["failed"] and r["error_N"]]
            ax.loglog([r["wall_s"] for r in ok], [r["error_N"] for r in ok], "o-")
            for r in ok[:: max(1, len(ok) // 5)]:
                ax.annotate(f"{r['dt']:g} h", (r["wall_s"], r["error_N"]), fontsize=7)
            rk45 = collected["ode_rk45"]
            ax.loglog([rk45["rk45_wall_s"]], [rk45["rk45_rel_error_N"]], "s", label="RK45 (paper)")
            ax.set_title("signaling ODE: RK4 dt (mwf, 9 weeks)")
            ax.set_ylabel("relative error of N(1512 h)")
            ax.legend(fontsize=7)
        elif name == "growth_dt":
            rows = [r for r in collected["growth_dt"] if _error(r)]
            ax.loglog([r["cpu_s"] for r in rows], [_error(r) for r in rows], "o-", label="Δtg sweep")
            for r in rows:
                ax.annotate(r["label"], (r["cpu_s"], _error(r)), fontsize=7)
            d, p = collected["default_settings"], collected["paper_settings"]
            ax.loglog([d["cpu_s"]], [max(d["errors"].values())], "*", ms=12, label="default")
            if p.get("errors"):
                ax.loglog([p["cpu_s"]], [max(p["errors"].values())], "s", label="paper's settings")
            ax.set_title("growth step Δtg (idealized, CPU s)")
            ax.set_ylabel("error / growth")
            ax.legend(fontsize=7)
        elif name == "solvers":
            floor = 1e-16
            rows = [r for r in collected["solvers"]["levels"] if "failed" not in r]
            for solver, marker in (("lu", "o"), ("iterative", "s")):
                mine = [r for r in rows if r["solver"] == solver]
                errs = [max(max(r["difference_from_lu"]["u"], r["difference_from_lu"]["p"]), floor)
                        if "difference_from_lu" in r else floor for r in mine]
                ax.loglog([r["solve_s"] for r in mine], errs, marker + "-",
                          label="MUMPS LU (reference, at the floor)" if solver == "lu" else "GMRES + BLR")
                for r, e in zip(mine, errs):
                    ax.annotate(f"{r['unknowns'] / 1e3:.0f}k", (r["solve_s"], e), fontsize=7)
            ax.set_title("linear solver (idealized, 2 ranks)")
            ax.set_ylabel(f"max |Δ(u, p)| / max, vs LU (floor {floor:g})")
            ax.legend(fontsize=7)
        else:
            ok = [r for r in rows if "failed" not in r and not r.get("reference")]
            ref = rows[0]
            floor = 1e-12
            for r in ok:
                err = max(_error(r) or 0.0, floor)
                ax.loglog([r["wall_s"]], [err], "o")
                ax.annotate(r["label"].split(", ", 1)[-1], (r["wall_s"], err), fontsize=7)
            if "failed" not in ref:
                ax.axvline(ref["wall_s"], color="k", ls=":", lw=1)
                ax.annotate("reference: " + ref["label"].split(", ", 1)[-1], (ref["wall_s"], floor),
                            fontsize=7, rotation=90, va="bottom")
            ax.set_title(name)
            ax.set_ylabel(f"error / growth (floor {floor:g})")
        ax.set_xlabel("wall s" if name != "growth_dt" else "CPU s")
        ax.xaxis.set_minor_formatter(matplotlib_ticker().NullFormatter())
        ax.grid(True, which="major", alpha=0.3)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    fig.suptitle("speed against accuracy: error of the final CSA/V ratios (or N) against time")
    fig.tight_layout()
    plot.save(fig, path, dpi=120)


def failure_chart(path: Path, result: dict) -> None:
    plt = plot.pyplot()
    fig, axes = plt.subplots(1, 4, figsize=(20, 4.2))
    collected = result["collected"]
    ax = axes[0]
    if "ode_dt" in collected:
        rows = collected["ode_dt"]
        ax.semilogy([r["dt"] for r in rows if not r["failed"]], [r["error_N"] for r in rows if not r["failed"]], "o-")
        for r in rows:
            if r["failed"]:
                ax.axvline(r["dt"], color="r", alpha=0.4)
        ax.set_title(f"RK4: stable to dt = {collected['rk4_largest_stable_dt']:g} h, fails from "
                     f"{collected['rk4_smallest_failing_dt']:g} h (red)", fontsize=9)
        ax.set_xlabel("dt (h)")
        ax.set_ylabel("relative error of N")
    ax = axes[1]
    rows = result["failure"]["growth_step"]
    for key, marker in (("no_cutting", "o"), ("up_to_4_halvings", "x")):
        th = [r["theta"] for r in rows]
        its = [r[key]["newton_iterations"] if r[key]["converged"] else np.nan for r in rows]
        ax.plot(th, its, marker + "-", label=key.replace("_", " "))
        for r in rows:
            if not r[key]["converged"]:
                ax.plot([r["theta"]], [0], "r" + marker)
    ax.axvline(1.005, color="k", ls=":", lw=1)
    ax.set_xscale("log")
    ax.set_xlabel("transverse growth ϑ applied in one step (dotted: a default step)")
    ax.set_ylabel("Newton iterations (red at 0: failed)")
    ax.set_title("Newton against the growth step (idealized, at rest)", fontsize=9)
    ax.legend(fontsize=8)
    ax = axes[2]
    if "refinement" in collected:
        ref = collected["refinement"]
        fit = ref["lu_memory"]
        common.plot_lu_memory(ax, ref["levels"], fit)
        if "solvers" in collected:
            blr = [r for r in collected["solvers"]["levels"] if r["solver"] == "iterative" and "failed" not in r]
            ax.loglog([r["unknowns"] for r in blr], [r["mumps_used_mb"] / 1024 for r in blr], "s",
                      label="GMRES + BLR LU (2 ranks), measured")
        ax.set_title(f"LU out of memory beyond ≈ {fit['unknowns_at_limit'] / 1e3:.0f}k unknowns "
                     f"({fit['memory_gib']:g} GiB)", fontsize=9)
        ax.set_ylabel("GiB")
        ax.legend(fontsize=8)
    ax = axes[3]
    if "solvers" in collected:
        sol = collected["solvers"]
        blr = [r for r in sol["levels"] if r["solver"] == "iterative" and "failed" not in r]
        ax.semilogx([r["unknowns"] for r in blr], [r["krylov_iterations"] / r["newton_iterations"] for r in blr],
                    "s-", label="GMRES + BLR 1e-4, idealized")
        for r in sol["gamg"]:
            if "failed" in r:
                ax.plot([r["unknowns"]], [0], "rx", ms=9, label=f"{r.get('variant', 'GAMG')} fieldsplit, "
                                                                f"{r['geometry']}: fails")
            else:
                ax.plot([r["unknowns"]], [r["krylov_iterations"] / r["newton_iterations"]], "^", ms=9,
                        label=f"{r.get('variant', 'GAMG')} fieldsplit, {r['geometry']}")
        prec = sol["precision"]
        failed = [r["precision"] for r in prec if "failed" in r]
        ok = [r for r in prec if "failed" not in r]
        ax.set_title("Krylov iterations per Newton step (growth solve at rest)\nBLR precision "
                     + ", ".join(f"{r['precision']:g}: {r['krylov_iterations'] / r['newton_iterations']:.0f}"
                                 for r in ok)
                     + (f"; fails at {', '.join(f'{p:g}' for p in failed)}" if failed else ""), fontsize=9)
        ax.set_xlabel("unknowns")
        ax.set_ylabel("iterations per Newton step (red at 0: failed)")
        ax.legend(fontsize=7)
    else:
        ax.axis("off")
    fig.tight_layout()
    plot.save(fig, path, dpi=120)


def _charts(output: Path, result: dict) -> None:
    pareto_chart(output / "atlas.png", result)
    failure_chart(output / "failure_map.png", result)


# -------------------------------------------------------------------------------- main


def parser() -> cli.Parser:
    p = cli.Parser("bench atlas", __doc__)
    p.add_argument("--geometries", nargs="+", metavar="ID", default=["idealized", "BFLH_VHF_Left"],
                   help="geometries of the dimensions measured here")
    p.add_argument("--protocol", default="mwf", help="named protocol")
    p.add_argument("--timeout", type=cli.number(), default=1800.0, help="seconds per run before it counts as failed")
    p.add_argument("--output", type=Path, default=Path("results/bench"), help="output folder")
    p.add_argument("--replot", action="store_true", help="redraw the charts from OUTPUT/atlas.json, run nothing")
    return p


def run(comm, args) -> int:
    if args.replot:
        result = json.loads((args.output / "atlas.json").read_text())
        _charts(args.output, result)
        return 0


    for name in args.geometries:
        if name not in geo.GEOMETRIES:
            raise InputError(f"unknown geometry {name!r}; known: {', '.join(geo.GEOMETRIES)}")
    protocols.named(args.protocol)

    start = time.perf_counter()
    dimensions = {}
    for name, cases in dimension_cases(args.geometries, args.protocol).items():
        print(f"atlas: {name}", flush=True)
        dimensions[name] = measure_dimension(cases, args.timeout, lambda m: print(m, flush=True))
    print("atlas: failure map, growth step", flush=True)
    failure = {"growth_step": newton_growth_step(), "iterative": ITERATIVE_FINDINGS}
    result = {"benchmark": "atlas", "machine": common.machine(), "protocol": args.protocol,
              "dimensions": dimensions, "failure": failure, "collected": collect(args.output),
              "versions": io.versions(), "wall_s": time.perf_counter() - start}
    args.output.mkdir(parents=True, exist_ok=True)
    io.write_json(args.output / "atlas.json", result)
    _charts(args.output, result)
    for name, rows in dimensions.items():
        for row in rows:
            err = _error(row)
            print(f"{name:28s} {row['label']:34s} wall {row.get('wall_s', float('nan')):8.1f} s  "
                  f"error {'-' if err is None else f'{err:.2e}'}"
                  + (f"  FAILED {row['failed']}" if "failed" in row else ""))
    for row in failure["growth_step"]:
        print(f"growth step ϑ = {row['theta']:g}: " + ", ".join(
            f"{k}: {'ok' if v['converged'] else 'failed'} ({v['newton_iterations']} its, {v['halvings']} cuts)"
            for k, v in row.items() if k != "theta"))
    if result["collected"]["missing"]:
        print("not in the atlas until run: " + "; ".join(result["collected"]["missing"]))
    print(f"wrote {args.output / 'atlas.json'}, atlas.png, failure_map.png")
    return 0


main = cli.entry(parser, run)
