"""Fit signaling parameters to measured CSA time courses by bounded least squares.

The data sets (`dataset`: a CSA time course under its protocol), the models of CSA/CSA0 at
the data points (`surrogate_model`, the ODE growth model `hyper.model.surrogate`, no mesh;
`coupled_model`, one full coupled run per evaluation), the cheapest model meeting an
accuracy (`choose`, as in `hyper.runs.fidelity`), the fit (`fit`) with its intervals, the
band of a fitted curve (`band`) and the figure (`figure`). The job, with the CLI and the
check of the optimum by coupled runs, is `hyper.commands.calibrate` (``hyper calibrate``).

Intervals: the Jacobian covariance s² (JᵀJ)⁻¹, s² = RSS/(n - p), with Student's t on
n - p degrees of freedom, clipped to the bounds where a value sits on one; `hyper calibrate
--help` says why a linearised interval suffices for this near-linear model.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hyper.core.params import InputError
from hyper.model import protocols, signaling, surrogate
from hyper.model.protocols import Protocol
from hyper.runs import driver, fidelity, measured, plot, runspec

# Default bounds of the parameters one may fit without giving bounds: a decade either side
# of the table value, wide enough for the published 0.01 and 0.025 1/h of kM; for the
# detraining time constant τ (h) a day to about eleven years.
BOUNDS = {"kM": (1e-3, 0.1), "kF": (1.9e-3, 0.19), "detraining": (24.0, 1e5)}
# Fittable parameters that are not signaling rates: the gain's turnover time constant τ (h,
# `hyper.model.growth.detrained`, --detraining), a growth setting of every run. It has no
# table value, so a fit starts at the geometric mean of its bounds.
GROWTH_PARAMETERS = ("detraining",)
LEVEL = 0.95
# Forward-difference step of the Jacobian, relative to the value: the RK4 solution is smooth
# in the rates, so the truncation error (~1e-6) dominates the round-off (~1e-10).
RELATIVE_STEP = 1e-6
CURVE_POINTS = 200


@dataclass(frozen=True)
class Dataset:
    name: str
    t: np.ndarray  # h, the measurement times after time 0
    csa_ratio: np.ndarray  # measured CSA / CSA at time 0, at t
    protocol: Protocol
    path: Path | None = None  # the data file, where the data came from one (its SHA-256 goes in the results)


def dataset(path: str | Path, protocol: Protocol, exclude_until: float = 0.0) -> Dataset:
    """The data of ``path`` under ``protocol``, without the points in (0, exclude_until] weeks."""
    measured_data = measured.read(path)
    if measured_data.section is not None:  # no silent fallback to the mid-belly CSA
        raise InputError(f"{path}: measured at section {measured_data.section:g} of the length; calibration "
                         f"fits the mid-belly CSA (its models have no regional sections)")
    t, ratio = measured_data.t, measured_data.csa_ratio
    keep = t > exclude_until * protocols.WEEK
    if keep.sum() < 1:
        raise InputError(f"{path}: no points left after {exclude_until:g} weeks")
    if t[-1] > protocol.end:
        raise InputError(f"{path}: data up to {t[-1]:g} h, beyond the end of protocol {protocol.name} "
                         f"({protocol.end:g} h)")
    return Dataset(Path(path).stem, t[keep], ratio[keep], protocol, Path(path))



# ------------------------------------------------------------------------------ models


def split(names: list[str], x) -> tuple[dict, float | None]:
    """The signaling rates of ``x`` (values in the order of ``names``) by name, and the
    detraining τ (h) among them (None where it is not fitted)."""
    values = dict(zip(names, x))
    return {n: v for n, v in values.items() if n not in GROWTH_PARAMETERS}, values.get("detraining")


def surrogate_model(datasets: list[Dataset], names: list[str], base: signaling.SignalingParams, *,
                    signaling_dt: float, factor: float, feedback: str, growth_dt: float = 168.0) -> Callable:
    """X (m, p) -> the model's CSA/CSA0 at every data point, (m, points): one ODE batch of m
    members per data set, the detraining τ among ``names`` one per member too (its turnover
    applied per growth step of at most ``growth_dt``, as the coupled model does)."""

    def evaluate(X: np.ndarray, times: list[np.ndarray] | None = None) -> np.ndarray:
        X = np.atleast_2d(X)
        rates, tau = split(names, X.T)
        if not rates:  # τ alone: the members are a batch by their τ, the rates the same in each
            rates = {"kM": np.full(len(X), float(base.kM))}
        params = dataclasses.replace(base, **{n: np.array(v, dtype=float) for n, v in rates.items()})
        out = []
        for k, d in enumerate(datasets):
            t = d.t if times is None else times[k]
            g = surrogate.grow(params, d.protocol, np.concatenate([[0.0], t]), signaling_dt=signaling_dt,
                               feedback=feedback, factor=factor, detraining=tau, growth_dt=growth_dt)
            out.append(g.csa_ratio[1:].T)
        return np.concatenate(out, axis=1)

    return evaluate


def coupled_model(comm, datasets: list[Dataset], names: list[str], base: signaling.SignalingParams, *,
                  geometry: str, settings) -> Callable:
    """X (m, p) -> CSA/CSA0 at every data point by full coupled runs, one per member and data
    set, read at the data times from the run's growth-step ends (linear in between)."""
    def evaluate(X: np.ndarray, times: list[np.ndarray] | None = None) -> np.ndarray:
        rows = []
        for x in np.atleast_2d(X):
            rates, tau = split(names, x)
            params = dataclasses.replace(base, **{name: float(v) for name, v in rates.items()})
            run = settings if tau is None else dataclasses.replace(settings, detraining=float(tau))
            row = []
            for k, d in enumerate(datasets):
                model, *_ = driver.build(comm, runspec.RunSpec(geometry, d.protocol, params, run))
                reports = list(model.run())
                t = np.array([r.t for r in reports])
                csa = np.array([r.csa_ratio for r in reports])
                row.append(np.interp(d.t if times is None else times[k], t, csa))
            rows.append(np.concatenate(row))
        return np.array(rows)

    return evaluate


