"""Sobol sensitivity analysis of the signaling model (MODEL.md §7), farmed across MPI ranks.

What is analysed: N(480 h) under ``daily15`` from the *baseline* rest state (MODEL.md §1),
as a function of the 14 parameters in ``PARAMETERS``, each uniform on [0.5, 2] x its
baseline value. All of it can be changed, in SALib's problem form: ``--parameters``
and ``--range LOW HIGH`` (multiples of the baselines), ``--protocol``, ``--at H`` (N, or
the CSA gain, at H hours instead of the protocol's end), or a TOML file (``--problem``)
with the keys of `CONFIG_KEYS`, at its top level or in a study file's [sobol] table:

    [sobol]
    function = "signaling"            # or csa-gain
    protocol = "mwf"
    at = 336.0                        # h; the protocol's end by default
    names = ["kM", "kF", "a10"]       # SALib's problem: names and absolute bounds
    bounds = [[0.005, 0.02], [0.01, 0.04], [0.045, 0.18]]
    samples = 4096

Options win over the file. SALib draws a Saltelli/Sobol design with second-order terms,
N (2D + 2) rows for N base samples, and estimates first-order, total and second-order
indices with bootstrap confidence intervals.

Evaluation. The rows are evaluated in chunks (jobs of ``hyper.runs.farm``), each chunk one
batch along the batch axis of the signaling model, through ``signaling.integrate``. The
default backend is its compiled RK4 step (``backend="c"``, C through cffi, the route
DOLFINx takes for its form kernels), bit for bit the numpy batch and an order of
magnitude faster (``python -m hyper.bench sobol``), with failures masked: a member that
fails (a non-finite or negative state) does not stop the others, its output becomes NaN.
The ``numpy`` backend is signaling's numpy batch with failures raised; there a failing
member fails its whole chunk.

Failures. Members whose trajectory fails are counted and reported, never dropped
silently. SALib needs every output, so by default (``on_failure="abort"``) no indices
are computed while any member failed; ``"drop"`` removes every base sample that has a
failed row (its whole block of 2D + 2 rows, which keeps SALib's design intact) and
says how many.

The grown muscle (``--function csa-gain``): the 9-week CSA gain CSA/CSA0 - 1 at 1512 h
under ``mwf`` on the fast ODE growth model (`hyper.model.surrogate`: the signaling ODEs with the
Hill feedback kM = kM0 h(CSA/CSA0) at every period end, the idealized muscle's section
factor), as a function of the 17 parameters in ``GAIN_PARAMETERS``: the 12 signaling rates,
kM, kF, the thresholds thetaM and thetaF, and the feedback's Hill exponent ``hill_n``, each
uniform on [0.5, 2] x its baseline (hill_n on [2, 8] around the paper's 4). The Hill
constant K stays 1: h(1) = 1 needs it, and a K off 1 would change kM before any growth.
Batched like ``signaling``: a chunk is one batch of `surrogate.grow` (compiled RK4,
failures masked).

The job (``run_chunks`` and ``run``) writes each finished chunk atomically to
``<output>/chunks/<digest>/``, the digest covering the sample matrix and every setting,
so a rerun skips finished chunks and never reuses chunks of a different run.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import shutil
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mpi4py import MPI

from hyper.commands import cli
from hyper.core import log
from hyper.core.log import PROGRESS_EVERY, info
from hyper.core.params import InputError, positive_hours
from hyper.model import protocols
from hyper.model import signaling as S
from hyper.model.protocols import Protocol, named
from hyper.runs import locks
from hyper.runs.plot import pyplot

PARAMETERS = ("a10", "a20", "a3", "a4", "b1", "b2", "b3", "b4", "c21", "c32", "c42", "c43", "kM", "kF")
# csa-gain: the signaling rates, kM, kF, the thresholds and the feedback's Hill exponent
GAIN_PARAMETERS = (*PARAMETERS, "thetaM", "thetaF", "hill_n")
HILL_N = 4.0  # the paper's Hill exponent of the feedback (growth.feedback)
GAIN_PROTOCOL = "mwf"  # 9 weeks: the gain is read at its end, 1512 h
GAIN_GEOMETRY = "idealized"  # the section factor of surrogate.SECTION_FACTOR

# The species a parameter belongs to (the figures' colours). A coupling parameter belongs to
# the species whose equation it sits in; ``SOURCE`` names the species it comes from.
SPECIES = {
    "IGF1": ("a10", "b1"),
    "AKT": ("a20", "b2", "c21"),
    "FOXO": ("a3", "b3", "c32"),
    "mTOR": ("a4", "b4", "c42", "c43"),
    "balance": ("kM", "kF", "thetaM", "thetaF"),
    "feedback": ("hill_n",),
}
SOURCE = {"c21": "IGF1", "c32": "AKT", "c42": "AKT", "c43": "FOXO"}

LOW, HIGH = 0.5, 2.0  # bounds as multiples of the baseline value
ISHIGAMI_AB = (7.0, 0.1)
# base samples: N (2D + 2) rows of D parameters are drawn at once; 1e7 is about 25 GB
MAX_SAMPLES = 10**7
# the default: a power of two, where the Sobol sequence is balanced, near the paper's 10,000
SAMPLES = 2**13


# --------------------------------------------------------------------------------------
# The design


def problem(base: S.SignalingParams | None = None, names=PARAMETERS, low: float = LOW, high: float = HIGH) -> dict:
    """SALib's problem: each parameter uniform on [low, high] x its baseline value."""
    base = S.SignalingParams() if base is None else base
    return {
        "num_vars": len(names),
        "names": list(names),
        "bounds": [[low * float(getattr(base, n)), high * float(getattr(base, n))] for n in names],
    }


