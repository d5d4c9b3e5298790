"""The dose–response atlas: the 9-week CSA gain of training protocols, on the ODE growth model.

A protocol is k sessions a week (1–7) of one intensity (0.1–1.0) and one duration
(0.25–4 h) over eight weeks after a rest week, as the paper's protocols (`schedule`): week
w has its sessions at 168 (w + 1) + 24 floor(7 i / k) h, i < k (k = 3 is mwf), the end at
1512 h. Its gain is CSA/CSA0 - 1 at 1512 h by `hyper.model.surrogate` on a section factor
(`atlas`). Batched: the protocols of one schedule (k, duration) differ only in intensity,
and are one batch of the signaling RK4 (`surrogate.intensity_batch`).

The load of a protocol is Σ intensity × duration per week (h at full intensity, `loads`).
For a budget B the best protocol is the largest gain with load <= B (`best_under`); the
diminishing-returns curve is the best gain against the load allowed (`frontier`).
`coupled_gain` is one protocol's gain by a full coupled run, the check of the atlas; the
figures are `heat_maps` and `returns`. The job is `hyper.commands.dose` (``hyper dose``).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from hyper.model import signaling, surrogate
from hyper.model.protocols import WEEK, Protocol, Session
from hyper.runs import driver, plot, runspec

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
    start = time.perf_counter()
    model, *_ = driver.build(comm, runspec.RunSpec("idealized", protocol, signaling.SignalingParams(), settings))
    *_, last = model.run()
    return last.csa_ratio - 1.0, time.perf_counter() - start


def heat_maps(path: Path, gains: np.ndarray) -> Path:
    """One panel per sessions a week: the gain over intensity × duration."""
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

