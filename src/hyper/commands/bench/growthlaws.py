"""The growth laws beyond the paper (issue 35), each switch against the default run, side by side.

    python -m hyper.bench growthlaws [--geometry BFLH_VHF_Left] [--quick] [--parts NAME …] [--ranks 1]

Every part is one coupled run of the same scene (the geometry, 9 weeks of ``mwf``; --quick:
its first --quick-end hours) with one switch changed from the default, in a process of its
own (fresh PETSc state, its own clock), one after the other, after a short warm-up run that
fills the form cache:

    default      the paper's model with the default regional CSA (--sections 9)
    sections-0   no regional sections (--sections 0): what the nine exact cuts per growth step cost
    fiber        along-fibre growth (--fiber-growth stretch) under mwf with every session a passive
                 stretch of --stretch (the protocol field ``stretch``), τ_f and λ_crit at their
                 defaults: an ϑ_f update and a growth solve in every session step
    detraining   the gain's turnover (--detraining --tau hours): a decay of N in every growth step
    local        local mechanosensing (--stimulus local): the contraction at the sessions' intensity
                 solved once before the first step, each cell's stimulus from its active fibre stress

Per part: the wall and CPU time of the time loop and of the set-up (mesh, forms, and for the
local stimulus its contraction), the ratios to the default's (the loop's, and set-up and
loop's), growth steps, Newton solves, iterations and Jacobian assemblies (each one factorised),
the time in the measures (CSA cuts, volume), the final CSA/CSA0 and V/V0 (and
ϑ_f, the fascicle length change, with along-fibre growth). A part is one entry of ``PARTS``
(its name, what it is, the settings it changes and the protocol's stretch): a switch added
later is one more entry. Writes results/bench/growthlaws.json and
growthlaws.png (CPU time ratio, set-up included, and Newton iterations per part).
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from pathlib import Path

from hyper.commands import cli
from hyper.commands.bench import common
from hyper.core import io
from hyper.core.params import InputError
from hyper.fem import geometry as geo
from hyper.fem.coupled import GrowthSettings
from hyper.model import protocols
from hyper.runs import plot
from hyper.runs.runspec import RunSpec

TAU = 223.0  # h: the detraining τ hyper calibrate fits jointly to DeFreitas and Narici (docs/growth-laws.md)
STRETCH = 1.1  # the passive stretch of a session with along-fibre growth
QUICK_END = 336.0  # h: mwf's rest week and first training week


@dataclasses.dataclass(frozen=True)
class Part:
    name: str
    what: str
    settings: dict  # GrowthSettings fields changed from the default (options of the run)
    stretched: bool = False  # every session of the protocol carries the --stretch


PARTS = (
    Part("default", "default (--sections 9)", {}),
    Part("sections-0", "--sections 0", {"sections": 0}),
    Part("fiber", "--fiber-growth stretch, sessions stretched", {"fiber_growth": "stretch"}, stretched=True),
    Part("detraining", "--detraining TAU", {"detraining": None}),  # None: the --tau given
    Part("local", "--stimulus local", {"stimulus": "local"}),
)
NAMES = tuple(p.name for p in PARTS)


def scene(case: dict) -> protocols.Protocol:
    """mwf, cut at the case's end, its sessions stretched where the part says."""
    mwf = protocols.named("mwf")
    end = case.get("end") or mwf.end
    sessions = tuple(dataclasses.replace(s, stretch=case["stretch"]) if case.get("stretch") else s
                     for s in mwf.sessions if s.start < end)
    return protocols.Protocol(sessions, end=end, name=f"mwf_to_{end:g}h" if end < mwf.end else "mwf")