def gain_problem(base: S.SignalingParams | None = None, low: float = LOW, high: float = HIGH) -> dict:
    """SALib's problem of the CSA gain: ``GAIN_PARAMETERS`` each uniform on [low, high] x its
    baseline (the Hill exponent's baseline is ``HILL_N``)."""
    base = S.SignalingParams() if base is None else base
    value = {n: HILL_N if n == "hill_n" else float(getattr(base, n)) for n in GAIN_PARAMETERS}
    return {"num_vars": len(GAIN_PARAMETERS), "names": list(GAIN_PARAMETERS),
            "bounds": [[low * value[n], high * value[n]] for n in GAIN_PARAMETERS]}


def design(function: str, names=None, bounds=None, low: float = LOW, high: float = HIGH) -> dict:
    """SALib's problem of ``function``: the parameters ``names`` (the function's own set by
    default), each on its ``bounds`` (absolute) or on [low, high] x its baseline. InputError
    for an unknown parameter or a bound that is not 0 < lower < upper."""
    if function == "ishigami":
        if names is not None or bounds is not None:
            raise InputError("the Ishigami function has its own three parameters", field="names")
        return ishigami_problem()
    if not (math.isfinite(low) and math.isfinite(high) and 0 < low < high):
        raise InputError(f"expected 0 < LOW < HIGH, multiples of the baselines, got {low:g} {high:g}", field="range")
    default = GAIN_PARAMETERS if function == "csa-gain" else PARAMETERS
    names = list(default if names is None else names)
    known = [f.name for f in dataclasses.fields(S.SignalingParams)] + (["hill_n"] if function == "csa-gain" else [])
    unknown = [n for n in names if n not in known]
    if unknown or not names or len(set(names)) != len(names):
        raise InputError(f"expected distinct parameters of {', '.join(known)}; got {', '.join(names) or 'none'}",
                         field="names")
    if bounds is None:
        base = S.SignalingParams()
        value = {n: HILL_N if n == "hill_n" else float(getattr(base, n)) for n in names}
        bounds = [[low * value[n], high * value[n]] for n in names]
    bounds = [list(map(float, b)) for b in bounds]
    if len(bounds) != len(names):
        raise InputError(f"expected one [lower, upper] pair per parameter ({len(names)}), got {len(bounds)}",
                         field="bounds")
    for name, (lo, hi) in zip(names, bounds):
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi):
            raise InputError(f"{name}: expected 0 < lower < upper, got [{lo:g}, {hi:g}]", field="bounds")
    return {"num_vars": len(names), "names": names, "bounds": bounds}


CONFIG_KEYS = ("function", "protocol", "at", "names", "bounds", "num_vars", "samples")


def read_config(path) -> dict:
    """The analysis a TOML file describes (keys `CONFIG_KEYS`; SALib's ``num_vars``, when
    given, must count ``names``): its top level, or a study file's [sobol] table."""
    from hyper.core.params import read_toml

    data, where = read_toml(path), str(path)
    if "sobol" in data:
        data, where = data["sobol"], f"{path}: sobol"
        if not isinstance(data, dict):
            raise InputError(f"{where}: expected a table ([sobol])")
    unknown = sorted(set(data) - set(CONFIG_KEYS))
    if unknown:
        raise InputError(f"{where}: unknown key(s) {', '.join(unknown)}; known: {', '.join(CONFIG_KEYS)}")
    checks = {
        "function": lambda v: v in FUNCTIONS, "protocol": lambda v: isinstance(v, str),
        "at": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
        "names": lambda v: isinstance(v, list) and all(isinstance(n, str) for n in v),
        "bounds": lambda v: isinstance(v, list) and all(
            isinstance(b, list) and len(b) == 2 and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                        for x in b) for b in v),
        "num_vars": lambda v: isinstance(v, int) and not isinstance(v, bool),
        "samples": lambda v: isinstance(v, int) and not isinstance(v, bool) and 2 <= v <= MAX_SAMPLES,
    }
    expected = {"function": f"one of {', '.join(FUNCTIONS)}", "protocol": "a protocol name or file",
                "at": "a number of hours", "names": "an array of parameter names",
                "bounds": "an array of [lower, upper] pairs", "num_vars": "an integer",
                "samples": f"an integer in [2, {MAX_SAMPLES}]"}
    for key, value in data.items():
        if not checks[key](value):
            raise InputError(f"{where}: {key}: expected {expected[key]}, got {value!r}")
    if "num_vars" in data and data["num_vars"] != len(data.get("names", ())):
        raise InputError(f"{where}: num_vars: {data['num_vars']} does not count names ({len(data.get('names', ()))})")
    if "bounds" in data and "names" not in data:
        raise InputError(f"{where}: bounds: give the names they belong to")
    text = data.get("protocol")
    if text is not None and text not in (*protocols.NAMES, "all") and not Path(text).is_absolute():
        data["protocol"] = str(Path(path).parent / data["protocol"])  # a file beside the config
    return data


def ishigami_problem() -> dict:
    return {"num_vars": 3, "names": ["x1", "x2", "x3"], "bounds": [[-math.pi, math.pi]] * 3}


def ishigami_exact(a: float = ISHIGAMI_AB[0], b: float = ISHIGAMI_AB[1]) -> dict[str, np.ndarray]:
    """The analytic indices of f = sin x1 + a sin² x2 + b x3⁴ sin x1 on [-pi, pi]³."""
    pi4 = math.pi**4
    v1 = 0.5 * (1 + b * pi4 / 5) ** 2
    v2 = a**2 / 8
    v13 = b**2 * pi4**2 * (1 / 18 - 1 / 50)
    v = v1 + v2 + v13
    S2 = np.full((3, 3), np.nan)
    S2[0, 1], S2[0, 2], S2[1, 2] = 0.0, v13 / v, 0.0
    return {"S1": np.array([v1, v2, 0.0]) / v, "ST": np.array([v1 + v13, v2, v13]) / v, "S2": S2}


