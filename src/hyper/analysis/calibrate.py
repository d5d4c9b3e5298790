"""Fit signaling parameters to measured CSA time courses by bounded least squares.

    hyper calibrate --data data/defreitas.csv --protocol mwf --fit kM
    hyper calibrate --data data/defreitas.csv --protocol mwf --fit kM --exclude-until 3
    hyper calibrate --data data/damas.csv --protocol data/damas.toml \\
                    --data data/seynnes.csv --protocol data/seynnes.toml --fit kM --fit kF=0.005:0.05

Each --data file (CSV: a time column named after its unit, week, day or hour, and a ``csa``
column in any area unit) goes with the --protocol after it in order; the simulated
CSA/CSA0 is compared with csa / csa at time 0. --fit NAME takes a parameter of
`hyper.model.signaling.SignalingParams` with its default bounds (``BOUNDS``), NAME=LOW:HIGH with
finite bounds of one's own. All data sets share the fitted values (a joint fit).

Model. --accuracy (a fraction of the growth, as in `hyper.runs.fidelity`) picks the cheapest
model that meets it: the ODE growth model `hyper.model.surrogate` (no mesh) where its measured
error plus the RK4 step's stays within it, else the full coupled model on --geometry (one
coupled run per evaluation). The optimum is then checked with a full coupled run per data
set (`hyper.runs.driver.execute`) and the difference reported (--no-check skips it).

Intervals: the Jacobian covariance scaled by the residual variance,
s² (JᵀJ)⁻¹ with s² = RSS/(n - p), and Student's t with n - p degrees of freedom. Why: the
model is smooth and close to linear in the rates over their intervals (the CSA gain grows
with kM, bent only by the feedback), every evaluation is an ODE batch, and the Jacobian is
one batch of p + 1 members; a profile likelihood would need a full fit per profile point
for the same answer on a near-linear model. The band of the figure propagates the same
covariance through the curve's own Jacobian. Where a fitted value sits on its bound the
interval is clipped to the bounds and says so.

Writes OUTPUT/calibration.json and OUTPUT/calibration.png (data, fit, 95 % band).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hyper.commands import cli
from hyper.core.log import info
from hyper.core.params import InputError
from hyper.model import protocols, signaling, surrogate
from hyper.model.protocols import Protocol
from hyper.runs import fidelity, locks, measured, runspec

# Default bounds of the parameters one may fit without giving bounds: a decade either side
# of the table value, wide enough for the published 0.01 and 0.025 1/h of kM.
BOUNDS = {"kM": (1e-3, 0.1), "kF": (1.9e-3, 0.19)}
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


def dataset(path: str | Path, protocol: Protocol, exclude_until: float = 0.0) -> Dataset:
    """The data of ``path`` under ``protocol``, without the points in (0, exclude_until] weeks."""
    measured_data = measured.read(path)
    t, ratio = measured_data.t, measured_data.csa_ratio
    keep = t > exclude_until * protocols.WEEK
    if keep.sum() < 1:
        raise InputError(f"{path}: no points left after {exclude_until:g} weeks")
    if t[-1] > protocol.end:
        raise InputError(f"{path}: data up to {t[-1]:g} h, beyond the end of protocol {protocol.name} "
                         f"({protocol.end:g} h)")
    return Dataset(Path(path).stem, t[keep], ratio[keep], protocol)


def fit_option(text: str) -> tuple[str, tuple[float, float]]:
    """NAME or NAME=LOW:HIGH of --fit: a SignalingParams field with finite bounds, LOW < HIGH."""
    name, sep, bounds = text.partition("=")
    fields = [f.name for f in dataclasses.fields(signaling.SignalingParams)]
    if name not in fields:
        raise InputError(f"--fit {text}: unknown parameter {name!r}; known: {', '.join(fields)}")
    if not sep:
        if name not in BOUNDS:
            raise InputError(f"--fit {name}: no default bounds (defaults for {', '.join(BOUNDS)}); "
                             f"give them as {name}=LOW:HIGH")
        return name, BOUNDS[name]
    low, colon, high = bounds.partition(":")
    try:
        lo, hi = float(low), float(high)
    except ValueError:
        lo = hi = math.nan
    if not colon or not (math.isfinite(lo) and math.isfinite(hi)):
        raise InputError(f"--fit {text}: expected finite bounds NAME=LOW:HIGH, e.g. {name}=0.001:0.1")
    if not lo < hi:
        raise InputError(f"--fit {text}: need LOW < HIGH")
    return name, (lo, hi)


# ------------------------------------------------------------------------------ models


def surrogate_model(datasets: list[Dataset], names: list[str], base: signaling.SignalingParams, *,
                    signaling_dt: float, factor: float, feedback: str) -> Callable:
    """X (m, p) -> the model's CSA/CSA0 at every data point, (m, points): one ODE batch of m
    members per data set."""

    def evaluate(X: np.ndarray, times: list[np.ndarray] | None = None) -> np.ndarray:
        X = np.atleast_2d(X)
        params = dataclasses.replace(base, **{name: X[:, j].copy() for j, name in enumerate(names)})
        out = []
        for k, d in enumerate(datasets):
            t = d.t if times is None else times[k]
            g = surrogate.grow(params, d.protocol, np.concatenate([[0.0], t]), signaling_dt=signaling_dt,
                               feedback=feedback, factor=factor)
            out.append(g.csa_ratio[1:].T)
        return np.concatenate(out, axis=1)

    return evaluate


def coupled_model(comm, datasets: list[Dataset], names: list[str], base: signaling.SignalingParams, *,
                  geometry: str, settings) -> Callable:
    """X (m, p) -> CSA/CSA0 at every data point by full coupled runs, one per member and data
    set, read at the data times from the run's growth-step ends (linear in between)."""
    from hyper.runs import driver as run

    def evaluate(X: np.ndarray, times: list[np.ndarray] | None = None) -> np.ndarray:
        rows = []
        for x in np.atleast_2d(X):
            params = dataclasses.replace(base, **{name: float(v) for name, v in zip(names, x)})
            row = []
            for k, d in enumerate(datasets):
                model, *_ = run.build(comm, runspec.RunSpec(geometry, d.protocol, params, settings))
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


