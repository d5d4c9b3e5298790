"""Scene-adaptive fidelity against the paper's settings, side by side.

    python -m hyper.bench fidelity [--geometries TA_VHF_Right] [--accuracy 1e-3]

For each geometry, three `mwf` runs on one rank, each in its own process (the worker
of `hyper.bench growth`):
- the choice of `hyper.runs.fidelity.choose` for a uniform growth question at --accuracy
  (what `python -m hyper.grow --accuracy A` runs);
- the paper's settings: Δtg = 1 h, no growth during sessions, signaling by RK45;
- a converged reference: Δtg = 6 h, RK4 at 0.05 h (5.5e-7 of the growth from the
  0.5 h answer on the idealized muscle, `python -m hyper.bench growth`).
Reports the error of both against the reference, |x - x_ref| / (x_ref - 1) for
x = CSA/CSA0 and V/V0, and the wall and CPU time of their time loops; the goal is the
choice at least 10x faster than the paper's settings at no more than the requested
error. Writes results/bench/fidelity.json.
"""

from __future__ import annotations

from pathlib import Path

from hyper.commands import cli
from hyper.commands.bench import common
from hyper.commands.bench import growth as growth_bench
from hyper.core import io
from hyper.core.params import InputError
from hyper.fem import geometry as geo
from hyper.runs import fidelity

REFERENCE = {"growth_dt": 6.0, "signaling_dt": 0.05}


def cases(geometry: str, accuracy: float) -> dict[str, dict]:
    choice = fidelity.choose(fidelity.Scene(geometry, "mwf", False, "growth"), accuracy)
    return {
        "reference": {"label": "reference: Δtg 6 h, RK4 0.05 h", "geometry": geometry, "protocol": "mwf",
                      "signaling": "rk4", "settings": dict(REFERENCE)},
        "choice": {"label": f"--accuracy {accuracy:g}: {choice.describe()}", "geometry": geometry,
                   "protocol": "mwf", "signaling": "rk4",
                   "settings": {"growth_dt": choice.growth_dt, "signaling_dt": choice.signaling_dt}},
        "paper": {"label": "paper: Δtg 1 h, no growth in sessions, RK45", "geometry": geometry, "protocol": "mwf",
                  "signaling": "rk45", "settings": {"growth_dt": growth_bench.PAPER_DT, "grow_during_sessions": False}},
    }


def compare(rows: dict[str, dict], accuracy: float) -> dict:
    ref = rows["reference"]
    out = {}
    for name in ("choice", "paper"):
        row = rows[name]
        if "failed" in row or "failed" in ref:
            continue
        errors = growth_bench.growth_errors(row["csa_ratio"], row["volume_ratio"],
                                            ref["csa_ratio"], ref["volume_ratio"])
        out[name] = {"errors": errors, "within_accuracy": max(errors.values()) <= accuracy,
                     "wall_s": row["wall_s"], "cpu_s": row["cpu_s"]}
    if "choice" in out and "paper" in out:
        out["speedup_wall"] = out["paper"]["wall_s"] / out["choice"]["wall_s"]
        out["speedup_cpu"] = out["paper"]["cpu_s"] / out["choice"]["cpu_s"]
    return out


def parser() -> cli.Parser:
    p = cli.Parser("bench fidelity", __doc__)
    p.add_argument("--geometries", nargs="+", metavar="ID", default=["TA_VHF_Right"], help="geometries")
    p.add_argument("--accuracy", type=cli.number(), default=1e-3, help="requested error, fraction of the growth")
    p.add_argument("--timeout", type=cli.number(), default=7200.0, help="seconds per run")
    p.add_argument("--output", type=Path, default=Path("results/bench"), help="output folder")
    return p


def run(comm, args) -> int:
    for name in args.geometries:
        if name not in geo.GEOMETRIES:
            raise InputError(f"unknown geometry {name!r}; known: {', '.join(geo.GEOMETRIES)}")
    plans = {name: cases(name, args.accuracy) for name in args.geometries}

    result = {"benchmark": "fidelity", "machine": common.machine(), "accuracy": args.accuracy,
              "reference_settings": REFERENCE,
              "geometries": {}, "versions": io.versions()}
    for name, plan in plans.items():
        rows = {}
        for key, case in plan.items():
            print(f"fidelity: {name}: {case['label']} …", flush=True)
            row = common.run_worker("growth", case, 1, args.timeout)
            row.pop("series", None)
            rows[key] = row
        result["geometries"][name] = {"runs": rows, "comparison": compare(rows, args.accuracy)}
        comparison = result["geometries"][name]["comparison"]
        for key in ("choice", "paper"):
            if key in comparison:
                c = comparison[key]
                print(f"  {key}: error {max(c['errors'].values()):.2e}, wall {c['wall_s']:.1f} s, "
                      f"CPU {c['cpu_s']:.1f} s",
                      flush=True)
        if "speedup_wall" in comparison:
            print(f"  choice is {comparison['speedup_wall']:.1f}x faster (wall), "
                  f"{comparison['speedup_cpu']:.1f}x (CPU) than the paper's settings", flush=True)
    io.write_json(args.output / "fidelity.json", result)
    print(f"wrote {args.output / 'fidelity.json'}")
    return 0


main = cli.entry(parser, run)