def sample(prob: dict, n: int, seed: int) -> np.ndarray:
    """The Saltelli/Sobol design with second-order terms: n (2D + 2) rows, grouped by base sample.

    SciPy warns when n is not a power of 2 (the Sobol sequence is balanced only then); the
    paper's n = 10,000 is not, so the warning is swallowed here and ``main`` says it once.
    """
    from SALib.sample import sobol as sobol_sample

    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
        raise InputError(f"samples must be an integer >= 2, got {n!r}")
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*balance properties of Sobol.*")
        return sobol_sample.sample(prob, int(n), calc_second_order=True, seed=seed)


# --------------------------------------------------------------------------------------
# Model evaluations


def ishigami(X: np.ndarray, a: float = ISHIGAMI_AB[0], b: float = ISHIGAMI_AB[1]) -> np.ndarray:
    return np.sin(X[:, 0]) + a * np.sin(X[:, 1]) ** 2 + b * X[:, 2] ** 4 * np.sin(X[:, 0])


def sample_params(X: np.ndarray, names=PARAMETERS, base: S.SignalingParams | None = None) -> S.SignalingParams:
    """The baseline parameters with the named fields replaced by the columns of X."""
    base = S.SignalingParams() if base is None else base
    return dataclasses.replace(base, **{name: X[:, k] for k, name in enumerate(names)})


def final_N(X: np.ndarray, *, names=PARAMETERS, protocol: Protocol | None = None, dt: float = 0.05,
            base: S.SignalingParams | None = None, backend: str = "c", at: float | None = None) -> np.ndarray:
    """N at ``at`` h (default: the end) of ``protocol`` (default daily15) for every row of X,
    from the baseline rest state, by RK4 with steps of at most dt. NaN marks a member whose
    trajectory failed (c backend); the numpy backend raises ``SignalingError`` instead."""
    protocol = named("daily15") if protocol is None else protocol
    end = protocol.end if at is None else at
    p = sample_params(np.atleast_2d(X), names, base)
    y0 = S.rest_state(base)
    if backend == "numpy":
        return S.integrate(p, protocol, y0, 0.0, end, dt, backend="numpy")[1][-1, 4]
    if backend != "c":
        raise InputError(f"backend must be 'c' or 'numpy', got {backend!r}")
    return S.integrate(p, protocol, y0, 0.0, end, dt, backend="c", failures="mask")[1][-1, 4]


def csa_gain(X: np.ndarray, *, names=GAIN_PARAMETERS, protocol: Protocol | None = None, dt: float = 0.05,
             geometry: str = GAIN_GEOMETRY, base: S.SignalingParams | None = None,
             backend: str = "c", at: float | None = None) -> np.ndarray:
    """CSA/CSA0 - 1 at ``at`` h (default: the end) of ``protocol`` (default mwf, 1512 h) for every row of X, on
    the fast growth model (`surrogate.grow`, Hill feedback). A column named ``hill_n`` is the
    feedback's exponent; the others replace SignalingParams fields. NaN marks a member whose
    trajectory failed (c backend); the numpy backend raises ``SignalingError`` instead."""
    from hyper.model import surrogate

    protocol = named(GAIN_PROTOCOL) if protocol is None else protocol
    if backend not in ("c", "numpy"):
        raise InputError(f"backend must be 'c' or 'numpy', got {backend!r}")
    X = np.atleast_2d(np.asarray(X, dtype=float))
    names = tuple(names)
    fields = [k for k, n in enumerate(names) if n != "hill_n"]
    hill_n = X[:, names.index("hill_n")] if "hill_n" in names else HILL_N
    p = sample_params(X[:, fields], [names[k] for k in fields], base)
    if p.size is None:  # only the Hill exponent varies: a batch all the same
        p = dataclasses.replace(p, kM=np.full(X.shape[0], float(p.kM)))
    end = protocol.end if at is None else at
    g = surrogate.grow(p, protocol, [end], signaling_dt=dt, factor=surrogate.section_factor(geometry),
                       hill_n=hill_n, backend=backend, failures="mask" if backend == "c" else "raise")
    return g.csa_ratio[-1] - 1.0


# --------------------------------------------------------------------------------------
# Analysis


@dataclass(frozen=True)
class Indices:
    names: tuple[str, ...]
    S1: np.ndarray
    S1_conf: np.ndarray  # half-width of the conf_level interval (bootstrap)
    ST: np.ndarray
    ST_conf: np.ndarray
    S2: np.ndarray  # (D, D), upper triangle; NaN elsewhere
    S2_conf: np.ndarray
    S1_boot: np.ndarray  # (resamples, D): the bootstrap replicates behind S1_conf
    ST_boot: np.ndarray
    base_samples: int  # base samples that entered the estimate
    dropped: int  # base samples left out because one of their rows failed

    def table(self) -> str:
        lines = [f"{'parameter':<10}{'S1':>9}{'±':>9}{'ST':>9}{'±':>9}"]
        for k in np.argsort(-self.ST):
            lines.append(f"{self.names[k]:<10}{self.S1[k]:9.4f}{self.S1_conf[k]:9.4f}{self.ST[k]:9.4f}{self.ST_conf[k]:9.4f}")
        return "\n".join(lines)


def failed_base_samples(Y: np.ndarray, D: int) -> np.ndarray:
    """Which base samples have a non-finite output in their block of 2D + 2 rows."""
    return ~np.isfinite(np.asarray(Y, dtype=float).reshape(-1, 2 * D + 2)).all(axis=1)