# ------------------------------------------------------------------------------ command


def parser() -> cli.Parser:
    p = cli.Parser("calibrate", __doc__)
    p.add_argument("--data", action="append", required=True, type=Path, metavar="CSV",
                   help="a CSA time course (repeat for a joint fit)")
    p.add_argument("--protocol", action="append", required=True, metavar="NAME|FILE",
                   help="the protocol of each --data, in order (a name or a .toml file)")
    p.add_argument("--fit", action="append", required=True, metavar="NAME[=LOW:HIGH]",
                   help=f"a parameter to fit (default bounds for {', '.join(BOUNDS)})")
    p.add_argument("--geometry", default="idealized", help="geometry of the coupled model and the check")
    p.add_argument("--accuracy", type=float, default=fidelity.DEFAULT_ACCURACY,
                   help="error allowed of the model, a fraction of the growth (hyper.runs.fidelity)")
    p.add_argument("--feedback", default="hill", help="h(CSA/CSA0): hill, linear or none")
    p.add_argument("--exclude-until", type=float, default=0.0, metavar="WEEK",
                   help="leave out the points in (0, WEEK] weeks (early oedema)")
    p.add_argument("--no-check", action="store_true", help="skip the coupled run at the optimum")
    p.add_argument("--output", type=cli.output(folder=True), default="results/calibration", help="output folder")
    return p