def run_case(comm, case: dict) -> dict:
    """One part's coupled run: its time, counts and final measures (slowest rank's wall)."""
    import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
    from mpi4py import MPI

    from hyper.runs.driver import build

    spec = RunSpec(case["geometry"], scene(case), settings=GrowthSettings(**case["settings"]))
    clock = common.Timings()
    comm.barrier()
    start, setup_cpu0 = time.perf_counter(), time.process_time()
    model = build(comm, spec, monitor=clock)[0]
    setup, setup_cpu = time.perf_counter() - start, time.process_time() - setup_cpu0
    comm.barrier()
    wall0, cpu0 = time.perf_counter(), time.process_time()
    reports = list(model.run())
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    last = reports[-1]
    return {**case, "ranks": comm.size, "unknowns": model.problem.num_dofs,
            "setup_wall_s": comm.allreduce(setup, op=MPI.MAX), "setup_cpu_s": comm.allreduce(setup_cpu, op=MPI.SUM),
            "wall_s": comm.allreduce(wall, op=MPI.MAX),
            "cpu_s": comm.allreduce(cpu, op=MPI.SUM), "growth_steps": model.step,
            "newton_solves": clock.calls["mechanics"],
            "newton_iterations": int(sum(r.newton_iterations for r in reports)),
            "jacobian_assemblies": model.jacobian.assemblies,
            "signaling_s": comm.allreduce(clock.seconds["signaling"], op=MPI.MAX),
            "measures_s": comm.allreduce(clock.seconds["measures"], op=MPI.MAX),
            "csa_ratio": last.csa_ratio, "volume_ratio": last.volume_ratio,
            **({"fiber_stretch": last.extra["fiber_stretch"]} if "fiber_stretch" in last.extra else {})}


def summary(row: dict) -> str:
    if "failed" in row:
        return f"FAILED {row['failed']}"
    fibre = f", ϑ_f {row['fiber_stretch']:.5f}" if "fiber_stretch" in row else ""
    return (f"{row['wall_s']:.1f} s (set-up {row['setup_wall_s']:.1f} s), {row['growth_steps']} steps, "
            f"{row['newton_solves']} solves, "
            f"{row['newton_iterations']} Newton its, {row['jacobian_assemblies']} Jacobians, "
            f"CSA/CSA0 {row['csa_ratio']:.5f}, V/V0 {row['volume_ratio']:.5f}{fibre}")


def case_of(part: Part, args) -> dict:
    settings = {k: (args.tau if k == "detraining" and v is None else v) for k, v in part.settings.items()}
    return {"part": part.name, "what": part.what, "geometry": args.geometry, "settings": settings,
            "stretch": args.stretch if part.stretched else None, "end": args.quick_end if args.quick else None}


def chart(path: Path, result: dict) -> None:
    plt = plot.pyplot()
    rows = [r for r in result["parts"] if "failed" not in r]
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 3.8), layout="constrained")
    names = [r["part"] for r in rows]
    ratios = [r["total_cpu_ratio_to_default"] for r in rows]
    a.barh(names, ratios, color=["0.5" if n == "default" else "tab:blue" for n in names])
    a.axvline(1.0, color="k", lw=1)
    for i, r in enumerate(rows):
        a.text(ratios[i], i, f" {ratios[i]:.2f}× ({r['setup_cpu_s'] + r['cpu_s']:.0f} s)", va="center", fontsize=8)
    a.set_xlabel("CPU time of the set-up and the time loop / default's")
    a.set_xlim(0, 1.35 * max(ratios))
    b.barh(names, [r["newton_iterations"] for r in rows], color="tab:orange")
    for i, r in enumerate(rows):
        b.text(r["newton_iterations"], i, f" {r['newton_iterations']} its, {r['growth_steps']} steps", va="center",
               fontsize=8)
    b.set_xlabel("Newton iterations of the run")
    b.set_xlim(0, 1.45 * max(r["newton_iterations"] for r in rows))
    protocol = "mwf" if not result["quick"] else f"mwf to {result['quick_end']:g} h"
    fig.suptitle(f"{result['geometry']}, {protocol}, {result['ranks']} rank(s): each growth law against the default",
                 fontsize=10)
    plot.save(fig, path, dpi=120)


