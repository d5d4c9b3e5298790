"""Protocol design: the protocol with the least weekly load that reaches a target CSA gain by a week.

    hyper design --target 5 --week 8 [--sessions 1 7] [--weekdays mon … sun] [--intensity 0.05 1]
                 [--duration 0.25 4] [--objective load|sessions] [--posterior FILE --probability P]
                 [--no-check] [--output results/design]

A candidate is k sessions a week (--sessions MIN MAX) on k of the --weekdays, spread over the
week as evenly as they allow, of one intensity (multiples of 0.05 in --intensity) and one
duration (multiples of 0.25 h in --duration), every week from day 0 to the end of --week. Its
gain is CSA/CSA0 - 1 then, by the ODE growth model (`hyper.model.surrogate`) on --geometry's
section factor; the candidates of one schedule are one batch (`hyper.analysis.design`). Its
load is Σ intensity × duration per week (h at full intensity), as in ``hyper dose``.

The design reaches --target (%) with the least load (--objective sessions: with the fewest
sessions a week, then the least load). With --posterior (the posterior.h5 of ``hyper
calibrate --method bayes``) every candidate runs at --draws of its kM samples, and its gain is
the one it reaches with --probability P (the 1 - P quantile); the check then runs at their
median kM.

Check: the design is run by the full coupled model on --geometry with the same RK4 step
(`hyper.runs.driver.execute`); the goal is to agree within 0.05 percentage points
(--no-check skips it). Refused, before anything is written: a target out of reach under the
constraints (the message names the most reachable gain), contradictory constraints, bad values.

Writes OUTPUT/design.toml (the design, a [repeat] protocol: ``hyper grow --protocol
OUTPUT/design.toml``), design.json (the design, the Pareto front, every candidate, the check),
design.png (the gain–load Pareto front) and check.h5 (the coupled run).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from hyper.analysis import design
from hyper.analysis.dose import GOAL_PP
from hyper.commands import cli
from hyper.core import io
from hyper.core.log import info
from hyper.core.params import InputError
from hyper.fem.coupled import GrowthSettings
from hyper.model import signaling, surrogate
from hyper.model.protocols import WEEK, WEEKDAYS, load
from hyper.runs import driver, fidelity, locks, runspec
from hyper.runs.checkpoint import file_digest

DEFAULT_PROBABILITY = 0.9


def parser() -> cli.Parser:
    p = cli.Parser("design", __doc__)
    p.add_argument("--target", type=cli.number(above=0, most=1000), required=True, metavar="PERCENT",
                   help="the CSA gain to reach, CSA/CSA0 - 1 in %%")
    p.add_argument("--week", type=cli.integer(1, 104), required=True, help="reached by the end of this week")
    p.add_argument("--sessions", type=cli.integer(1, 7), nargs=2, default=[1, 7], metavar=("MIN", "MAX"),
                   help="sessions a week allowed")
    p.add_argument("--weekdays", nargs="+", choices=WEEKDAYS, default=list(WEEKDAYS), help="days a session may fall on")
    p.add_argument("--intensity", type=cli.number(0, 1), nargs=2, default=[0.05, 1.0], metavar=("MIN", "MAX"),
                   help="intensities allowed (the grid: multiples of 0.05)")
    p.add_argument("--duration", type=cli.positive("hours"), nargs=2, default=[0.25, 4.0], metavar=("MIN", "MAX"),
                   help="session durations allowed, h (the grid: multiples of 0.25 h up to 4 h)")
    p.add_argument("--objective", choices=design.OBJECTIVES, default="load",
                   help="least weekly load, or fewest sessions a week (then least load)")
    p.add_argument("--geometry", choices=sorted(surrogate.SECTION_FACTOR), default="idealized",
                   help="the muscle: its section factor, and the check's geometry")
    p.add_argument("--posterior", type=Path, reads=True, metavar="H5",
                   help="posterior.h5 of hyper calibrate --method bayes: design over its kM samples")
    p.add_argument("--probability", type=cli.number(above=0, below=1), metavar="P",
                   help=f"with --posterior: reach the target with this probability ({DEFAULT_PROBABILITY:g} if not "
                        "given)")
    p.add_argument("--draws", type=cli.integer(1, 2000), default=100, help="with --posterior: kM samples used")
    p.add_argument("--seed", type=cli.seed(), default=0, help="with --posterior: seed of the samples drawn")
    p.add_argument("--accuracy", type=cli.number(), default=fidelity.DEFAULT_ACCURACY,
                   help="error allowed, a fraction of the growth: chooses the RK4 step (hyper.runs.fidelity)")
    p.add_argument("--no-check", action="store_true", help="skip the coupled run of the design")
    p.add_argument("--output", type=cli.output(folder=True), default="results/design", help="output folder")
    return p


def posterior_kM(path: Path, draws: int, seed: int) -> tuple[np.ndarray, dict]:
    """``draws`` of the file's kM samples (all, if it has fewer), drawn without replacement."""
    with io.reading_h5(path, "posterior file") as f:
        if "kM" not in f:
            raise InputError(f"--posterior {path}: no kM samples (datasets: {', '.join(sorted(f)) or 'none'}); "
                             "give the posterior.h5 of hyper calibrate --method bayes --fit kM")
        samples = np.asarray(f["kM"][()], dtype=float)
        attrs = {k: f.attrs[k].item() if hasattr(f.attrs[k], "item") else f.attrs[k]
                 for k in ("method", "geometry", "feedback") if k in f.attrs}
    if samples.ndim != 1 or not samples.size or not np.all(np.isfinite(samples) & (samples > 0)):
        raise InputError(f"--posterior {path}: kM samples must be a non-empty list of finite numbers > 0")
    if attrs.get("feedback", "hill") != "hill":
        raise InputError(f"--posterior {path}: fitted with feedback {attrs['feedback']!r}; the design uses hill")
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(samples.size, size=min(draws, samples.size), replace=False))
    return samples[pick], {"file": str(path), "sha256": file_digest(path), "samples": int(samples.size),
                           "draws": int(pick.size), **{k: str(v) for k, v in attrs.items()}}