def jacobian(evaluate: Callable, x: np.ndarray, bounds: np.ndarray, times=None) -> tuple[np.ndarray, np.ndarray]:
    """(model at x, its Jacobian) by forward differences, all p + 1 points in one batch;
    a step that would leave the bounds is taken backwards."""
    h = RELATIVE_STEP * np.maximum(np.abs(x), 1e-12)
    h = np.where(x + h > bounds[:, 1], -h, h)
    X = np.vstack([x, x + np.diag(h)])
    Y = evaluate(X, times)
    return Y[0], ((Y[1:] - Y[0]) / h[:, None]).T


@dataclass
class Fit:
    names: list[str]
    bounds: np.ndarray  # (p, 2)
    x: np.ndarray
    low: np.ndarray
    high: np.ndarray
    covariance: np.ndarray
    rmse: float
    residuals: np.ndarray
    at_bound: list[str]
    unseen: list[str]  # parameters the data do not constrain: their interval is their bounds
    evaluations: int
    wall_s: float


def fit(evaluate: Callable, datasets: list[Dataset], names: list[str], bounds: np.ndarray, x0: np.ndarray,
        level: float = LEVEL) -> Fit:
    """Bounded least squares (SciPy's trust-region reflective) of the model to the data, and
    the Jacobian-covariance intervals at ``level``."""
    from scipy import optimize, stats

    y = np.concatenate([d.csa_ratio for d in datasets])
    n, p = len(y), len(names)
    if n <= p:
        raise InputError(f"{n} data point(s) for {p} parameter(s): need more points than parameters")
    cache = {}

    def model(x):
        key = x.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = jacobian(evaluate, x, bounds)
        return cache[key]

    start = time.perf_counter()
    result = optimize.least_squares(lambda x: model(x)[0] - y, x0, jac=lambda x: model(x)[1],
                                    bounds=(bounds[:, 0], bounds[:, 1]), method="trf", x_scale="jac")
    r, J = model(result.x)[0] - y, model(result.x)[1]
    rss = float(r @ r)
    # A parameter the data do not see (a zero Jacobian column, e.g. kF while FOXO stays below
    # its threshold) has no finite interval: infinite variance, not pinv's zero.
    seen = np.linalg.norm(J, axis=0) > 1e-12 * max(np.linalg.norm(J), 1e-300)
    covariance = np.full((p, p), np.nan)
    covariance[np.ix_(seen, seen)] = rss / (n - p) * np.linalg.pinv(J[:, seen].T @ J[:, seen])
    covariance[~seen, ~seen] = np.inf
    half = stats.t.ppf(0.5 + level / 2, n - p) * np.sqrt(np.diag(covariance))
    unseen = [name for name, ok in zip(names, seen) if not ok]
    low = np.maximum(result.x - half, bounds[:, 0])
    high = np.minimum(result.x + half, bounds[:, 1])
    at_bound = [name for name, v, b in zip(names, result.x, bounds)
                if np.isclose(v, b[0], rtol=1e-6) or np.isclose(v, b[1], rtol=1e-6)]
    return Fit(list(names), bounds, result.x, low, high, covariance, math.sqrt(rss / n), r, at_bound, unseen,
               int(result.nfev + result.njev), time.perf_counter() - start)