def analyze(prob: dict, Y: np.ndarray, *, seed: int, resamples: int = 100, conf_level: float = 0.95,
            on_failure: str = "abort") -> Indices:
    """SALib's Sobol indices (first, total, second order) with bootstrap intervals.

    Non-finite outputs mark failed members: ``on_failure="abort"`` raises ValueError,
    ``"drop"`` leaves out every base sample with a failed row. The bootstrap is seeded
    with seed + 1 (SALib takes a seed of 0 for no seed).
    """
    from SALib.analyze import sobol as sobol_analyze

    D = prob["num_vars"]
    Y = np.asarray(Y, dtype=float)
    if Y.ndim != 1 or Y.size % (2 * D + 2):
        raise ValueError(f"Y must hold n (2D + 2) = n x {2 * D + 2} outputs, got shape {Y.shape}")
    bad = failed_base_samples(Y, D)
    if bad.any():
        if on_failure == "abort":
            raise ValueError(
                f"{int((~np.isfinite(Y)).sum())} of {Y.size} model evaluations failed (in {int(bad.sum())} "
                "base samples); SALib needs every output: rerun with a smaller dt, or drop those base samples"
            )
        if on_failure != "drop":
            raise ValueError(f"on_failure must be 'abort' or 'drop', got {on_failure!r}")
        Y = Y.reshape(-1, 2 * D + 2)[~bad].ravel()
    if Y.size == 0:
        raise ValueError("no base sample is left to analyse")
    with np.errstate(invalid="ignore", divide="ignore"):
        si = sobol_analyze.analyze(prob, Y, calc_second_order=True, num_resamples=resamples,
                                   conf_level=conf_level, keep_resamples=True, seed=seed + 1)
    return Indices(
        names=tuple(prob["names"]),
        S1=np.asarray(si["S1"]), S1_conf=np.asarray(si["S1_conf"]),
        ST=np.asarray(si["ST"]), ST_conf=np.asarray(si["ST_conf"]),
        S2=np.asarray(si["S2"]), S2_conf=np.asarray(si["S2_conf"]),
        S1_boot=np.asarray(si["S1_conf_all"]), ST_boot=np.asarray(si["ST_conf_all"]),
        base_samples=int(Y.size // (2 * D + 2)), dropped=int(bad.sum()),
    )


# --------------------------------------------------------------------------------------
# Figures

COLOURS = {"IGF1": "tab:blue", "AKT": "tab:orange", "FOXO": "tab:red", "mTOR": "tab:green", "balance": "tab:purple",
           "feedback": "tab:brown", "other": "tab:gray"}


def species_of(name: str) -> str:
    return next((s for s, names in SPECIES.items() if name in names), "other")


# label placement in figure_spread, in pixels of the figure as drawn (100 dpi): a
# character of an 8 pt label, the room around a label, its height, a marker's radius
LABEL_CHAR_PX, LABEL_PAD_PX, LABEL_HEIGHT_PX, MARKER_PX = 6.0, 6.0, 13.0, 8.0


def label_offsets(points: np.ndarray, sizes, marker: float) -> list[tuple[float, float]]:
    """Offsets (pixels, from its point to its box's lower left corner) of one label per
    point such that no two label boxes overlap and no box covers a point: each label in
    turn takes the first free place on rings of growing radius around its point."""
    points = np.asarray(points, dtype=float)
    boxes: list[tuple[float, float, float, float]] = []

    def free(x0, y0, w, h) -> bool:
        if any(x0 < b[2] and b[0] < x0 + w and y0 < b[3] and b[1] < y0 + h for b in boxes):
            return False
        return not np.any((points[:, 0] > x0 - marker) & (points[:, 0] < x0 + w + marker)
                          & (points[:, 1] > y0 - marker) & (points[:, 1] < y0 + h + marker))

    out = []
    for (x, y), (w, h) in zip(points, sizes):
        choice = None
        for radius in marker * (1.2 + 0.8 * np.arange(15)):
            for angle in np.deg2rad([30, -30, 150, -150, 90, -90, 0, 180, 60, -60, 120, -120]):
                dx, dy = radius * math.cos(angle), radius * math.sin(angle)
                # the box extends from the point's side away from it
                x0 = x + dx - (w if dx < 0 else 0.0)
                y0 = y + dy - (h if dy < 0 else 0.0)
                if free(x0, y0, w, h):
                    choice = (x0 - x, y0 - y, w, h)
                    break
            if choice is not None:
                break
        if choice is None:  # nowhere free: the first place, overlapping
            choice = (marker, marker, w, h)
        boxes.append((x + choice[0], y + choice[1], x + choice[0] + w, y + choice[1] + h))
        out.append(choice[:2])
    return out


def figure_spread(ind: Indices, output: str = "N(480 h)"):
    """The Fig. 3F analog: for each parameter the bootstrap mean of its index against the bootstrap
    standard deviation, first-order and total side by side. Colour: species; a coupling
    parameter is split between its own species and the one it comes from. Labels are
    placed where they overlap no other label and no point (`label_offsets`)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6))
    boots = []
    for ax, (label, boot) in zip(axes, (("first-order $S_1$", ind.S1_boot), ("total $S_T$", ind.ST_boot))):
        mean, std = boot.mean(axis=0), boot.std(axis=0, ddof=1)
        for k, name in enumerate(ind.names):
            species = species_of(name)
            alt = SOURCE.get(name)
            ax.plot(mean[k], std[k], "o", ms=10, color=COLOURS[species], markeredgecolor="k",
                    fillstyle="left" if alt else "full", markerfacecoloralt=COLOURS[alt] if alt else "none")
        ax.margins(0.12)  # room for the labels of the outer points
        ax.set_xlabel(f"mean of {label} over the bootstrap")
        ax.set_ylabel("standard deviation over the bootstrap")
        ax.grid(alpha=0.3)
        boots.append((ax, mean, std))
    present = {species_of(n) for n in ind.names}
    handles = [plt.Line2D([], [], marker="o", ls="", color=COLOURS[s], markeredgecolor="k", label=s)
               for s in SPECIES if s in present]
    axes[1].legend(handles=handles, loc="best", fontsize=8, title="species (split: coupling)")
    fig.suptitle(f"Sobol indices of {output}, {ind.base_samples} base samples")
    fig.tight_layout()
    fig.canvas.draw()  # the final limits and layout, so that points map to their pixels
    pt = 72.0 / fig.dpi
    for ax, mean, std in boots:
        points = ax.transData.transform(np.column_stack([mean, std]))
        sizes = [(LABEL_CHAR_PX * len(n) + LABEL_PAD_PX, LABEL_HEIGHT_PX) for n in ind.names]
        for k, (dx, dy) in enumerate(label_offsets(points, sizes, MARKER_PX)):
            far = math.hypot(dx, dy) > 3 * MARKER_PX
            ax.annotate(ind.names[k], (mean[k], std[k]), xytext=(dx * pt, dy * pt),
                        textcoords="offset points", fontsize=8, ha="left", va="bottom",
                        arrowprops={"arrowstyle": "-", "lw": 0.5, "color": "0.4"} if far else None)
    return fig


def figure_bars(ind: Indices, output: str = "N(480 h)"):
    """S1 and ST with their confidence intervals, parameters by decreasing ST."""
    plt = pyplot()
    order = np.argsort(-ind.ST)
    x = np.arange(len(order))
    fig, ax = plt.subplots(figsize=(10, 4.2))
    ax.bar(x - 0.2, ind.S1[order], 0.4, yerr=ind.S1_conf[order], capsize=2, label="$S_1$", color="tab:blue")
    ax.bar(x + 0.2, ind.ST[order], 0.4, yerr=ind.ST_conf[order], capsize=2, label="$S_T$", color="tab:orange")
    ax.set_xticks(x, [ind.names[k] for k in order])
    for tick, k in zip(ax.get_xticklabels(), order):
        tick.set_color(COLOURS[species_of(ind.names[k])])
    ax.set_ylabel("Sobol index")
    ax.axhline(0.0, color="k", lw=0.5)
    ax.legend()
    ax.set_title(f"first-order and total Sobol indices of {output} (bars: 95 % bootstrap intervals)")
    fig.tight_layout()
    return fig


# --------------------------------------------------------------------------------------
# The job layer: chunks of rows as farm jobs, written atomically, skipped when done


def digest(X: np.ndarray, settings: dict) -> str:
    """What a chunk's outputs depend on: the sample matrix and every setting."""
    h = hashlib.sha256(np.ascontiguousarray(X, dtype=float).tobytes())
    h.update(json.dumps(settings, sort_keys=True, default=str).encode())
    return h.hexdigest()[:16]


def chunk_jobs(rows: int, chunk: int):
    from hyper.runs.farm import Job

    return [Job(f"rows_{a:09d}_{min(a + chunk, rows):09d}", cost=float(min(a + chunk, rows) - a),
                payload=(a, min(a + chunk, rows))) for a in range(0, rows, chunk)]


def _chunk_ok(path: Path, key: str, start: int, stop: int) -> bool:
    try:
        with np.load(path) as f:
            return (bool(f["complete"]) and str(f["digest"]) == key and int(f["start"]) == start
                    and int(f["stop"]) == stop and f["Y"].shape == (stop - start,))
    except Exception:  # noqa: BLE001 - unreadable in any way (truncated, not a zip, ...) means not done
        return False


def run_chunks(comm, X: np.ndarray, evaluate: Callable[[np.ndarray], np.ndarray], folder: Path, key: str,
               chunk: int, label: str = "sobol", stop: Callable[[], bool] | None = None,
               progress_every: float = PROGRESS_EVERY):
    """Evaluate every row of X in chunks farmed over ``comm``; collective.

    Each chunk is written atomically to ``folder/<key>/<job key>.npz`` with its row range,
    the digest ``key`` and a complete mark; chunks already there are skipped. Once
    ``stop()`` turns true (SIGTERM) the chunks in progress finish and are written, and the
    others are not started: their results are ``{"interrupted": True}``. Returns (Y, farm
    results): Y, all outputs in row order, on rank 0 (None elsewhere, and None on rank 0
    too if a chunk failed or was not computed).
    """
    from hyper.core import io
    from hyper.runs import farm

    where = Path(folder) / key
    jobs = chunk_jobs(X.shape[0], chunk)

    def path(job):
        return where / f"{job.key}.npz"

    def is_done(job):
        return _chunk_ok(path(job), key, *job.payload)

    def work(subcomm, job):
        if subcomm.allreduce(bool(stop is not None and stop()), op=MPI.LOR):
            return {"interrupted": True}
        first, last = job.payload
        Y = np.asarray(evaluate(X[first:last]), dtype=float)
        if Y.shape != (last - first,):
            raise ValueError(f"the evaluator returned shape {Y.shape} for {last - first} rows")
        with io.atomic_path(path(job)) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, Y=Y, start=first, stop=last, digest=key, complete=True)
        return {"failed": int((~np.isfinite(Y)).sum())}

    results = farm.run(comm, jobs, work, is_done=is_done, label=label, progress_every=progress_every)
    Y = None
    if comm.rank == 0 and all(r.status != "failed" and not interrupted(r) for r in results):
        Y = np.empty(X.shape[0])
        for job in jobs:
            with np.load(path(job)) as f:
                Y[job.payload[0]:job.payload[1]] = f["Y"]
    return Y, results