def run(comm, args) -> int:
    if args.probability is not None and args.posterior is None:
        raise InputError("--probability: only with --posterior")
    constraints = design.Constraints(args.target / 100, args.week, tuple(args.sessions), tuple(args.weekdays),
                                     tuple(args.intensity), tuple(args.duration))
    probability = DEFAULT_PROBABILITY if args.probability is None else args.probability
    kM, source = (None, None) if args.posterior is None else posterior_kM(args.posterior, args.draws, args.seed)
    choice = fidelity.choose(fidelity.Scene(args.geometry, "design", False, "growth"), args.accuracy)
    factor = surrogate.section_factor(args.geometry)
    params = signaling.SignalingParams()
    start = time.perf_counter()
    candidates = design.evaluate(constraints, params, kM=kM, probability=probability,
                                 signaling_dt=choice.signaling_dt, factor=factor)
    best = design.choose(candidates, constraints.target, args.objective)  # an unreachable target stops here
    grid_s = time.perf_counter() - start
    pareto = design.front(candidates)
    info(comm, f"design: {len(candidates)} candidates{'' if kM is None else f' x {kM.size} kM samples'} in "
               f"{grid_s:.1f} s (RK4 {choice.signaling_dt:g} h)")
    info(comm, f"design: {best.sessions_per_week} x {best.duration_h:g} h at intensity {best.intensity:g} a week "
               f"({' '.join(best.weekdays)}), load {best.load:g} h: +{100 * best.gain:.3f} % by week {args.week}"
               + ("" if kM is None else f" with probability {probability:g}"))

    protocol = best.rule(args.week).protocol("design")
    at = params if kM is None else dataclasses.replace(params, kM=float(np.median(kM)))
    check = None
    if not args.no_check:
        point = best.gain if kM is None else float(
            surrogate.grow(at, protocol, [protocol.end], signaling_dt=choice.signaling_dt,
                           factor=factor).csa_ratio[0] - 1.0)
        check = coupled_check(comm, args, protocol, at, choice, point)

    if comm.rank == 0:
        note = (f"hyper design: +{args.target:g} % CSA by week {args.week} with the least "
                f"{'load' if args.objective == 'load' else 'sessions'} on {args.geometry}")
        with io.atomic_path(args.output / "design.toml") as tmp:
            tmp.write_text(design.toml_text(best, args.week, "design", note))
        load(args.output / "design.toml")  # what grow will read: a design that does not load is a bug here
        write(args, constraints, candidates, pareto, best, check, source, probability, choice, grid_s)
        design.figure(args.output / "design.png", candidates, pareto, best, constraints.target,
                      f"{args.geometry}, week {args.week}" + ("" if kM is None else f", P = {probability:g}"))
    info(comm, f"design: wrote {args.output / 'design.toml'}, design.json and design.png")
    return cli.EXIT_OK


def coupled_check(comm, args, protocol, params, choice, point: float) -> dict:
    """The design's gain by a full coupled run against the ODE model's at the same parameters."""
    spec = runspec.RunSpec(args.geometry, protocol, params, GrowthSettings(signaling_dt=choice.signaling_dt))
    outputs = runspec.Outputs(args.output / "check.h5")
    with locks.hold(comm, [outputs.h5]):
        result = driver.execute(comm, spec, outputs, checkpoints=False, progress_every=1e9)
        if comm.rank == 0:
            outputs.store(result.series, result.meta, runspec.result_groups(spec))
    coupled = float(np.interp(protocol.end, result.series["t"], result.series["csa_ratio"])) - 1.0
    diff = 100 * (point - coupled)
    info(comm, f"design: check: coupled {100 * coupled:.4f} %, ODE model {100 * point:.4f} %, difference "
               f"{diff:+.2g} pp (goal {GOAL_PP:g} pp)")
    return {"result": str(outputs.h5), "coupled_gain_pct": 100 * coupled, "surrogate_gain_pct": 100 * point,
            "difference_pp": diff, "goal_pp": GOAL_PP, "within_goal": abs(diff) <= GOAL_PP,
            "kM": float(np.asarray(params.kM)), "coupled_wall_s": result.meta["wall_s"]}


def write(args, constraints, candidates, pareto, best, check, source, probability, choice, grid_s) -> Path:
    result = {
        "design": {**best.describe(), "protocol": str(args.output / "design.toml"), "weeks": args.week,
                   "end_h": args.week * WEEK},
        "target_pct": args.target, "week": args.week, "objective": args.objective, "geometry": args.geometry,
        "constraints": {"sessions": list(constraints.sessions), "weekdays": list(constraints.weekdays),
                        "intensity": list(constraints.intensity), "duration_h": list(constraints.duration)},
        "posterior": source, "probability": None if source is None else probability,
        "pareto_front": [c.describe() for c in pareto], "candidates": [c.describe() for c in candidates],
        "check": check, "grid_wall_s": grid_s, "signaling_dt": choice.signaling_dt,
        "section_factor": surrogate.section_factor(args.geometry), "versions": io.versions(),
    }
    return io.write_json(args.output / "design.json", result, indent=1)


main = cli.entry(parser, run, locks=lambda args: [args.output])
