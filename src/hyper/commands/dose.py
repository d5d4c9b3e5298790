"""The dose–response atlas: the 9-week CSA gain of training protocols, on the ODE growth model.

    hyper dose [--checks 10] [--budgets 1 2 4 8] [--output results/dose]

A protocol is k sessions a week (1–7) of one intensity (0.1–1.0) and one duration
(0.25–4 h) over eight weeks after a rest week, as the paper's protocols: week w has its
sessions at 168 (w + 1) + 24 floor(7 i / k) h, i < k (k = 3 is mwf), the end at 1512 h.
Its gain is CSA/CSA0 - 1 at 1512 h by `hyper.model.surrogate` on the idealized muscle's section
factor. Batched: the protocols of one schedule (k, duration) differ only in intensity, and
are one batch of the signaling RK4 (`surrogate.intensity_batch`); the whole grid is
computed with the feedback h and without it (h = 1).

The load of a protocol is Σ intensity × duration per week (h at full intensity). For each
--budgets B the best protocol is the largest gain with load <= B; the diminishing-returns
curve is the best gain against the load allowed, with and without the feedback.

--checks N protocols drawn at random (seeded) are run by the full coupled model on the
idealized muscle with the same RK4 step; the goal is to agree within 0.05 percentage points.

Writes OUTPUT/dose.json (every protocol and its gains), dose.png (heat maps) and
dose_returns.png (the diminishing returns).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from hyper.analysis.dose import GOAL_PP, atlas, best_under, coupled_gain, describe, heat_maps, loads, returns, schedule
from hyper.commands import cli
from hyper.core import io
from hyper.core.log import info
from hyper.core.params import InputError
from hyper.fem.coupled import GrowthSettings
from hyper.model import surrogate
from hyper.runs import fidelity


def parser() -> cli.Parser:
    p = cli.Parser("dose", __doc__)
    p.add_argument("--checks", type=cli.integer(0, 1000), default=10, help="protocols checked by coupled runs")
    p.add_argument("--seed", type=cli.seed(), default=0, help="seed of the protocols checked")
    p.add_argument("--budgets", type=cli.positive("hours"), nargs="+", default=[1.0, 2.0, 4.0, 8.0],
                   help="weekly loads Σ intensity × duration (h) to find the best protocol under")
    p.add_argument("--accuracy", type=cli.number(), default=fidelity.DEFAULT_ACCURACY,
                   help="error allowed, a fraction of the growth: chooses the RK4 step (hyper.runs.fidelity)")
    p.add_argument("--output", type=cli.output(folder=True), default="results/dose", help="output folder")
    return p


def run(comm, args) -> int:
    if any(not b > 0 for b in args.budgets):
        raise InputError("--budgets: every budget must be > 0")
    choice = fidelity.choose(fidelity.Scene("idealized", "dose", False, "growth"), args.accuracy)
    factor = surrogate.section_factor("idealized")
    start = time.perf_counter()
    gains = {law: atlas(law, signaling_dt=choice.signaling_dt, factor=factor) for law in ("hill", "none")}
    atlas_s = time.perf_counter() - start
    info(comm, f"dose: {gains['hill'].size} protocols x 2 feedback laws in {atlas_s:.1f} s "
               f"(RK4 {choice.signaling_dt:g} h)")

    best = {}
    for b in args.budgets:
        index = best_under(gains["hill"], b)
        best[f"{b:g}"] = None if index is None else {**describe(index), "gain_pct": 100 * float(gains["hill"][index])}
        if index is not None:
            info(comm, f"dose: load <= {b:g} h/week: best {best[f'{b:g}']}")

    rng = np.random.default_rng(args.seed)
    picks = rng.choice(gains["hill"].size, size=min(args.checks, gains["hill"].size), replace=False)
    settings = GrowthSettings(signaling_dt=choice.signaling_dt)
    checks = []
    for flat in picks:
        index = np.unravel_index(flat, gains["hill"].shape)
        d = describe(index)
        protocol = schedule(d["sessions_per_week"], d["duration_h"], d["intensity"])
        gain, wall = coupled_gain(comm, protocol, settings)
        diff = 100 * (float(gains["hill"][index]) - gain)
        checks.append({**d, "surrogate_gain_pct": 100 * float(gains["hill"][index]), "coupled_gain_pct": 100 * gain,
                       "difference_pp": diff, "coupled_wall_s": wall})
        info(comm, f"dose: check {protocol.name}: coupled {100 * gain:.4f} %, surrogate "
                   f"{100 * float(gains['hill'][index]):.4f} %, difference {diff:+.2g} pp")
    worst = max((abs(c["difference_pp"]) for c in checks), default=None)
    if worst is not None:
        info(comm, f"dose: largest difference {worst:.2g} pp over {len(checks)} coupled runs (goal {GOAL_PP:g} pp)")

    if comm.rank == 0:
        write(args, gains, best, checks, worst, atlas_s, choice)
        heat_maps(args.output / "dose.png", gains["hill"])
        returns(args.output / "dose_returns.png", gains)
    info(comm, f"dose: wrote {args.output / 'dose.json'}, dose.png and dose_returns.png")
    return cli.EXIT_OK


def write(args, gains, best, checks, worst, atlas_s, choice) -> Path:
    L = loads()
    protocols_ = [{**describe(index), "gain_pct": 100 * float(gains["hill"][index]),
                   "gain_pct_without_feedback": 100 * float(gains["none"][index])}
                  for index in np.ndindex(L.shape)]
    result = {"protocols": protocols_, "best_under_budget": best, "checks": checks, "largest_difference_pp": worst,
              "goal_pp": GOAL_PP, "atlas_wall_s": atlas_s, "signaling_dt": choice.signaling_dt,
              "section_factor": surrogate.section_factor("idealized"), "versions": io.versions()}
    path = args.output / "dose.json"
    return io.write_json(path, result, indent=1)


main = cli.entry(parser, run, locks=lambda args: [args.output])