def interrupted(result) -> bool:
    """A chunk that a SIGTERM kept from starting."""
    return result.status == "done" and bool(result.result) and bool(result.result.get("interrupted"))


def remove_stale(folder: Path, key: str) -> list[str]:
    """Remove the chunk folders of other runs (other digests) under ``folder``; their names."""
    stale = sorted(p.name for p in Path(folder).glob("*") if p.is_dir() and p.name != key)
    for name in stale:
        shutil.rmtree(Path(folder) / name, ignore_errors=True)
    return stale


# --------------------------------------------------------------------------------------
# The job

# the units of sobol.h5's datasets: the indices are fractions of the output's variance
INDEX_UNITS = {"parameters": "name", "X": "the parameters' own (see the bounds group)", "Y": "the output's own",
               "failed_rows": "index", **{k: "1" for k in ("S1", "S1_conf", "ST", "ST_conf", "S2", "S2_conf",
                                                          "S1_bootstrap", "ST_bootstrap")}}


FUNCTIONS = ("signaling", "csa-gain", "ishigami")
SECTION_GEOMETRIES = ("idealized", "cylinder")
OUTPUT = {"signaling": "N(end)", "csa-gain": "CSA/CSA0 - 1 at the end", "ishigami": "the Ishigami function"}


def parser() -> cli.Parser:
    p = cli.Parser("sobol", description="Sobol sensitivity analysis of N(480 h) under daily15 (MODEL.md §7), or\n"
                   "(--function csa-gain) of the 9-week CSA gain under mwf on the fast growth model,\n"
                   "farmed over MPI ranks (run under mpirun -n K). Writes sobol.h5, indices.csv and two\n"
                   "figures to --output.")
    p.add_argument("--samples", type=cli.integer(2, MAX_SAMPLES),
                   help=f"base samples N (a power of two balances the design); N (2D + 2) evaluations. "
                        f"Default: the --problem file's, else {SAMPLES}")
    p.add_argument("--problem", type=Path, metavar="F.toml",
                   help="the analysis in SALib's problem form (names, bounds) with function, protocol, at, "
                        "samples: a TOML file, or a study file's [sobol] table; options override it")
    p.add_argument("--parameters", nargs="+", metavar="NAME",
                   help="the parameters varied (SignalingParams fields; csa-gain also hill_n); the function's "
                        "own set by default")
    p.add_argument("--range", nargs=2, type=float, metavar=("LOW", "HIGH"), default=(LOW, HIGH),
                   help="each parameter uniform on [LOW, HIGH] x its baseline (unless the file gives bounds)")
    p.add_argument("--at", type=float, metavar="H",
                   help="the output's time (h): N, or the CSA gain, at H hours; the protocol's end by default")
    p.add_argument("--output", type=cli.output(folder=True), default="results/sobol", help="output folder")
    p.add_argument("--signaling-dt", type=float, default=0.05, metavar="H", help="largest RK4 step (h)")
    p.add_argument("--chunk", type=cli.integer(1, MAX_SAMPLES), default=10000, help="rows per job and per chunk file")
    p.add_argument("--seed", type=cli.integer(0, 2**32 - 2), default=1,
                   help="seed of the design; the bootstrap uses seed + 1")
    p.add_argument("--resamples", type=cli.integer(2, 10**5), default=100, help="bootstrap resamples")
    p.add_argument("--protocol", default=None, metavar="NAME|FILE",
                   help=f"a named protocol ({', '.join(protocols.NAMES)}) or a TOML protocol file; the output "
                   f"is N (signaling; default daily15) or the CSA gain (csa-gain; default {GAIN_PROTOCOL}) at its end")
    p.add_argument("--on-failure", choices=("abort", "drop"), default="abort",
                   help="failed members: compute no indices (abort), or drop their base samples")
    p.add_argument("--backend", choices=("c", "numpy"), default="c",
                   help="RK4 backend: compiled (c) or signaling.integrate (numpy); same numbers")
    p.add_argument("--function", choices=FUNCTIONS,
                   help="the model: N(end) of the signaling model, CSA/CSA0 - 1 at the end on the fast "
                   "growth model (17 parameters: the rates, kM, kF, thetaM, thetaF, the Hill exponent), "
                   "or the Ishigami test function; signaling unless the --problem file says")
    p.add_argument("--geometry", choices=tuple(SECTION_GEOMETRIES), default=GAIN_GEOMETRY,
                   help="csa-gain: whose section factor turns N into CSA (surrogate.SECTION_FACTOR)")
    cli.progress_option(p)
    return p


