"""Calibration and the dose atlas on the ODE growth model, side by side with full coupled runs.

    python -m hyper.bench calibrate [--skip-coupled-fit]

Times, in this process on one rank:
- the one-parameter fit of kM to DeFreitas (data/defreitas.csv, mwf) on `hyper.model.surrogate`
  (goal <= 60 s on 2 cores) and the same fit with every evaluation a full coupled run on
  the idealized muscle (`calibrate.coupled_model`), with both optima;
- the dose atlas of `hyper.dose` (1120 protocols, with and without the feedback; goal <= 2 min);
- surrogate_check: the coupled idealized runs of mwf, every3days and weekly against the
  surrogate at every growth-step end: the section factor (CSA/CSA0 - 1) / (N - 1) at 9
  weeks and the largest error as a fraction of the 9-week growth.
Writes results/bench/calibrate.json.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from hyper.analysis import calibrate, dose
from hyper.commands import cli
from hyper.commands.bench import common
from hyper.core import io
from hyper.fem import coupled
from hyper.model import protocols, signaling, surrogate
from hyper.runs import driver, fidelity, runspec


def timed_fit(evaluate, data) -> dict:
    bounds = np.array([calibrate.BOUNDS["kM"]])
    f = calibrate.fit(evaluate, [data], ["kM"], bounds, np.array([0.01]))
    return {"kM": float(f.x[0]), "low": float(f.low[0]), "high": float(f.high[0]), "rmse": f.rmse,
            "evaluations": f.evaluations, "wall_s": f.wall_s}


def surrogate_check(comm) -> dict:
    out = {}
    factor = surrogate.section_factor("idealized")
    for name in ("mwf", "every3days", "weekly"):
        protocol = protocols.named(name)
        model, *_ = driver.build(comm, runspec.RunSpec("idealized", protocol))
        reports = list(model.run())
        t = np.array([r.t for r in reports])
        csa = np.array([r.csa_ratio for r in reports])
        fast = surrogate.grow(signaling.SignalingParams(), protocol, t, factor=factor)
        out[name] = {"section_factor": (csa[-1] - 1.0) / (reports[-1].states[4] - 1.0),
                     "error_of_growth": float(np.max(np.abs(fast.csa_ratio - csa)) / (csa[-1] - 1.0)),
                     "coupled_csa_ratio": float(csa[-1]), "surrogate_csa_ratio": float(fast.csa_ratio[-1])}
        print(f"surrogate check {name}: {out[name]}", flush=True)
    return out


def parser() -> cli.Parser:
    p = cli.Parser("bench calibrate", __doc__)
    p.add_argument("--skip-coupled-fit", action="store_true", help="leave out the fit by coupled runs (minutes)")
    p.add_argument("--output", type=Path, default=Path("results/bench"), help="output folder")
    return p


def run(comm, args) -> int:
    mwf = protocols.named("mwf")
    data = calibrate.dataset("data/defreitas.csv", mwf)
    choice = fidelity.choose(fidelity.Scene("idealized", "mwf", False, "growth"), fidelity.DEFAULT_ACCURACY)
    base = signaling.SignalingParams()
    result = {"benchmark": "calibrate", "machine": common.machine(), "signaling_dt": choice.signaling_dt,
              "growth_dt": choice.growth_dt, "versions": io.versions()}
    fast = calibrate.surrogate_model([data], ["kM"], base, signaling_dt=choice.signaling_dt,
                                     factor=surrogate.section_factor("idealized"), feedback="hill")
    result["fit_surrogate"] = timed_fit(fast, data)
    print(f"fit on the ODE growth model: {result['fit_surrogate']}", flush=True)
    start = time.perf_counter()
    for law in ("hill", "none"):
        dose.atlas(law, signaling_dt=choice.signaling_dt, factor=surrogate.section_factor("idealized"))
    result["atlas"] = {"protocols": int(dose.loads().size), "feedback_laws": 2, "wall_s": time.perf_counter() - start}
    print(f"dose atlas: {result['atlas']}", flush=True)
    result["surrogate_check"] = surrogate_check(comm)
    if not args.skip_coupled_fit:
        settings = coupled.GrowthSettings(growth_dt=choice.growth_dt, signaling_dt=choice.signaling_dt)
        slow = calibrate.coupled_model(comm, [data], ["kM"], base, geometry="idealized", settings=settings)
        result["fit_coupled"] = timed_fit(slow, data)
        result["speedup"] = result["fit_coupled"]["wall_s"] / result["fit_surrogate"]["wall_s"]
        print(f"fit by coupled runs: {result['fit_coupled']}; the ODE model is {result['speedup']:.0f}x faster",
              flush=True)
    if comm.rank == 0:
        io.write_json(args.output / "calibrate.json", result)
    print(f"wrote {args.output / 'calibrate.json'}")
    return 0


main = cli.entry(parser, run)
