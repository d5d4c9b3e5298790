"""Protocol design: the protocol with the least weekly load (or fewest sessions) that reaches a
target CSA gain by a given week, on the ODE growth model (`hyper.model.surrogate`).

A candidate is k sessions a week on k of the allowed weekdays (spread as evenly over the week
as those days allow, `spread`), of one intensity and one duration, every week from day 0 to
the target week: a `Repeat` rule, so that the design is written as the ``[repeat]`` protocol
TOML that ``hyper grow --protocol FILE`` runs (`toml_text`). The grid is the atlas's
(`hyper.analysis.dose`): durations its multiples of 0.25 h (sessions end on an RK4 step),
intensities multiples of 0.05 (finer than the atlas: the load is linear in them), both within
the constraints. Its load is the atlas's, Σ intensity × duration per week.

Batched as the atlas: the candidates of one schedule (k, duration) differ only in intensity
(and, with a posterior, in kM) and are one batch of the signaling RK4 (`evaluate`).

With kM samples of a posterior the gain of a candidate is the one it reaches with probability
P over them: the (1 - P) quantile of its gains. `choose` picks the design; `front` is the
gain–load Pareto front (more load never less gain on it), drawn by `figure`.
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hyper.analysis.dose import DURATIONS
from hyper.core.params import InputError
from hyper.model import signaling, surrogate
from hyper.model.protocols import WEEK, WEEKDAYS, Repeat
from hyper.runs import plot

INTENSITIES = np.round(np.arange(1, 21) * 0.05, 10)
OBJECTIVES = ("load", "sessions")


@dataclass(frozen=True)
class Constraints:
    """What the design must reach and within what it may choose; contradictions are InputErrors."""

    target: float  # CSA/CSA0 - 1 to reach
    week: int  # by the end of this week (training from day 0)
    sessions: tuple[int, int]  # per week, least and most
    weekdays: tuple[str, ...]  # the days a session may fall on
    intensity: tuple[float, float]  # least and most, in [0, 1]
    duration: tuple[float, float]  # h, least and most

    def __post_init__(self):
        if not (np.isfinite(self.target) and self.target > 0):
            raise InputError(f"--target must be a gain > 0 %, got {100 * self.target:g}")
        for name, (low, high) in (("--sessions", self.sessions), ("--intensity", self.intensity),
                                  ("--duration", self.duration)):
            if low > high:
                raise InputError(f"{name}: the least ({low:g}) is more than the most ({high:g})")
        if len(set(self.weekdays)) < len(self.weekdays) or not set(self.weekdays) <= set(WEEKDAYS):
            raise InputError(f"--weekdays: each of {', '.join(WEEKDAYS)} at most once, got {' '.join(self.weekdays)}")
        if self.sessions[0] > len(self.weekdays):
            raise InputError(f"--sessions: at least {self.sessions[0]} a week, but only {len(self.weekdays)} "
                             f"weekday(s) allowed ({' '.join(self.weekdays)})")
        if not self.intensities().size:
            raise InputError(f"--intensity: no intensity of the grid (multiples of 0.05) lies in "
                             f"[{self.intensity[0]:g}, {self.intensity[1]:g}]")
        if not self.durations().size:
            raise InputError(f"--duration: no duration of the grid (multiples of 0.25 h up to 4 h) lies in "
                             f"[{self.duration[0]:g}, {self.duration[1]:g}] h")

    def per_week(self) -> range:
        return range(self.sessions[0], min(self.sessions[1], len(self.weekdays)) + 1)

    def intensities(self) -> np.ndarray:
        low, high = self.intensity
        return INTENSITIES[(INTENSITIES >= low - 1e-12) & (INTENSITIES <= high + 1e-12)]

    def durations(self) -> np.ndarray:
        low, high = self.duration
        return DURATIONS[(DURATIONS >= low - 1e-12) & (DURATIONS <= high + 1e-12)]


def spread(k: int, allowed: tuple[str, ...]) -> tuple[str, ...]:
    """The k allowed weekdays with the largest smallest gap round the week (the first such set in
    the week's order): recovery between sessions, as the paper's mwf spreads three."""
    days = sorted(WEEKDAYS.index(d) for d in allowed)

    def smallest_gap(subset):
        return min((subset[(i + 1) % k] - subset[i]) % 7 or 7 for i in range(k))

    best = max(itertools.combinations(days, k), key=smallest_gap)  # max keeps the first of equals
    return tuple(WEEKDAYS[d] for d in best)


@dataclass(frozen=True)
class Candidate:
    sessions_per_week: int
    weekdays: tuple[str, ...]
    intensity: float
    duration_h: float
    gain: float  # CSA/CSA0 - 1 at the target week (with a posterior: reached with probability P)

    @property
    def load(self) -> float:
        return self.sessions_per_week * self.intensity * self.duration_h

    def rule(self, week: int) -> Repeat:
        return Repeat(self.duration_h, self.intensity, week, self.weekdays)

    def describe(self) -> dict:
        return {"sessions_per_week": self.sessions_per_week, "weekdays": list(self.weekdays),
                "intensity": self.intensity, "duration_h": self.duration_h, "load": self.load,
                "gain_pct": 100 * self.gain}


def evaluate(constraints: Constraints, params: signaling.SignalingParams, *, kM=None, probability: float = 0.5,
             signaling_dt: float = 0.05, factor: float = 1.0) -> list[Candidate]:
    """Every candidate with its gain at the end of the target week; ``kM`` samples: the gain reached
    with ``probability`` over them."""
    intensities = constraints.intensities()
    end = constraints.week * WEEK
    draws = None if kM is None else np.asarray(kM, dtype=float)
    out = []
    for k in constraints.per_week():
        days = spread(k, constraints.weekdays)
        for d in constraints.durations():
            protocol = Repeat(float(d), 1.0, constraints.week, days).protocol("candidate")
            if draws is None:
                unit, batch = surrogate.intensity_batch(protocol, intensities, params)
            else:  # members: intensity-major, each intensity over every kM sample
                unit, batch = surrogate.intensity_batch(protocol, np.repeat(intensities, draws.size), params)
                batch = dataclasses.replace(batch, kM=np.tile(draws, intensities.size))
            g = surrogate.grow(batch, unit, [end], signaling_dt=signaling_dt, factor=factor).csa_ratio[0] - 1.0
            if draws is not None:
                g = np.quantile(g.reshape(intensities.size, draws.size), 1.0 - probability, axis=1)
            out += [Candidate(k, days, float(i), float(d), float(gi)) for i, gi in zip(intensities, g)]
    return out


def choose(candidates: list[Candidate], target: float, objective: str) -> Candidate:
    """The candidate reaching ``target`` with the least load (ties: fewer sessions, more gain), or
    with the fewest sessions (ties: less load); InputError naming the most reachable gain."""
    if objective not in OBJECTIVES:
        raise InputError(f"objective must be one of {', '.join(OBJECTIVES)}, got {objective!r}")
    reached = [c for c in candidates if c.gain >= target]
    if not reached:
        top = max(candidates, key=lambda c: c.gain)
        raise InputError(f"--target {100 * target:g} %: out of reach under the constraints; the most reachable "
                         f"gain is {100 * top.gain:.3g} % ({top.sessions_per_week} x {top.duration_h:g} h at "
                         f"intensity {top.intensity:g} a week)")
    if objective == "load":
        return min(reached, key=lambda c: (round(c.load, 9), c.sessions_per_week, -c.gain))
    return min(reached, key=lambda c: (c.sessions_per_week, round(c.load, 9), -c.gain))


def front(candidates: list[Candidate]) -> list[Candidate]:
    """The gain–load Pareto front: by increasing load, each candidate with more gain than every
    one of less or equal load (of equal loads, the best gain)."""
    out = []
    for c in sorted(candidates, key=lambda c: (c.load, -c.gain)):
        if not out or c.gain > out[-1].gain:
            out.append(c)
    return out


def toml_text(best: Candidate, week: int, name: str, note: str) -> str:
    """The design as a protocol TOML (`hyper.model.protocols.load`): a ``[repeat]`` rule."""
    days = ", ".join(f'"{d}"' for d in best.weekdays)
    return (f"# {note}\n"
            f'name = "{name}"\n\n[repeat]\nweekdays = [{days}]\nduration = {best.duration_h!r}\n'
            f"intensity = {best.intensity!r}\nweeks = {week}\n")


def figure(path: Path, candidates: list[Candidate], pareto: list[Candidate], best: Candidate, target: float,
           title: str) -> Path:
    """Every candidate's gain against its load, the Pareto front, the target and the design."""
    plt = plot.pyplot()
    fig, ax = plt.subplots(figsize=(6, 4), constrained_layout=True)
    ax.scatter([c.load for c in candidates], [100 * c.gain for c in candidates], s=4, color="0.75",
               label="candidates")
    ax.step([c.load for c in pareto], [100 * c.gain for c in pareto], where="post", label="Pareto front")
    ax.axhline(100 * target, color="k", ls=":", lw=1, label=f"target {100 * target:g} %")
    ax.plot([best.load], [100 * best.gain], "r*", ms=12,
            label=f"design: {best.sessions_per_week} x {best.duration_h:g} h @ {best.intensity:g}")
    ax.set_xlabel("weekly load, Σ intensity × duration (h)")
    ax.set_ylabel("CSA gain (%)")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return plot.save(fig, path)