def _settings(args, protocol: Protocol | None, prob: dict) -> dict:
    """Everything a chunk's outputs depend on besides the sample matrix."""
    if args.function == "ishigami":
        return {"function": "ishigami", "a_b": ISHIGAMI_AB}
    return {**_model_settings(args, protocol), "problem": prob, "at": args.at}


def _model_settings(args, protocol: Protocol) -> dict:
    if args.function == "csa-gain":
        from hyper.model import surrogate

        return {"function": "csa-gain", "dt": args.signaling_dt, "protocol": protocol.to_attributes(),
                "baseline": dataclasses.asdict(S.SignalingParams()), "start": "baseline rest state",
                "names": list(GAIN_PARAMETERS), "feedback": "hill", "K": 1.0, "geometry": args.geometry,
                "section_factor": surrogate.section_factor(args.geometry), "model": "surrogate.grow"}
    return {"function": "signaling", "dt": args.signaling_dt, "protocol": protocol.to_attributes(),
            "baseline": dataclasses.asdict(S.SignalingParams()), "start": "baseline rest state"}


def _check(args) -> tuple[Protocol | None, dict]:
    """The protocol and SALib's problem of the options and the --problem file (options win);
    completes ``args`` with the file's function, samples and time."""
    positive_hours(args.signaling_dt, "--signaling-dt", S.SMALLEST_DT)
    config = read_config(args.problem) if args.problem is not None else {}
    source = f"--problem {args.problem}: " if args.problem is not None else ""
    args.function = args.function or config.get("function", "signaling")
    args.samples = args.samples or config.get("samples", SAMPLES)
    names = args.parameters or config.get("names")
    bounds = config.get("bounds") if args.parameters is None else None
    try:
        prob = design(args.function, names, bounds, *args.range)
    except InputError as err:
        from_file = err.field == "bounds" or (err.field == "names" and not args.parameters)
        where = f"{source}{err.field}" if from_file else {"names": "--parameters", "range": "--range"}[err.field]
        raise InputError(f"{where}: {err.reason}") from None
    if args.function == "ishigami":
        if args.at is not None or args.protocol is not None:
            raise InputError("--at and --protocol: the Ishigami function has no time and no protocol")
        return None, prob
    default = GAIN_PROTOCOL if args.function == "csa-gain" else "daily15"
    text = args.protocol or config.get("protocol", default)
    found = protocols.from_option(text)
    args.protocol_text = str(Path(text).resolve()) if text not in protocols.NAMES else text
    if len(found) > 1:
        raise InputError(f"--protocol {text}: the analysis takes one protocol")
    args.at = args.at if args.at is not None else config.get("at")
    if args.at is not None:
        positive_hours(args.at, "--at")
        if args.at > found[0].end:
            raise InputError(f"--at: {args.at:g} h is after the end of {found[0].name} ({found[0].end:g} h)")
    return found[0], prob


