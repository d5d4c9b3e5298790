"""Speed of a growth step: the Newton solve with kept factors against the lagged SNES Newton.

    python -m hyper.bench speed [--geometries idealized BFLH_VHF_Left ST_VHF_Left] [--protocol mwf]

Each geometry runs the same coupled run (``hyper.runs.driver.execute``, as ``hyper grow`` does:
snapshots and checkpoints written to a scratch folder) twice, each in its own process,
one after the other: with ``newton = "lagged"`` (SNES Newton, the Jacobian reassembled
every 10 iterations and after a failed solve: the algorithm before issue 17) and with
``newton = "kept"`` (`hyper.fem.newton`: a predictor, and iterations with LU factors and
secant pairs kept across steps). Recorded per run: time to the first growth step (wall and CPU from
the call of ``execute`` to the start of the first step's work: mesh, fibres, forms,
solver and section set-up, the first snapshot; the form cache is warm after the first
run of a geometry), the
wall and CPU time of the time loop and its phases (Jacobian assembly, factorisation,
back-solves, residual assembly, growth update, measures, signaling, and the rest: I/O),
Newton iterations, factorisations, and the CSA/CSA0 and V/V0 series. Factorisation and
back-solve times are PETSc's own event timers (MatLUFactorSym/Num, MatSolve), so both
algorithms are timed alike.

Also per run, from the same timers: the physical limit of a growth step as issue 17
defines it (one residual assembly and one back-substitution, at their mean times in this
run), the time per solved step as a multiple of it, and the floor of the loop: the least
any Newton method with factors kept across steps needs (one matrix assembled and
factorised, every solved step at the limit, and the growth update, measures and signaling
as measured). Both follow the machine, where the goals in seconds do not.

The series are compared as |x_kept − x_lagged| / (x_lagged,end − 1) at every step, for
x = CSA/CSA0 and V/V0: the difference as a fraction of the growth.

Writes results/bench/speed.json and speed.png (phases with each run's floor, iterations
and factorisations, series differences).
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from hyper.commands import cli
from hyper.commands.bench import common
from hyper.core import io
from hyper.core.params import InputError
from hyper.fem import geometry as geo
from hyper.fem.coupled import GrowthSettings
from hyper.model import protocols
from hyper.runs import driver, plot, runspec

GEOMETRIES = ("idealized", "BFLH_VHF_Left", "ST_VHF_Left")
METHODS = ("lagged", "kept")
# (name in the result, monitor phases summed into it); factorisation and back-solves
# come from PETSc's event log
PHASES = (("jacobian_assembly", ("jacobian assembly",)), ("residual_assembly", ("residual assembly",)),
          ("growth_update", ("growth update",)), ("measures", ("measures",)), ("signaling", ("signaling",)))
PETSC_EVENTS = {"factorisation": ("MatLUFactorSym", "MatLUFactorNum"), "back_solves": ("MatSolve",)}


class FirstStepTimings(common.Timings):
    """`common.Timings` that also notes when the run's first phase starts (the first
    growth step's signaling): wall and CPU time then, ``started``."""

    def __init__(self):
        super().__init__()
        self.started: tuple[float, float] | None = None

    def track(self, name: str):
        if self.started is None:
            self.started = (time.perf_counter(), time.process_time())
        return super().track(name)