def parser() -> cli.Parser:
    p = cli.Parser("bench growthlaws", __doc__)
    p.add_argument("--geometry", default="BFLH_VHF_Left", help="the mesh")
    p.add_argument("--parts", nargs="+", choices=NAMES, metavar="PART", default=list(NAMES),
                   help=f"which parts to run ({', '.join(NAMES)}); default is always run, as the reference")
    p.add_argument("--quick", action="store_true", help="cut mwf at --quick-end hours (a check, not the result)")
    p.add_argument("--quick-end", type=cli.positive("hours"), default=QUICK_END,
                   help="end of the cut mwf with --quick (h)")
    p.add_argument("--tau", type=cli.positive("hours"), default=TAU, help="the detraining part's time constant (h)")
    p.add_argument("--stretch", type=cli.number(above=1.0), default=STRETCH,
                   help="the passive stretch of every session in the fiber part (stretched / rest length)")
    p.add_argument("--ranks", type=cli.integer(1, 1024), default=1, help="MPI ranks per run")
    p.add_argument("--timeout", type=cli.positive("seconds"), default=3600.0, help="seconds per run before it counts "
                   "as failed")
    p.add_argument("--output", type=Path, default=Path("results/bench"), help="folder for growthlaws.json and .png")
    common.add_worker_options(p)
    return p


def run(comm, args) -> int:
    if args.worker:
        common.write_worker_result(comm, args.json, run_case(comm, args.worker))
        return 0
    if args.geometry not in geo.GEOMETRIES:
        raise InputError(f"--geometry: unknown geometry {args.geometry!r}; known: {', '.join(geo.GEOMETRIES)}")
    end = protocols.named("mwf").end
    if args.quick and args.quick_end >= end:
        raise InputError(f"--quick-end: {args.quick_end:g} h is not before mwf's end ({end:g} h)")
    host = common.machine()
    started = time.perf_counter()
    chosen = [p for p in PARTS if p.name == "default" or p.name in args.parts]
    print(f"growthlaws: {args.geometry}, {', '.join(p.name for p in chosen)}, {args.ranks} rank(s), load average "
          f"{host['load_average_at_start'][0]:.2f} on {os.cpu_count()} cores", flush=True)
    # a first run compiles the forms into the cache every later process reads: a warm-up, not
    # reported, so that the default (timed first) does not pay for it
    warm = common.run_worker("growthlaws", {**case_of(PARTS[0], args), "end": min(args.quick_end, QUICK_END)},
                             args.ranks, args.timeout)
    print("  warm-up    " + (f"FAILED {warm['failed']}" if "failed" in warm else f"{warm['wall_s']:.1f} s"), flush=True)
    rows = []
    for part in chosen:
        row = common.run_worker("growthlaws", case_of(part, args), args.ranks, args.timeout)
        rows.append(row)
        print(f"  {part.name:<11} {summary(row)}", flush=True)
    default = rows[0]
    if "failed" in default:
        raise InputError(f"the default run failed: {default['failed']}; nothing written")
    for row in rows:
        if "failed" not in row:
            row["wall_ratio_to_default"] = row["wall_s"] / default["wall_s"]
            row["cpu_ratio_to_default"] = row["cpu_s"] / default["cpu_s"]
            # a switch may cost in the set-up (the local stimulus' contraction): counted here
            row["total_cpu_ratio_to_default"] = (row["cpu_s"] + row["setup_cpu_s"]) / (
                default["cpu_s"] + default["setup_cpu_s"])
    result = {"benchmark": "growthlaws", "machine": {**host, "load_average_at_end": os.getloadavg()},
              "geometry": args.geometry, "ranks": args.ranks, "quick": args.quick, "quick_end": args.quick_end,
              "tau_h": args.tau, "stretch": args.stretch, "parts": rows, "versions": io.versions(),
              "wall_s": time.perf_counter() - started}
    args.output.mkdir(parents=True, exist_ok=True)
    io.write_json(args.output / "growthlaws.json", result)
    chart(args.output / "growthlaws.png", result)
    for row in rows:
        if "failed" not in row:
            print(f"  {row['part']:<11} time loop: wall x{row['wall_ratio_to_default']:.3f}, "
                  f"CPU x{row['cpu_ratio_to_default']:.3f}; with the set-up: "
                  f"CPU x{row['total_cpu_ratio_to_default']:.3f}")
    print(f"wrote {args.output / 'growthlaws.json'} and growthlaws.png", flush=True)
    return 0


main = cli.entry(parser, run)

if __name__ == "__main__":
    sys.exit(main())