def run(comm, args) -> int:
    protocol, prob = _check(args)
    # a second analysis writing the same folder would take the first one's chunks for stale
    with locks.hold(comm, [args.output]):
        return analyse(comm, args, protocol, prob)


def analyse(comm, args, protocol, prob) -> int:
    from hyper.core import io
    from hyper.runs.farm import summary_line

    start = time.perf_counter()
    # io.versions() imports dolfinx, whose PETSc initialization is collective over COMM_WORLD:
    # done by rank 0 alone (when it writes the results) it would meet the other ranks' next
    # collective call and hang. All ranks import it here, together.
    io.versions()
    D = prob["num_vars"]
    # before sampling: SALib's sampler marks the problem dict it is given (rank 0's only)
    settings = _settings(args, protocol, prob)
    X = sample(dict(prob), args.samples, args.seed) if comm.rank == 0 else np.empty((args.samples * (2 * D + 2), D))
    _idle_barrier(comm)
    comm.Bcast(X, root=0)
    key = digest(X, settings)
    if args.function == "ishigami":
        evaluate = ishigami
    else:
        if args.backend == "c":
            # rank 0 builds the kernel; the other ranks then load it from the cache
            error = comm.bcast(S.c_backend_error() if comm.rank == 0 else None, root=0)
            if error is not None:
                log.error(comm, f"{error}; use --backend numpy")
                return cli.EXIT_SOME_FAILED
            S.c_backend_error()
        if args.function == "csa-gain":
            evaluate = functools.partial(csa_gain, names=prob["names"], protocol=protocol, dt=args.signaling_dt,
                                         geometry=args.geometry, backend=args.backend, at=args.at)
        else:
            evaluate = functools.partial(final_N, names=prob["names"], protocol=protocol, dt=args.signaling_dt,
                                         backend=args.backend, at=args.at)
    chunks = args.output / "chunks"
    if comm.rank == 0:
        stale = remove_stale(chunks, key)
        if stale:
            info(comm, f"removed chunks of other settings: {', '.join(stale)}")
        if args.samples & (args.samples - 1):
            info(comm, f"note: {args.samples} base samples is not a power of 2; "
                       "the Sobol sequence is balanced only then")
    comm.barrier()
    info(comm, f"sobol: {args.function}, {D} parameters, N = {args.samples}, {X.shape[0]} evaluations in chunks of "
               f"{args.chunk} on {comm.size} rank(s), dt = {args.signaling_dt} h, backend {args.backend}, "
               f"digest {key}")
    t_eval, c_eval = time.perf_counter(), time.process_time()
    from hyper.runs.driver import StopOnTerm

    with StopOnTerm() as stop:
        Y, results = run_chunks(comm, X, evaluate, chunks, key, args.chunk, label="sobol", stop=stop,
                                progress_every=args.progress_every)
    if comm.allreduce(stop(), op=MPI.LOR):
        left = sum(interrupted(r) for r in results)
        info(comm, f"stopped by SIGTERM: {left} chunk(s) not computed, the others saved in {chunks}; "
                   f"run the same command again to continue; exit status {cli.EXIT_TERMINATED}")
        _idle_barrier(comm)
        return cli.EXIT_TERMINATED
    eval_wall = time.perf_counter() - t_eval
    # CPU time of all ranks: on a shared machine, cpu / (wall x ranks) is the share of their
    # cores the ranks actually got
    eval_cpu = comm.reduce(time.process_time() - c_eval, root=0)
    info(comm, summary_line(results))
    code = (_finish(args, prob, X, Y, results, protocol, key, (eval_wall, eval_cpu), start, comm.size)
            if comm.rank == 0 else 0)
    _idle_barrier(comm)
    return int(comm.bcast(code, root=0))


def _idle_barrier(comm) -> None:
    """A barrier at which waiting ranks sleep: MPICH's blocking calls spin, and a spinning rank
    would take a core from rank 0 while it samples or analyses alone."""
    request = comm.Ibarrier()
    while not request.Test():
        time.sleep(0.02)