def run_case(comm, case: dict) -> dict:
    """One run of ``case`` (geometry, protocol, newton) through `hyper.runs.driver.execute`."""
    import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
    from mpi4py import MPI
    from petsc4py import PETSc


    PETSc.Log.begin()
    clock = FirstStepTimings()
    spec = runspec.RunSpec(case["geometry"], protocols.named(case["protocol"]),
                       settings=GrowthSettings(newton=case["newton"]))
    comm.barrier()
    start, cpu0 = time.perf_counter(), time.process_time()
    with tempfile.TemporaryDirectory() as tmp:
        outputs = runspec.Outputs(Path(comm.bcast(tmp, root=0)) / "run.h5")
        result = driver.execute(comm, spec, outputs, monitor=clock, progress_every=60.0)
        comm.barrier()
    wall = time.perf_counter() - start
    cpu = time.process_time() - cpu0
    model = result.model

    def slowest(x):
        return comm.allreduce(x, op=MPI.MAX)

    loop = result.meta["wall_s"]
    phases = {name: slowest(sum(clock.seconds[k] for k in keys)) for name, keys in PHASES}
    for name, events in PETSC_EVENTS.items():
        phases[name] = slowest(sum(PETSc.Log.Event(e).getPerfInfo()["time"] for e in events))
    factorisations = int(PETSc.Log.Event("MatLUFactorNum").getPerfInfo()["count"])
    mechanics = slowest(clock.seconds["mechanics"])
    inside = phases["jacobian_assembly"] + phases["residual_assembly"] + phases["factorisation"] + phases["back_solves"]
    phases["newton_other"] = max(mechanics - inside, 0.0)
    phases["io_and_rest"] = max(slowest(loop) - mechanics - sum(phases[k] for k in ("growth_update", "measures",
                                                                                     "signaling")), 0.0)
    series = result.series
    solved = int(np.count_nonzero(series["newton_iterations"]))
    residual = phases["residual_assembly"] / max(clock.calls["residual assembly"], 1)
    back_solve = phases["back_solves"] / max(int(PETSc.Log.Event("MatSolve").getPerfInfo()["count"]), 1)
    refresh = (phases["jacobian_assembly"] + phases["factorisation"]) / max(factorisations, 1)
    rest = sum(phases[k] for k in ("growth_update", "measures", "signaling"))
    per_step = slowest(loop) / max(solved, 1)
    return {
        **case,
        "ranks": comm.size,
        "unknowns": model.problem.num_dofs,
        "csa_ratio": model.csa_ratio,
        "volume_ratio": model.volume_ratio,
        "growth_steps": model.step,
        "solved_steps": solved,
        "newton_iterations": int(series["newton_iterations"].sum()),
        "jacobian_assemblies": model.jacobian.assemblies,
        "factorisations": factorisations,
        "halvings": int(series["halvings"].max()),
        "first_step_wall_s": slowest(clock.started[0] - start),
        "first_step_cpu_s": slowest(clock.started[1] - cpu0),
        "setup_wall_s": slowest(wall - loop),
        "loop_wall_s": slowest(loop),
        "per_solved_step_s": per_step,
        # issue 17's physical limit of a step: one residual and one back-substitution
        "residual_s": residual,
        "back_solve_s": back_solve,
        "limit_s": residual + back_solve,
        "per_step_over_limit": per_step / (residual + back_solve),
        # the least loop any Newton method with kept factors needs: one matrix, each solved
        # step at the limit, and the growth, measures and signaling as measured
        "floor_s": refresh + solved * (residual + back_solve) + rest,
        "wall_s": slowest(wall),
        "cpu_s": comm.allreduce(cpu, op=MPI.SUM),
        "phases_s": phases,
        "series": {name: series[name].tolist() for name in ("t", "csa_ratio", "volume_ratio")},
    }


def differences(old: dict, new: dict) -> dict:
    """The largest |new − old| over the series, as a fraction of old's final growth."""
    out = {}
    for key in ("csa_ratio", "volume_ratio"):
        a, b = np.asarray(old["series"][key]), np.asarray(new["series"][key])
        if a.shape != b.shape:
            out[key] = float("nan")
            continue
        out[key] = float(np.max(np.abs(b - a)) / abs(a[-1] - 1.0))
    return out


def chart(path: Path, result: dict) -> None:
    plt = plot.pyplot()
    rows = [(g, m, result["runs"][g][m]) for g in result["geometries"] for m in METHODS
            if "failed" not in result["runs"][g][m]]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.8))
    names = [name for name, _ in PHASES] + list(PETSC_EVENTS) + ["newton_other", "io_and_rest"]
    labels = ["{}\n{}".format(g.replace("_", "\n", 1), m) for g, m, _ in rows]  # muscle ids on two lines
    bottom = np.zeros(len(rows))
    for i, name in enumerate(names):
        values = np.array([r["phases_s"][name] for _, _, r in rows])
        axes[0].bar(labels, values, bottom=bottom, label=name.replace("_", " "), color=f"C{i}")
        bottom += values
    for k, (_, _, r) in enumerate(rows):
        axes[0].annotate(f"CPU {r['cpu_s']:.1f} s", (k, bottom[k]), ha="center", va="bottom", fontsize=7)
        axes[0].hlines(r["floor_s"], k - 0.4, k + 0.4, colors="k", linestyles="--", lw=1.2,
                       label="floor with kept factors" if k == 0 else None)
    axes[0].set_ylabel("wall time of the time loop (s)")
    axes[0].set_ylim(0, 1.5 * bottom.max())  # room for the legend above the bars
    axes[0].legend(fontsize=7, ncol=2, loc="upper left")
    axes[0].tick_params(axis="x", labelsize=7)
    x = np.arange(len(rows))
    axes[1].bar(x - 0.2, [r["newton_iterations"] for _, _, r in rows], 0.4, label="Newton iterations")
    axes[1].bar(x + 0.2, [r["factorisations"] for _, _, r in rows], 0.4, label="factorisations")
    axes[1].set_xticks(x, labels, fontsize=7)
    axes[1].set_yscale("log")
    axes[1].legend(fontsize=8)
    for g in result["geometries"]:
        runs = result["runs"][g]
        if any("failed" in runs[m] for m in METHODS):
            continue
        t = np.asarray(runs["lagged"]["series"]["t"]) / 168
        for key, style in (("csa_ratio", "-"), ("volume_ratio", "--")):
            a, b = (np.asarray(runs[m]["series"][key]) for m in METHODS)
            diff = np.abs(b - a) / abs(a[-1] - 1.0)
            axes[2].semilogy(t, np.maximum(diff, 1e-16), style, label=f"{g} {key.split('_')[0]}")
    axes[2].axhline(1e-6, color="k", lw=1, ls=":", label="1e-6 of the growth")
    axes[2].set_xlabel("time (weeks)")
    axes[2].set_ylabel("|kept − lagged| / growth")
    axes[2].legend(fontsize=7)
    fig.suptitle(f"{result['protocol']}: lagged SNES Newton against kept factors (1 rank, load average "
                 f"{result['machine']['load_average_at_start'][0]:.1f} on {result['machine']['cpus']} cores)",
                 fontsize=10)
    fig.tight_layout()
    plot.save(fig, path, dpi=130)