def run(comm, args) -> int:
    from hyper.fem import coupled
    from hyper.runs import driver as driver

    if len(args.data) != len(args.protocol):
        raise InputError(f"{len(args.data)} --data but {len(args.protocol)} --protocol: "
                         "give one protocol per data file")
    fits = dict(fit_option(text) for text in args.fit)
    if len(fits) != len(args.fit):
        raise InputError("--fit: a parameter named twice")
    if not math.isfinite(args.exclude_until) or args.exclude_until < 0:
        raise InputError(f"--exclude-until: expected a number of weeks >= 0, got {args.exclude_until:g}")
    runspec.check_geometry(comm, args.geometry)
    datasets = [dataset(path, protocols.resolve(p), args.exclude_until)
                for path, p in zip(args.data, args.protocol)]
    names = list(fits)
    bounds = np.array([fits[n] for n in names])
    base = signaling.SignalingParams()
    x0 = np.clip([float(getattr(base, n)) for n in names], bounds[:, 0], bounds[:, 1])
    kind, choice, reasons = choose(args.geometry, datasets, args.accuracy)
    settings = coupled.GrowthSettings(growth_dt=choice.growth_dt, signaling_dt=choice.signaling_dt,
                                      feedback=args.feedback)
    for why in reasons:
        info(comm, f"calibrate: {why}")
    if kind == "surrogate":
        evaluate = surrogate_model(datasets, names, base, signaling_dt=choice.signaling_dt,
                                   factor=surrogate.section_factor(args.geometry), feedback=args.feedback)
    else:
        evaluate = coupled_model(comm, datasets, names, base, geometry=args.geometry, settings=settings)
    f = fit(evaluate, datasets, names, bounds, x0)
    for j, name in enumerate(names):
        info(comm, f"calibrate: {name} = {f.x[j]:.5g} [{f.low[j]:.5g}, {f.high[j]:.5g}] ({LEVEL:.0%})")
    info(comm, f"calibrate: RMSE {f.rmse:.3g} of CSA/CSA0, {f.evaluations} evaluations, {f.wall_s:.1f} s")

    checks = {}
    if not args.no_check:
        fitted = dataclasses.replace(base, **{n: float(v) for n, v in zip(names, f.x)})
        model_at = evaluate(f.x)[0]
        offset = 0
        for d in datasets:
            spec = runspec.RunSpec(args.geometry, d.protocol, fitted, settings)
            outputs = runspec.Outputs(args.output / f"check_{d.name}.h5")
            with locks.hold(comm, [outputs.h5]):
                result = driver.execute(comm, spec, outputs, checkpoints=False, progress_every=1e9)
                if comm.rank == 0:
                    outputs.store(result.series, result.meta, runspec.result_groups(spec))
            coupled_csa = np.interp(d.t, result.series["t"], result.series["csa_ratio"])
            fast = model_at[offset:offset + len(d.t)]
            offset += len(d.t)
            diff = np.abs(fast - coupled_csa)
            checks[d.name] = {"result": str(outputs.h5), "coupled_csa_ratio": coupled_csa.tolist(),
                              "model_csa_ratio": fast.tolist(), "max_abs_difference": float(diff.max()),
                              "max_difference_of_growth": float(diff.max() / abs(coupled_csa[-1] - 1.0)),
                              "coupled_wall_s": result.meta["wall_s"]}
            info(comm, f"calibrate: check {d.name}: coupled run at the optimum differs by at most "
                       f"{diff.max():.2g} in CSA/CSA0 ({checks[d.name]['max_difference_of_growth']:.2g} of the growth)")

    curve_t = [np.linspace(0.0, d.protocol.end, CURVE_POINTS)[1:] for d in datasets]
    curve, half = band(evaluate, f, bounds, curve_t) if kind == "surrogate" else (evaluate(f.x, curve_t)[0], None)
    if comm.rank == 0:
        write(args, datasets, f, kind, reasons, choice, checks)
        figure(args.output / "calibration.png", datasets, f, curve_t, curve, half)
    info(comm, f"calibrate: wrote {args.output / 'calibration.json'} and {args.output / 'calibration.png'}")
    return cli.EXIT_OK


def write(args, datasets: list[Dataset], f: Fit, kind: str, reasons: list[str], choice, checks: dict) -> Path:
    from hyper.core import io

    result = {
        "parameters": {name: {"value": float(f.x[j]), "low": float(f.low[j]), "high": float(f.high[j]),
                              "level": LEVEL, "at_bound": name in f.at_bound,
                              "constrained_by_data": name not in f.unseen,
                              "method": "Jacobian covariance s^2 (J^T J)^-1, s^2 = RSS/(n-p), Student t",
                              "bounds": f.bounds[j].tolist()}
                       for j, name in enumerate(f.names)},
        "rmse": f.rmse,
        "points": len(f.residuals),
        "data": {d.name: {"t_h": d.t.tolist(), "csa_ratio": d.csa_ratio.tolist(), "protocol": d.protocol.name}
                 for d in datasets},
        "exclude_until_weeks": args.exclude_until,
        "model": kind, "reasons": reasons, "accuracy": args.accuracy, "geometry": args.geometry,
        "signaling_dt": choice.signaling_dt, "growth_dt": choice.growth_dt, "feedback": args.feedback,
        "evaluations": f.evaluations, "fit_wall_s": f.wall_s, "check": checks, "versions": io.versions(),
    }
    path = args.output / "calibration.json"
    with io.atomic_path(path) as tmp:
        tmp.write_text(json.dumps(result, indent=2) + "\n")
    return path


def figure(path: Path, datasets: list[Dataset], f: Fit, times: list[np.ndarray], curve: np.ndarray, half):
    from hyper.runs import plot

    plt = plot.pyplot()
    fig, ax = plt.subplots(figsize=(6, 4), constrained_layout=True)
    offset = 0
    label = ", ".join(f"{n} = {v:.4g} [{lo:.4g}, {hi:.4g}]" for n, v, lo, hi in zip(f.names, f.x, f.low, f.high))
    for d, t in zip(datasets, times):
        c = curve[offset:offset + len(t)]
        line, = ax.plot(t / protocols.WEEK, 100 * (c - 1), label=f"{d.name} ({d.protocol.name}) fit")
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


main = cli.entry(parser, run, locks=lambda args: [args.output])

if __name__ == "__main__":
    raise SystemExit(main())