def _finish(args, prob, X, Y, results, protocol, key, timing, start, ranks) -> int:
    """Rank 0: analysis, HDF5, CSV, figures, summary. Returns the exit code."""
    from hyper.core import io
    from hyper.runs import plot

    if Y is None:
        log.error(None, "some chunks failed (see above); rerun the same command to compute only those")
        return cli.EXIT_SOME_FAILED
    jobs = chunk_jobs(X.shape[0], args.chunk)
    computed = sum(r.status == "done" for r in results)
    evaluated_rows = sum(j.payload[1] - j.payload[0] for j, r in zip(jobs, results) if r.status == "done")
    failed = np.flatnonzero(~np.isfinite(Y))
    eval_wall, eval_cpu = timing
    rate = evaluated_rows / eval_wall if evaluated_rows else float("nan")
    share = eval_cpu / (eval_wall * ranks) if eval_wall > 0 else float("nan")
    info(None, f"evaluations: {X.shape[0]} ({evaluated_rows} computed now in {computed} chunks, "
               f"{eval_wall:.1f} s, {rate:.0f} evaluations/s, the ranks got {100 * share:.0f} % of "
               f"{ranks} core(s)), failed members: {failed.size}")
    if failed.size:
        for row in failed[:5]:
            info(None, "  failed: row " + str(row) + ", "
                       + ", ".join(f"{n}={v:.4g}" for n, v in zip(prob["names"], X[row])))
    try:
        ind = analyze(prob, Y, seed=args.seed, resamples=args.resamples, on_failure=args.on_failure)
    except ValueError as err:
        log.error(None, str(err))
        return cli.EXIT_SOME_FAILED
    if ind.dropped:
        info(None, f"dropped {ind.dropped} base samples with a failed member; indices from {ind.base_samples}")
    wall = time.perf_counter() - start
    from importlib.metadata import version

    attrs = {
        "model": f"Sobol indices of {OUTPUT[args.function]} (MODEL.md §7)",
        "function": args.function, "N": args.samples, "D": prob["num_vars"], "evaluations": X.shape[0],
        "seed": args.seed, "bootstrap_seed": args.seed + 1, "resamples": args.resamples, "conf_level": 0.95,
        "dt": args.signaling_dt, "backend": args.backend, "ranks": ranks, "chunk": args.chunk, "digest": key,
        "failures": int(failed.size), "on_failure": args.on_failure, "dropped_base_samples": ind.dropped,
        "base_samples_used": ind.base_samples, "wall_s": wall, "evaluation_wall_s": eval_wall,
        "evaluation_cpu_s": eval_cpu, "cpu_share": share,
        "evaluations_computed": evaluated_rows, "evaluations_per_s": rate, "version_SALib": version("SALib"),
        "protocol": protocol.name if protocol else "", "start_state": "baseline rest state (MODEL.md §1)",
        "at_h": (protocol.end if args.at is None else args.at) if protocol else float("nan"),
    }
    if args.function == "csa-gain":
        from hyper.model import surrogate

        attrs.update(output="CSA/CSA0 - 1 at the protocol's end (surrogate.grow, Hill feedback, K = 1)",
                     geometry=args.geometry, section_factor=surrogate.section_factor(args.geometry),
                     hill_n_baseline=HILL_N)
    groups = {"bounds": {n: np.asarray(b, dtype=float) for n, b in zip(prob["names"], prob["bounds"])}}
    groups["settings"] = {"function": args.function, "signaling_dt": args.signaling_dt, "backend": args.backend,
                          "samples": args.samples, "seed": args.seed, "chunk": args.chunk,
                          "at_h": attrs["at_h"], "problem": args.problem.name if args.problem else ""}
    if protocol is not None:
        groups["protocol"] = protocol.to_attributes()
        groups["signaling"] = dataclasses.asdict(S.SignalingParams())
    from hyper.runs import provenance

    # the [sobol] table of a study file that reruns this analysis (hyper sobol --problem FILE)
    config = {"function": args.function, "names": list(prob["names"]),
              "bounds": [[float(lo), float(hi)] for lo, hi in prob["bounds"]], "samples": args.samples}
    if protocol is not None:
        config["protocol"] = args.protocol_text
        if args.at is not None:  # else the protocol's end, which the digest records as "not given"
            config["at"] = args.at
    attrs["study"] = "\n".join(provenance.table("sobol", config))
    out = args.output
    io.write_series(out / "sobol.h5", {
        "parameters": np.array(prob["names"], dtype="S"), "X": X, "Y": Y, "failed_rows": failed,
        "S1": ind.S1, "S1_conf": ind.S1_conf, "ST": ind.ST, "ST_conf": ind.ST_conf, "S2": ind.S2,
        "S2_conf": ind.S2_conf, "S1_bootstrap": ind.S1_boot, "ST_bootstrap": ind.ST_boot,
    }, attrs=attrs, groups=groups, units=INDEX_UNITS)
    with io.atomic_path(out / "indices.csv") as tmp:
        with open(tmp, "w") as f:
            f.write("parameter,S1,S1_conf,ST,ST_conf\n")
            for k, name in enumerate(ind.names):
                f.write(f"{name},{ind.S1[k]:.6g},{ind.S1_conf[k]:.6g},{ind.ST[k]:.6g},{ind.ST_conf[k]:.6g}\n")
    at = (protocol.end if args.at is None else args.at) if protocol else None
    label = {"signaling": f"N({at:g} h, {protocol.name})" if protocol else "",
             "csa-gain": f"the CSA gain at {at:g} h ({protocol.name})" if protocol else "",
             "ishigami": "the Ishigami function"}[args.function]
    for name, make in (("spread.png", figure_spread), ("indices.png", figure_bars)):
        plot.save(make(ind, label), out / name, dpi=130)
    info(None, ind.table())
    info(None, f"wall {wall:.1f} s; results: {out / 'sobol.h5'}, {out / 'indices.csv'}, {out / 'spread.png'}, "
               f"{out / 'indices.png'}")
    return 0


main = cli.entry(parser, run)

if __name__ == "__main__":
    sys.exit(main())
