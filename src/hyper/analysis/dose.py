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

import json
import time
from pathlib import Path

import numpy as np

from hyper.commands import cli
from hyper.core.log import info
from hyper.model import signaling, surrogate
from hyper.model.protocols import WEEK, Protocol, Session
from hyper.runs import fidelity, runspec

SESSIONS = np.arange(1, 8)  # per week
INTENSITIES = np.round(np.arange(1, 11) * 0.1, 10)
DURATIONS = np.arange(1, 17) * 0.25  # h: multiples of the RK4 steps, so sessions end on a step
END = 9 * WEEK
GOAL_PP = 0.05  # percentage points, the agreement asked of the checks


def schedule(per_week: int, duration: float, intensity: float = 1.0) -> Protocol:
    """k sessions a week for eight weeks after a rest week, spread over the week as mwf."""
    days = [24.0 * (7 * i // per_week) for i in range(per_week)]
    sessions = tuple(Session(WEEK * (w + 1) + d, float(duration), float(intensity)) for w in range(8) for d in days)
    return Protocol(sessions, END, f"{per_week}x{duration:g}h@{intensity:g}")


def loads() -> np.ndarray:
    """Σ intensity × duration per week, shape (sessions, intensities, durations)."""
    return SESSIONS[:, None, None] * INTENSITIES[None, :, None] * DURATIONS[None, None, :]


def atlas(feedback: str = "hill", *, signaling_dt: float = 0.05, factor: float = 1.0) -> np.ndarray:
    """The 9-week CSA gain (CSA/CSA0 - 1) of every protocol, shape (sessions, intensities, durations)."""
    gains = np.empty((SESSIONS.size, INTENSITIES.size, DURATIONS.size))
    for a, k in enumerate(SESSIONS):
        for c, d in enumerate(DURATIONS):
            unit, params = surrogate.intensity_batch(schedule(int(k), d), INTENSITIES)
            g = surrogate.grow(params, unit, [END], signaling_dt=signaling_dt, feedback=feedback, factor=factor)
            gains[a, :, c] = g.csa_ratio[0] - 1.0
    return gains


def best_under(gains: np.ndarray, budget: float) -> tuple[int, int, int] | None:
    """Index (sessions, intensity, duration) of the largest gain with load <= budget."""
    allowed = loads() <= budget + 1e-12
    if not allowed.any():
        return None
    return tuple(int(i) for i in np.unravel_index(np.argmax(np.where(allowed, gains, -np.inf)), gains.shape))


def frontier(gains: np.ndarray, budgets: np.ndarray) -> np.ndarray:
    """The best gain for each load budget (NaN where no protocol fits)."""
    out = np.full(budgets.shape, np.nan)
    for j, b in enumerate(budgets):
        index = best_under(gains, float(b))
        if index is not None:
            out[j] = gains[index]
    return out


def describe(index: tuple[int, int, int]) -> dict:
    a, b, c = index
    return {"sessions_per_week": int(SESSIONS[a]), "intensity": float(INTENSITIES[b]),
            "duration_h": float(DURATIONS[c]), "load": float(loads()[index])}


def coupled_gain(comm, protocol: Protocol, settings) -> tuple[float, float]:
    """(9-week CSA gain, wall s) of a full coupled idealized run."""
    from hyper.runs import driver as run

    start = time.perf_counter()
    model, *_ = run.build(comm, runspec.RunSpec("idealized", protocol, signaling.SignalingParams(), settings))
    *_, last = model.run()
    return last.csa_ratio - 1.0, time.perf_counter() - start


def parser() -> cli.Parser:
    p = cli.Parser("dose", __doc__)
    p.add_argument("--checks", type=cli.integer(0, 1000), default=10, help="protocols checked by coupled runs")
    p.add_argument("--seed", type=cli.integer(0), default=0, help="seed of the protocols checked")
    p.add_argument("--budgets", type=float, nargs="+", default=[1.0, 2.0, 4.0, 8.0],
                   help="weekly loads Σ intensity × duration (h) to find the best protocol under")
    p.add_argument("--accuracy", type=float, default=fidelity.DEFAULT_ACCURACY,
                   help="error allowed, a fraction of the growth: chooses the RK4 step (hyper.runs.fidelity)")
    p.add_argument("--output", type=cli.output(folder=True), default="results/dose", help="output folder")
    return p


def run(comm, args) -> int:
    from hyper.core.params import InputError
    from hyper.fem.coupled import GrowthSettings

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
    from hyper.core import io

    L = loads()
    protocols_ = [{**describe(index), "gain_pct": 100 * float(gains["hill"][index]),
                   "gain_pct_without_feedback": 100 * float(gains["none"][index])}
                  for index in np.ndindex(L.shape)]
    result = {"protocols": protocols_, "best_under_budget": best, "checks": checks, "largest_difference_pp": worst,
              "goal_pp": GOAL_PP, "atlas_wall_s": atlas_s, "signaling_dt": choice.signaling_dt,
              "section_factor": surrogate.section_factor("idealized"), "versions": io.versions()}
    path = args.output / "dose.json"
    with io.atomic_path(path) as tmp:
        tmp.write_text(json.dumps(result, indent=1) + "\n")
    return path


def heat_maps(path: Path, gains: np.ndarray) -> Path:
    """One panel per sessions a week: the gain over intensity × duration."""
    from hyper.runs import plot

    plt = plot.pyplot()
    fig, axes = plt.subplots(1, SESSIONS.size, figsize=(3 * SESSIONS.size, 3.2), sharey=True, constrained_layout=True)
    top = 100 * gains.max()
    for a, ax in enumerate(axes):
        image = ax.pcolormesh(DURATIONS, INTENSITIES, 100 * gains[a], vmin=0, vmax=top, shading="nearest")
        ax.set_title(f"{SESSIONS[a]} sessions/week", fontsize=9)
        ax.set_xlabel("duration (h)")
    axes[0].set_ylabel("intensity")
    fig.colorbar(image, ax=axes, label="9-week CSA gain (%)")
    return plot.save(fig, path)


def returns(path: Path, gains: dict) -> Path:
    """The best gain against the weekly load allowed, with and without the feedback."""
    from hyper.runs import plot

    plt = plot.pyplot()
    budgets = np.linspace(0.05, loads().max(), 300)
    fig, ax = plt.subplots(figsize=(6, 4), constrained_layout=True)
    for law, label in (("hill", "feedback h(CSA/CSA0)"), ("none", "no feedback")):
        ax.plot(budgets, 100 * frontier(gains[law], budgets), label=label)
    ax.set_xlabel("weekly load allowed, Σ intensity × duration (h)")
    ax.set_ylabel("best 9-week CSA gain (%)")
    ax.grid(alpha=0.3)
    ax.legend()
    return plot.save(fig, path)


main = cli.entry(parser, run, locks=lambda args: [args.output])

if __name__ == "__main__":
    raise SystemExit(main())