def parser() -> cli.Parser:
    p = cli.Parser("bench speed", __doc__)
    p.add_argument("--geometries", nargs="+", default=list(GEOMETRIES), help="meshes")
    p.add_argument("--protocol", default="mwf", help="named protocol")
    p.add_argument("--ranks", type=cli.integer(1), default=1, help="MPI ranks per run")
    p.add_argument("--timeout", type=cli.number(), default=3600.0, help="seconds per run")
    p.add_argument("--output", type=Path, default=Path("results/bench"), help="output folder")
    common.add_worker_options(p)
    return p


def run(comm, args) -> int:
    if args.worker:
        common.write_worker_result(comm, args.json, run_case(comm, args.worker))
        return 0

    for name in args.geometries:
        if name not in geo.GEOMETRIES:
            raise InputError(f"--geometries: unknown geometry {name!r}; known: {', '.join(geo.GEOMETRIES)}")
    protocols.named(args.protocol)
    if args.ranks < 1:
        raise InputError(f"--ranks must be a positive integer, got {args.ranks}")
    host = common.machine()
    started = time.perf_counter()
    runs: dict[str, dict] = {}
    for name in args.geometries:
        runs[name] = {}
        for method in METHODS:
            case = {"geometry": name, "protocol": args.protocol, "newton": method}
            r = common.run_worker("speed", case, args.ranks, args.timeout)
            runs[name][method] = r
            if "failed" in r:
                print(f"  {name} {method}: FAILED {r['failed']}", flush=True)
                continue
            print(f"  {name} {method}: CSA/CSA0 {r['csa_ratio']:.9f}, V/V0 {r['volume_ratio']:.9f}, "
                  f"{r['newton_iterations']} Newton its, {r['factorisations']} factorisations, loop "
                  f"{r['loop_wall_s']:.1f} s ({r['per_solved_step_s']:.3f} s/step), CPU {r['cpu_s']:.1f} s, "
                  f"first step after {r['first_step_wall_s']:.2f} s (CPU {r['first_step_cpu_s']:.2f} s); "
                  f"limit {r['limit_s']:.3f} s/step (residual {r['residual_s']:.3f} s + back-solve "
                  f"{r['back_solve_s']:.3f} s), a step {r['per_step_over_limit']:.1f}x it; floor of the loop "
                  f"{r['floor_s']:.1f} s", flush=True)
    summary = {}
    for name, pair in runs.items():
        if any("failed" in pair[m] for m in METHODS):
            continue
        old, new = pair["lagged"], pair["kept"]
        summary[name] = {"series_difference_of_growth": differences(old, new),
                         "final_difference_of_growth": {
                             k: abs(new[k] - old[k]) / abs(old[k] - 1.0) for k in ("csa_ratio", "volume_ratio")},
                         "cpu_ratio": old["cpu_s"] / new["cpu_s"],
                         "loop_wall_ratio": old["loop_wall_s"] / new["loop_wall_s"]}
        print(f"  {name}: kept is {summary[name]['cpu_ratio']:.1f}x less CPU; series differ by at most "
              f"{summary[name]['series_difference_of_growth']['csa_ratio']:.1e} (CSA), "
              f"{summary[name]['series_difference_of_growth']['volume_ratio']:.1e} (V) of the growth", flush=True)
    result = {"machine": {**host, "load_average_at_end": os.getloadavg()}, "protocol": args.protocol,
              "ranks": args.ranks, "geometries": list(args.geometries), "runs": runs, "summary": summary,
              "wall_s": time.perf_counter() - started}
    out = args.output
    out.mkdir(parents=True, exist_ok=True)
    io.write_json(out / "speed.json", result)
    chart(out / "speed.png", result)
    print(f"wrote {out / 'speed.json'}, {out / 'speed.png'}")
    return 0


main = cli.entry(parser, run)

if __name__ == "__main__":
    sys.exit(main())
