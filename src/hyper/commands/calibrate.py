"""Fit signaling parameters to measured CSA time courses by bounded least squares.

    hyper calibrate --data data/defreitas.csv --protocol mwf --fit kM
    hyper calibrate --data data/defreitas.csv --protocol mwf --fit kM --exclude-until 3
    hyper calibrate --data data/damas.csv --protocol data/damas.toml \\
                    --data data/seynnes.csv --protocol data/seynnes.toml --fit kM --fit kF=0.005:0.05

Each --data file (CSV: a time column named after its unit, week, day or hour, and a ``csa``
column in any area unit) goes with the --protocol after it in order; the simulated
CSA/CSA0 is compared with csa / csa at time 0. --fit NAME takes a parameter of
`hyper.model.signaling.SignalingParams` with its default bounds (``BOUNDS``), NAME=LOW:HIGH with
finite bounds of one's own; ``detraining`` is the time constant τ (h) of the gain's turnover
(`hyper.model.growth.detrained`, grow's --detraining), default bounds 24 h to 1e5 h, the fit
starting at their geometric mean: data that follow a training block with a rest show how fast
the gain decays. All data sets share the fitted values (a joint fit).

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

Bayes (--method bayes; `hyper.analysis.bayes`), on the fast model only:

    hyper calibrate --data data/defreitas.csv --protocol mwf --fit kM --method bayes --no-check
    hyper calibrate --data data/damas.csv --protocol data/damas.toml \
                    --data data/seynnes.csv --protocol data/seynnes.toml --fit kM --method bayes --priors P.toml

Priors (--priors FILE, TOML): a table per fitted parameter and [noise], each with ``kind``
(log-uniform, the default; log-normal; uniform), ``low`` and ``high`` (default: the --fit
bounds; for the noise 1e-4 and 0.1 of CSA/CSA0) and, for a log-normal, ``median`` and
``sigma`` (of ln x), e.g.

    [kM]
    kind = "log-normal"
    median = 0.015
    sigma = 0.5

Without the file every parameter is log-uniform on its bounds and every noise level
log-uniform on [1e-4, 0.1]. Likelihood: each data set (study) has its own Gaussian
measurement noise σ (CSA/CSA0): --noise SIGMA gives it (once for all, or once per --data),
else it is fitted. All data sets share the fitted parameters (a joint fit). Sampler
(--sampler): ``grid``, the exact posterior of one parameter (each fitted σ integrated out;
two ODE batches), or ``emcee`` (--walkers in one ODE batch per step, --steps); ``auto``
takes the grid for one parameter. The least-squares fit runs too, as emcee's start and for
the comparison. Writes OUTPUT/posterior.h5 (the samples, one dataset per quantity; the
data files' SHA-256, the priors and the diagnostics as groups), OUTPUT/calibration.json
(both fits) and OUTPUT/calibration.png (data, posterior median, 95 % credible and
predictive bands). --no-check skips the coupled run at the posterior median. The samples feed
``hyper design --posterior`` and ``hyper predict`` (coupled runs of them on a real muscle).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from hyper.analysis import bayes
from hyper.analysis.calibrate import (
    BOUNDS,
    CURVE_POINTS,
    GROWTH_PARAMETERS,
    LEVEL,
    Dataset,
    Fit,
    band,
    choose,
    coupled_model,
    dataset,
    figure,
    fit,
    split,
    surrogate_model,
)
from hyper.commands import cli
from hyper.core import io
from hyper.core.log import info
from hyper.core.params import InputError
from hyper.fem import coupled
from hyper.model import protocols, signaling, surrogate
from hyper.runs import driver, fidelity, locks, runspec
from hyper.runs.checkpoint import file_digest

METHODS = ("lsq", "bayes")
SAMPLERS = ("auto", "grid", "emcee")


def fit_option(text: str) -> tuple[str, tuple[float, float]]:
    """NAME or NAME=LOW:HIGH of --fit: a SignalingParams field with finite bounds, LOW < HIGH."""
    name, sep, bounds = text.partition("=")
    fields = [f.name for f in dataclasses.fields(signaling.SignalingParams)] + list(GROWTH_PARAMETERS)
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
        example = ":".join(f"{b:g}" for b in BOUNDS.get(name, (0.001, 0.1)))
        raise InputError(f"--fit {text}: expected finite bounds NAME=LOW:HIGH, e.g. {name}={example}")
    if not lo < hi:
        raise InputError(f"--fit {text}: need LOW < HIGH")
    for bound in (lo, hi):  # a bound the model refuses (kM < 0) would stop the fit after it started
        try:
            if name in GROWTH_PARAMETERS:
                coupled.GrowthSettings(**{name: bound})
            else:
                signaling.SignalingParams(**{name: bound})
        except InputError as err:
            raise InputError(f"--fit {text}: {err}") from None
    return name, (lo, hi)


def parser() -> cli.Parser:
    p = cli.Parser("calibrate", __doc__)
    p.add_argument("--data", action="append", required=True, type=Path, metavar="CSV", reads=True,
                   help="a CSA time course (repeat for a joint fit)")
    p.add_argument("--protocol", action="append", required=True, metavar="NAME|FILE", reads=True,
                   help="the protocol of each --data, in order (a name or a .toml file)")
    p.add_argument("--fit", action="append", required=True, metavar="NAME[=LOW:HIGH]",
                   help=f"a parameter to fit (default bounds for {', '.join(BOUNDS)})")
    p.add_argument("--geometry", default="idealized", help="geometry of the coupled model and the check")
    p.add_argument("--accuracy", type=cli.number(), default=fidelity.DEFAULT_ACCURACY,
                   help="error allowed of the model, a fraction of the growth (hyper.runs.fidelity)")
    p.add_argument("--feedback", default="hill", help="h(CSA/CSA0): hill, linear or none")
    p.add_argument("--exclude-until", type=cli.number(), default=0.0, metavar="WEEK",
                   help="leave out the points in (0, WEEK] weeks (early oedema)")
    p.add_argument("--no-check", action="store_true", help="skip the coupled run at the optimum")
    p.add_argument("--method", choices=METHODS, default="lsq",
                   help="lsq: least squares with a linearised interval; bayes: the posterior on the fast model")
    p.add_argument("--priors", type=Path, metavar="TOML", reads=True,
                   help="bayes: the priors (default: log-uniform on the bounds; see above)")
    p.add_argument("--noise", action="append", type=cli.number(above=0), metavar="SIGMA",
                   help="bayes: the measurement noise of CSA/CSA0, once for all data or once per --data "
                        "(default: fitted per data set)")
    p.add_argument("--sampler", choices=SAMPLERS, default="auto", help="bayes: grid (one parameter) or emcee")
    p.add_argument("--walkers", type=cli.integer(2, 10_000), default=32, help="bayes, emcee: walkers")
    p.add_argument("--steps", type=cli.integer(10, 10**6), default=2000, help="bayes, emcee: steps per walker")
    p.add_argument("--seed", type=cli.seed(), default=0, help="bayes: the seed of the sampler and the band")
    p.add_argument("--output", type=cli.output(folder=True), default="results/calibration", help="output folder")
    return p


def run(comm, args) -> int:
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
    points = sum(len(d.t) for d in datasets)
    if points <= len(names):  # here, before any line on stdout: `fit` would find it only after the model choice
        raise InputError(f"{points} data point(s) for {len(names)} parameter(s): need more points than parameters")
    bounds = np.array([fits[n] for n in names])
    base = signaling.SignalingParams()
    x0 = np.clip([math.sqrt(fits[n][0] * fits[n][1]) if n in GROWTH_PARAMETERS else float(getattr(base, n))
                  for n in names], bounds[:, 0], bounds[:, 1])
    problem, sampler = bayes_problem(args, datasets, fits)
    kind, choice, reasons = choose(args.geometry, datasets, args.accuracy)
    if problem is not None and kind != "surrogate":  # here, before any line on stdout
        raise InputError(f"--method bayes samples the ODE growth model only, and here {reasons[0]}; "
                         "loosen --accuracy or take --geometry idealized or cylinder")
    settings = coupled.GrowthSettings(growth_dt=choice.growth_dt, signaling_dt=choice.signaling_dt,
                                      feedback=args.feedback)
    for why in reasons:
        info(comm, f"calibrate: {why}")
    if kind == "surrogate":
        evaluate = surrogate_model(datasets, names, base, signaling_dt=choice.signaling_dt,
                                   factor=surrogate.section_factor(args.geometry), feedback=args.feedback,
                                   growth_dt=choice.growth_dt)
    else:
        evaluate = coupled_model(comm, datasets, names, base, geometry=args.geometry, settings=settings)
    f = fit(evaluate, datasets, names, bounds, x0)
    for j, name in enumerate(names):
        info(comm, f"calibrate: {name} = {f.x[j]:.5g} [{f.low[j]:.5g}, {f.high[j]:.5g}] ({LEVEL:.0%})")
    info(comm, f"calibrate: RMSE {f.rmse:.3g} of CSA/CSA0, {f.evaluations} evaluations, {f.wall_s:.1f} s")
    post = None
    if problem is not None:
        post = posterior(problem, sampler, evaluate, datasets, f, args)
        for line in bayes.describe(post):
            info(comm, f"calibrate: {line}")
        info(comm, f"calibrate: {post.method}: {post.evaluations} model evaluations, {post.wall_s:.1f} s")
    at = f.x if post is None else post.median[:len(names)]  # where the coupled check runs

    checks = {}
    if not args.no_check:
        rates, tau = split(names, at)
        fitted = dataclasses.replace(base, **{n: float(v) for n, v in rates.items()})
        at_settings = settings if tau is None else dataclasses.replace(settings, detraining=float(tau))
        model_at = evaluate(at)[0]
        offset = 0
        for d in datasets:
            spec = runspec.RunSpec(args.geometry, d.protocol, fitted, at_settings)
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

    if post is not None:
        curve_t = [np.linspace(0.0, d.protocol.end, CURVE_POINTS)[1:] for d in datasets]
        bands = bayes.predictive(problem, evaluate, post, curve_t, seed=args.seed)
        if comm.rank == 0:
            write_bayes(args, datasets, f, post, problem, kind, reasons, choice, checks)
            bayes.figure(args.output / "calibration.png", datasets, post, curve_t, bands,
                         title=f"{args.geometry} (ODE growth model), " + ", ".join(d.protocol.name for d in datasets))
        info(comm, f"calibrate: wrote {args.output / 'posterior.h5'}, {args.output / 'calibration.json'} and "
                   f"{args.output / 'calibration.png'}")
        return cli.EXIT_OK
    curve_t = [np.linspace(0.0, d.protocol.end, CURVE_POINTS)[1:] for d in datasets]
    curve, half = band(evaluate, f, bounds, curve_t) if kind == "surrogate" else (evaluate(f.x, curve_t)[0], None)
    if comm.rank == 0:
        write(args, datasets, f, kind, reasons, choice, checks)
        figure(args.output / "calibration.png", datasets, f, curve_t, curve, half)
    info(comm, f"calibrate: wrote {args.output / 'calibration.json'} and {args.output / 'calibration.png'}")
    return cli.EXIT_OK


def write(args, datasets: list[Dataset], f: Fit, kind: str, reasons: list[str], choice, checks: dict) -> Path:
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
    return io.write_json(path, result)


def bayes_problem(args, datasets: list[Dataset], fits: dict) -> tuple[bayes.Problem | None, str]:
    """The posterior to sample and the sampler, checked before any work (None for --method lsq)."""
    if args.method != "bayes":
        for option in ("priors", "noise"):
            if getattr(args, option) is not None:
                raise InputError(f"--{option}: only with --method bayes")
        return None, ""
    priors, noise_prior = bayes.read_priors(args.priors, fits)
    noise = [None] * len(datasets) if args.noise is None else list(args.noise)
    if len(noise) == 1:
        noise *= len(datasets)
    if len(noise) != len(datasets):
        raise InputError(f"{len(args.noise)} --noise for {len(datasets)} --data: give one for all or one per data file")
    names = [d.name for d in datasets]
    if len(set(names)) != len(names):  # each study's noise is named after its file
        raise InputError(f"--data: two data files named {sorted(n for n in names if names.count(n) > 1)[0]}.csv; "
                         "each data set needs a name of its own")
    sampler = args.sampler if args.sampler != "auto" else "grid" if len(fits) == 1 else "emcee"
    if sampler == "grid" and len(fits) != 1:
        raise InputError(f"--sampler grid: the grid posterior is for one parameter, got {len(fits)}; take emcee")
    problem = bayes.Problem(tuple(fits), tuple(priors[n] for n in fits), tuple(names),
                            tuple(len(d.t) for d in datasets), np.concatenate([d.csa_ratio for d in datasets]),
                            tuple(noise), noise_prior)
    if sampler == "emcee":
        bayes.check_walkers(args.walkers, len(problem.columns))
    return problem, sampler


def posterior(problem: bayes.Problem, sampler: str, evaluate, datasets: list[Dataset], f: Fit,
              args) -> bayes.Posterior:
    if sampler == "grid":
        return bayes.grid(problem, evaluate, seed=args.seed)
    # emcee starts at the least-squares optimum, each fitted noise at its study's RMS residual
    residuals = problem.split(f.residuals[None, :])
    start = list(f.x) + [max(float(np.sqrt(np.mean(residuals[s] ** 2))), problem.noise_prior.low)
                         for s in problem.fitted_noise]
    return bayes.sample(problem, evaluate, np.array(start), walkers=args.walkers, steps=args.steps, seed=args.seed)


def write_bayes(args, datasets: list[Dataset], f: Fit, post: bayes.Posterior, problem: bayes.Problem, kind: str,
                reasons: list[str], choice, checks: dict) -> Path:
    """OUTPUT/posterior.h5 (the samples, with the data's SHA-256) and OUTPUT/calibration.json."""
    digests = {d.name: file_digest(d.path) for d in datasets}
    priors = {p.name: p.attributes() for p in problem.all_priors}
    groups = {f"data_{d.name}": {"file": str(d.path), "file_sha256": digests[d.name], "protocol": d.protocol.name,
                                 "time_h": d.t, "csa_ratio": d.csa_ratio,
                                 "noise": "fitted" if sigma is None else sigma}
              for d, sigma in zip(datasets, problem.noise)}
    groups.update({f"prior_{name}": attrs for name, attrs in priors.items()})
    groups["diagnostics"] = post.diagnostics
    groups["summary"] = {"columns": ",".join(post.columns), "median": post.median, "low": post.low,
                         "high": post.high, "level": bayes.LEVEL}
    units = {c: ("1 (CSA/CSA0)" if c.startswith("sigma_") else io.unit(c)) for c in post.columns}
    io.write_series(args.output / "posterior.h5", {c: post.samples[:, j] for j, c in enumerate(post.columns)},
                    attrs={"method": "bayes", "sampler": post.method, "model": kind, "geometry": args.geometry,
                           "feedback": args.feedback, "signaling_dt": choice.signaling_dt, "seed": args.seed,
                           "wall_s": post.wall_s, "evaluations": post.evaluations},
                    groups=groups, units=units)
    summary = {c: {"median": float(m), "low": float(lo), "high": float(hi), "level": bayes.LEVEL, "prior": priors[c]}
               for c, m, lo, hi in zip(post.columns, post.median, post.low, post.high)}
    result = {
        "method": "bayes", "sampler": post.method, "posterior": summary, "diagnostics": post.diagnostics,
        "noise_given": {d.name: sigma for d, sigma in zip(datasets, problem.noise) if sigma is not None},
        "least_squares": {name: {"value": float(f.x[j]), "low": float(f.low[j]), "high": float(f.high[j]),
                                 "at_bound": name in f.at_bound} for j, name in enumerate(f.names)},
        "rmse": f.rmse, "points": len(f.residuals),
        "data": {d.name: {"file": str(d.path), "sha256": digests[d.name], "t_h": d.t.tolist(),
                          "csa_ratio": d.csa_ratio.tolist(), "protocol": d.protocol.name} for d in datasets},
        "exclude_until_weeks": args.exclude_until, "samples": str(args.output / "posterior.h5"),
        "model": kind, "reasons": reasons, "accuracy": args.accuracy, "geometry": args.geometry,
        "signaling_dt": choice.signaling_dt, "feedback": args.feedback, "seed": args.seed,
        "evaluations": post.evaluations, "posterior_wall_s": post.wall_s, "check": checks, "versions": io.versions(),
    }
    return io.write_json(args.output / "calibration.json", result)


main = cli.entry(parser, run, locks=lambda args: [args.output])