def band(evaluate: Callable, f: Fit, bounds: np.ndarray, times: list[np.ndarray], level: float = LEVEL):
    """(curve, half-width of its ``level`` band) at ``times``: the covariance through the
    curve's Jacobian, J C Jᵀ, with the fit's t quantile."""
    from scipy import stats

    curve, J = jacobian(evaluate, f.x, bounds, times)
    n = len(f.residuals)
    # the curve does not move with an unconstrained parameter (its column is zero): it adds nothing
    C = np.where(np.isfinite(f.covariance), f.covariance, 0.0)
    half = stats.t.ppf(0.5 + level / 2, n - len(f.x)) * np.sqrt(np.einsum("ij,jk,ik->i", J, C, J))
    return curve, half


def choose(geometry: str, datasets: list[Dataset], accuracy: float) -> tuple[str, fidelity.Choice, list[str]]:
    """The cheapest model meeting ``accuracy``: ("surrogate" or "coupled", the steps, why)."""
    scene = fidelity.Scene(geometry, ",".join(sorted({d.protocol.name for d in datasets})), False, "growth")
    try:
        choice = fidelity.choose(scene, accuracy)
    except InputError as err:
        raise InputError(f"--accuracy {accuracy:g}: {err}") from None
    if geometry in surrogate.SECTION_FACTOR:
        predicted = surrogate.SURROGATE_ERROR + fidelity.signaling_error(choice.signaling_dt, "growth")
        if predicted <= accuracy:
            return "surrogate", choice, [
                f"ODE growth model (hyper.model.surrogate, section factor {surrogate.section_factor(geometry):g}): "
                f"measured error {surrogate.SURROGATE_ERROR:g} + RK4 {choice.signaling_dt:g} h "
                f"{fidelity.signaling_error(choice.signaling_dt, 'growth'):.2g} <= accuracy {accuracy:g}"]
        why = f"the ODE growth model's error {predicted:.2g} exceeds accuracy {accuracy:g}"
    else:
        why = f"the ODE growth model is not measured on {geometry}"
    return "coupled", choice, [f"{why}: full coupled model on {geometry}", choice.describe()]


def figure(path: Path, datasets: list[Dataset], f: Fit, times: list[np.ndarray], curve: np.ndarray, half):
    """The data, the fitted curves and (``half``, where given) their band, in % of CSA change."""
    plt = plot.pyplot()
    fig, ax = plt.subplots(figsize=(6, 4), constrained_layout=True)
    offset = 0
    label = ", ".join(f"{n} = {v:.4g} [{lo:.4g}, {hi:.4g}]" for n, v, lo, hi in zip(f.names, f.x, f.low, f.high))
    for d, t in zip(datasets, times):
        c = curve[offset:offset + len(t)]
        name = d.name if d.protocol.name == d.name else f"{d.name} ({d.protocol.name})"
        line, = ax.plot(t / protocols.WEEK, 100 * (c - 1), label=f"{name} fit")
        if half is not None:
            h = half[offset:offset + len(t)]
            ax.fill_between(t / protocols.WEEK, 100 * (c - h - 1), 100 * (c + h - 1), color=line.get_color(),
                            alpha=0.25, lw=0)
        ax.plot(np.concatenate([[0], d.t]) / protocols.WEEK, 100 * (np.concatenate([[1], d.csa_ratio]) - 1), "o",
                color=line.get_color(), label=f"{d.name} data")
        offset += len(t)
    ax.set_xlabel("time (weeks)")
    ax.set_ylabel("CSA change (%)")
    ax.set_title(label + f"  (RMSE {100 * f.rmse:.2g} %)", fontsize=8)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    return plot.save(fig, path)

