"""Bayesian calibration of signaling parameters on the fast model: priors, likelihood, sampler, diagnostics.

The priors (`Prior`, read from a TOML file by `read_priors`), the problem (`Problem`: the
data of every study, the fitted parameters, and each study's measurement noise, given or
fitted), its log posterior over a batch of members (`Problem.log_posterior`), two ways to
sample it (`grid`, exact for one parameter; `sample`, emcee's affine-invariant ensemble for
any number), the posterior predictive band (`predictive`) and the figure (`figure`). The job
is `hyper.commands.calibrate` (``hyper calibrate --method bayes``).

Likelihood. Each study s has its own noise σ_s (CSA/CSA0 units): the measured CSA/CSA0 is
the model's plus independent N(0, σ_s²) errors. Why one σ per study: the studies measure
different muscles with different methods (pQCT, ultrasound, MRI), so their errors differ;
a σ is either given (``--noise``) or fitted with the noise prior.

Coordinates. Every quantity is sampled in z = ln x where its prior is log-uniform or
log-normal (z = x where uniform): kM spans two decades, and in ln kM the posterior is close
to Gaussian, so the grid is even and emcee's stretch move works on one scale.

Grid. With one parameter the posterior is a 1-D density: `grid` evaluates it on an even
grid in z (one ODE batch), refines the grid over the region that holds the mass (a second
batch), and integrates each study's fitted σ out on a σ grid (no model evaluation: σ only
scales the residuals). Quantiles come from the exact cumulative sum, the samples by inverse
transform. It is exact up to the grid (800 points over the mass) and far cheaper than MCMC;
emcee on the same problem agrees with it (tests/test_bayes.py).
"""

from __future__ import annotations

import dataclasses
import math
import textwrap
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hyper.core.params import InputError, as_float, positive_hours, read_toml
from hyper.model import protocols, signaling
from hyper.runs import plot

KINDS = ("log-uniform", "log-normal", "uniform")
# A fitted noise σ (CSA/CSA0) without a prior of one's own: log-uniform (scale-free, the
# Jeffreys prior of a scale, truncated) from 1e-4, below any imaging method's precision, to
# 0.1, a 10 % error, larger than any of the data sets' whole change.
NOISE = "noise"
DEFAULT_NOISE = (1e-4, 0.1)
LEVEL = 0.95
GRID_POINTS = 400  # per stage: a coarse grid over the prior, then a fine one over the mass
NOISE_POINTS = 400
# The fine grid spans the coarse cells holding all but this fraction of the mass (and one
# cell more either side): what is left out is below the grid's own error.
GRID_TAIL = 1e-9
PREDICTIVE_DRAWS = 200
# emcee's rule of thumb: a chain at least 50 integrated autocorrelation times long.
CONVERGED_TAUS = 50


@dataclass(frozen=True)
class Prior:
    """The prior of one quantity: log-uniform or uniform on [low, high], or a log-normal
    (``median``, ``sigma`` the standard deviation of ln x) truncated to [low, high]."""

    name: str
    kind: str
    low: float
    high: float
    median: float = math.nan
    sigma: float = math.nan

    def __post_init__(self):
        where = f"prior {self.name}"
        if self.kind not in KINDS:
            raise InputError(f"{where}: kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if not (math.isfinite(self.low) and math.isfinite(self.high)):
            raise InputError(f"{where}: bounds must be finite, got [{self.low:g}, {self.high:g}]")
        if not self.low < self.high:
            raise InputError(f"{where}: need low < high, got [{self.low:g}, {self.high:g}]")
        if self.kind != "uniform" and self.low <= 0:
            raise InputError(f"{where}: a {self.kind} prior needs low > 0, got {self.low:g}")
        if self.kind == "log-normal":
            if not (math.isfinite(self.median) and self.low < self.median < self.high):
                raise InputError(f"{where}: a log-normal prior needs a median in ({self.low:g}, {self.high:g}), "
                                 f"got {self.median:g}")
            if not (math.isfinite(self.sigma) and self.sigma > 0):
                raise InputError(f"{where}: a log-normal prior needs sigma > 0 (of ln x), got {self.sigma:g}")
        elif not (math.isnan(self.median) and math.isnan(self.sigma)):
            raise InputError(f"{where}: median and sigma belong to a log-normal prior, not a {self.kind} one")

    @property
    def logarithmic(self) -> bool:
        return self.kind != "uniform"

    def to_z(self, x):
        return np.log(x) if self.logarithmic else np.asarray(x, dtype=float)

    def from_z(self, z):
        return np.exp(z) if self.logarithmic else np.asarray(z, dtype=float)

    @property
    def z_bounds(self) -> tuple[float, float]:
        return float(self.to_z(self.low)), float(self.to_z(self.high))

    def logpdf_z(self, z) -> np.ndarray:
        """ln of the density in z (up to a constant), -inf outside the bounds."""
        z = np.asarray(z, dtype=float)
        lo, hi = self.z_bounds
        inside = (z >= lo) & (z <= hi)
        if self.kind == "log-normal":
            value = -0.5 * ((z - math.log(self.median)) / self.sigma) ** 2
        else:
            value = np.zeros_like(z)
        return np.where(inside, value, -np.inf)

    def describe(self) -> str:
        shape = f"median {self.median:g}, sigma {self.sigma:g} (of ln), " if self.kind == "log-normal" else ""
        return f"{self.name}: {self.kind}, {shape}on [{self.low:g}, {self.high:g}]"

    def attributes(self) -> dict:
        return {k: v for k, v in dataclasses.asdict(self).items() if not (isinstance(v, float) and math.isnan(v))}


PRIOR_KEYS = ("kind", "low", "high", "median", "sigma")


def prior_of(name: str, table, bounds: tuple[float, float], where: str) -> Prior:
    """The prior of ``name`` from its TOML table, ``bounds`` where the table gives none."""
    if not isinstance(table, dict):
        raise InputError(f"{where}: [{name}] must be a table (kind, low, high, median, sigma)")
    unknown = sorted(set(table) - set(PRIOR_KEYS))
    if unknown:
        raise InputError(f"{where}: [{name}]: unknown key {unknown[0]!r}; known: {', '.join(PRIOR_KEYS)}")
    kind = table.get("kind", "log-uniform")
    if not isinstance(kind, str):
        raise InputError(f"{where}: [{name}] kind: expected text, one of {', '.join(KINDS)}")
    values = {key: as_float(table[key], f"{where}: [{name}] {key}") for key in PRIOR_KEYS[1:] if key in table}
    return Prior(name, kind, values.get("low", bounds[0]), values.get("high", bounds[1]),
                 values.get("median", math.nan), values.get("sigma", math.nan))


def read_priors(path: str | Path | None, bounds: dict[str, tuple[float, float]]) -> tuple[dict[str, Prior], Prior]:
    """({parameter: prior}, the noise prior) from a TOML file (None: the defaults).

    A table per fitted parameter (``[kM]``) and ``[noise]``, each with ``kind`` (log-uniform,
    the default; log-normal; uniform), ``low`` and ``high`` (default: the parameter's --fit
    bounds, `DEFAULT_NOISE` for the noise) and, for log-normal, ``median`` and ``sigma``
    (of ln x). A parameter left out gets the default prior: log-uniform on its bounds."""
    tables = {} if path is None else read_toml(path)
    where = str(path)
    fields = {f.name for f in dataclasses.fields(signaling.SignalingParams)}
    for name in tables:
        if name != NOISE and name not in bounds:
            known = f"fitted: {', '.join(bounds)}, and {NOISE}"
            raise InputError(f"{where}: unknown parameter {name!r} ({known})" if name not in fields else
                             f"{where}: [{name}] is not fitted (give --fit {name}); {known}")
    priors = {name: prior_of(name, tables.get(name, {}), bounds[name], where) for name in bounds}
    for name, prior in priors.items():
        for bound in (prior.low, prior.high):  # a bound the model refuses (kM < 0) would stop the sampler
            try:
                if name == "detraining":  # the gain's turnover τ (h), a growth setting, not a rate
                    positive_hours(bound, name)
                else:
                    signaling.SignalingParams(**{name: bound})
            except InputError as err:
                raise InputError(f"{where}: [{name}]: {err}") from None
    noise = prior_of(NOISE, tables.get(NOISE, {}), DEFAULT_NOISE, where)
    if noise.low <= 0:
        raise InputError(f"{where}: [{NOISE}]: a noise level needs low > 0, got {noise.low:g}")
    return priors, noise


# ------------------------------------------------------------------------------ the problem


@dataclass(frozen=True)
class Problem:
    """The posterior of ``names`` (with ``priors``) and of each study's noise that is not
    given (``noise[s]`` None: fitted with ``noise_prior``), given the data ``y`` of the
    studies (``studies``, ``sizes`` points each, in order)."""

    names: tuple[str, ...]
    priors: tuple[Prior, ...]
    studies: tuple[str, ...]
    sizes: tuple[int, ...]
    y: np.ndarray
    noise: tuple[float | None, ...]
    noise_prior: Prior

    def __post_init__(self):
        if len(self.names) != len(self.priors) or not len(self.studies) == len(self.sizes) == len(self.noise):
            raise InputError("a prior per parameter and a noise level (or None) per study")
        if sum(self.sizes) != len(self.y):
            raise InputError(f"{len(self.y)} data points, the studies hold {sum(self.sizes)}")
        for s, sigma in zip(self.studies, self.noise):
            if sigma is not None and not (math.isfinite(sigma) and sigma > 0):
                raise InputError(f"noise of {s}: expected a finite number > 0, got {sigma:g}")

    @property
    def fitted_noise(self) -> list[int]:
        return [s for s, sigma in enumerate(self.noise) if sigma is None]

    @property
    def columns(self) -> list[str]:
        """Every sampled quantity: the parameters, then sigma_STUDY of each fitted noise."""
        return list(self.names) + [f"sigma_{self.studies[s]}" for s in self.fitted_noise]

    @property
    def all_priors(self) -> list[Prior]:
        return list(self.priors) + [dataclasses.replace(self.noise_prior, name=f"sigma_{self.studies[s]}")
                                    for s in self.fitted_noise]

    def to_x(self, Z: np.ndarray) -> np.ndarray:
        return np.column_stack([p.from_z(Z[:, j]) for j, p in enumerate(self.all_priors)])

    def to_z(self, X: np.ndarray) -> np.ndarray:
        return np.column_stack([p.to_z(X[:, j]) for j, p in enumerate(self.all_priors)])

    def split(self, values: np.ndarray) -> list[np.ndarray]:
        """(m, points) -> one (m, points of s) block per study."""
        return np.split(values, np.cumsum(self.sizes)[:-1], axis=1)

    def sigmas(self, X: np.ndarray) -> np.ndarray:
        """(m, studies): each member's noise per study, given or its sampled column."""
        out = np.empty((len(X), len(self.studies)))
        column = len(self.names)
        for s, sigma in enumerate(self.noise):
            if sigma is None:
                out[:, s] = X[:, column]
                column += 1
            else:
                out[:, s] = sigma
        return out

    def log_likelihood(self, model: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
        """(m,): the Gaussian log likelihood of the data for model values (m, points)."""
        total = np.zeros(len(model))
        for s, (block, y) in enumerate(zip(self.split(model), self.split(self.y[None, :]))):
            rss = np.sum((block - y) ** 2, axis=1)
            n = self.sizes[s]
            total += -n * np.log(sigmas[:, s]) - rss / (2 * sigmas[:, s] ** 2) - 0.5 * n * math.log(2 * math.pi)
        return total

    def log_posterior(self, Z: np.ndarray, evaluate: Callable) -> np.ndarray:
        """(m,) up to a constant, for members Z (m, columns) in z; -inf outside the priors.
        The model is evaluated once, on the members inside (one batch)."""
        Z = np.atleast_2d(Z)
        lp = np.sum([p.logpdf_z(Z[:, j]) for j, p in enumerate(self.all_priors)], axis=0)
        inside = np.isfinite(lp)
        if inside.any():
            X = self.to_x(Z[inside])
            model = evaluate(X[:, :len(self.names)])
            ll = self.log_likelihood(model, self.sigmas(X))
            lp[inside] += np.where(np.isfinite(ll), ll, -np.inf)
        return lp


# ------------------------------------------------------------------------------ the posterior


@dataclass
class Posterior:
    columns: list[str]
    samples: np.ndarray  # (draws, columns), in the quantities' own units
    median: np.ndarray
    low: np.ndarray  # the LEVEL central credible interval
    high: np.ndarray
    method: str  # "grid" or "emcee"
    diagnostics: dict  # per column where it applies: tau, ess; acceptance; converged; …
    evaluations: int  # model members evaluated
    wall_s: float


def _intervals(samples: np.ndarray, level: float = LEVEL):
    q = np.quantile(samples, [0.5, 0.5 - level / 2, 0.5 + level / 2], axis=0)
    return q[0], q[1], q[2]


def _noise_marginal(problem: Problem, model: np.ndarray, prior: Prior) -> tuple[np.ndarray, list[np.ndarray]]:
    """(G,): ln ∫ L p(σ) dσ over every fitted σ (and L at each given one), and per fitted
    study its (G, NOISE_POINTS) log conditional on the σ grid (for the samples)."""
    lo, hi = prior.z_bounds
    edges = np.linspace(lo, hi, NOISE_POINTS + 1)
    zs = 0.5 * (edges[1:] + edges[:-1])
    log_weight = prior.logpdf_z(zs) + math.log(edges[1] - edges[0])
    log_weight -= _logsumexp(log_weight)
    sigma = prior.from_z(zs)
    total = np.zeros(len(model))
    conditionals = []
    for s, (block, y) in enumerate(zip(problem.split(model), problem.split(problem.y[None, :]))):
        rss = np.sum((block - y) ** 2, axis=1)[:, None]
        n = problem.sizes[s]
        given = problem.noise[s]
        if given is not None:
            total += (-n * math.log(given) - rss[:, 0] / (2 * given ** 2))
            continue
        terms = -n * np.log(sigma)[None, :] - rss / (2 * sigma[None, :] ** 2) + log_weight[None, :]
        marginal = _logsumexp(terms, axis=1)
        total += marginal
        conditionals.append(terms - marginal[:, None])
    return total, conditionals


def _logsumexp(a, axis=None):
    a = np.asarray(a, dtype=float)
    top = np.max(a, axis=axis, keepdims=True)
    top = np.where(np.isfinite(top), top, 0.0)
    out = np.log(np.sum(np.exp(a - top), axis=axis, keepdims=True)) + top
    return out.squeeze(axis) if axis is not None else float(out.squeeze())


def grid(problem: Problem, evaluate: Callable, *, draws: int = 4000, seed: int = 0,
         points: int = GRID_POINTS) -> Posterior:
    """The exact posterior of one parameter (each fitted σ integrated out on a grid), in two
    ODE batches: a grid over the prior, then one over the cells that hold the mass."""
    if len(problem.names) != 1:
        raise InputError(f"the grid posterior is for one parameter, got {len(problem.names)} "
                         f"({', '.join(problem.names)}); sample them with emcee")
    start = time.perf_counter()
    prior = problem.priors[0]
    lo, hi = prior.z_bounds

    def stage(a: float, b: float):
        edges = np.linspace(a, b, points + 1)
        z = 0.5 * (edges[1:] + edges[:-1])
        model = evaluate(prior.from_z(z)[:, None])
        marginal, conditionals = _noise_marginal(problem, model, problem.noise_prior)
        logp = prior.logpdf_z(z) + np.where(np.isfinite(marginal), marginal, -np.inf)
        if not np.isfinite(logp).any():
            raise InputError("the posterior is zero everywhere on the prior's range (the model fails there)")
        weight = np.exp(logp - np.max(logp))
        return edges, z, weight / weight.sum(), conditionals

    edges, z, mass, _ = stage(lo, hi)
    cdf = np.cumsum(mass)
    first = max(int(np.searchsorted(cdf, GRID_TAIL / 2)) - 1, 0)
    last = min(int(np.searchsorted(cdf, 1 - GRID_TAIL / 2)) + 1, points - 1)
    edge_mass = float(mass[0] + mass[-1])
    edges, z, mass, conditionals = stage(edges[first], edges[last + 1])
    # the cumulative distribution at the cells' right edges, the density even within a cell
    cdf = np.concatenate([[0.0], np.cumsum(mass)])
    cdf[-1] = 1.0
    quantile = lambda q: float(prior.from_z(np.interp(q, cdf, edges)))  # noqa: E731
    rng = np.random.default_rng(seed)
    u = rng.random(draws)
    zs = np.interp(u, cdf, edges)
    cells = np.clip(np.searchsorted(edges, zs) - 1, 0, points - 1)
    columns = [prior.from_z(zs)]
    noise_lo, noise_hi = problem.noise_prior.z_bounds
    noise_edges = np.linspace(noise_lo, noise_hi, NOISE_POINTS + 1)
    for conditional in conditionals:  # each fitted σ from its conditional given the cell's parameter
        p = np.exp(conditional[cells])
        c = np.cumsum(p, axis=1)
        k = np.minimum((c < rng.random(draws)[:, None] * c[:, -1:]).sum(axis=1), NOISE_POINTS - 1)
        width = noise_edges[1] - noise_edges[0]
        columns.append(problem.noise_prior.from_z(noise_edges[k] + width * rng.random(draws)))
    samples = np.column_stack(columns)
    median, low, high = _intervals(samples)
    median[0], low[0], high[0] = quantile(0.5), quantile(0.5 - LEVEL / 2), quantile(0.5 + LEVEL / 2)
    diagnostics = {"grid_points": points, "grid_low": float(prior.from_z(edges[0])),
                   "grid_high": float(prior.from_z(edges[-1])), "prior_edge_mass": edge_mass,
                   "ess": [float(draws)] * samples.shape[1], "tau": [1.0] * samples.shape[1],
                   "converged": True}
    return Posterior(problem.columns, samples, median, low, high, "grid", diagnostics, 2 * points,
                     time.perf_counter() - start)


def check_walkers(walkers: int, dim: int) -> None:
    """emcee's stretch move needs at least two walkers per dimension."""
    if walkers < 2 * dim:
        raise InputError(f"--walkers {walkers}: emcee needs at least 2 per sampled quantity ({2 * dim})")


def sample(problem: Problem, evaluate: Callable, x0: np.ndarray, *, walkers: int = 32, steps: int = 2000,
           seed: int = 0) -> Posterior:
    """emcee's ensemble sampler from a small ball around ``x0`` (a point in every column's
    units inside the priors, e.g. the least-squares optimum), all walkers one batch
    (``vectorize``). Diagnostics: the integrated autocorrelation time τ per column, the
    effective sample size walkers (steps - burn-in) / τ, the mean acceptance fraction; the
    burn-in is 2 max τ, the thinning τ_min / 2, and the chain counts as converged where it
    is at least `CONVERGED_TAUS` τ long."""
    import emcee  # the sampler only: the least-squares path never loads it

    dim = len(problem.columns)
    check_walkers(walkers, dim)
    start = time.perf_counter()
    rng = np.random.default_rng(seed)
    bounds = np.array([p.z_bounds for p in problem.all_priors])
    z0 = np.clip(problem.to_z(np.atleast_2d(x0))[0], bounds[:, 0], bounds[:, 1])
    # a ball of 1e-2 in z (1 % of a rate), kept inside the priors
    width = 0.01 * np.minimum(1.0, bounds[:, 1] - bounds[:, 0])
    p0 = np.clip(z0 + width * rng.standard_normal((walkers, dim)), bounds[:, 0] + 1e-12, bounds[:, 1] - 1e-12)
    counted = [0]

    def log_prob(Z):
        counted[0] += len(Z)
        return problem.log_posterior(Z, evaluate)

    sampler = emcee.EnsembleSampler(walkers, dim, log_prob, vectorize=True)
    sampler.random_state = np.random.RandomState(seed).get_state()  # emcee's own moves, seeded
    sampler.run_mcmc(p0, steps, progress=False)
    tau = np.asarray(sampler.get_autocorr_time(tol=0), dtype=float)
    burn = min(int(math.ceil(2 * np.max(tau))), steps // 2)
    thin = max(1, int(np.min(tau) / 2))
    Z = sampler.get_chain(discard=burn, thin=thin, flat=True)
    samples = problem.to_x(Z)
    median, low, high = _intervals(samples)
    ess = walkers * (steps - burn) / tau
    diagnostics = {"tau": tau.tolist(), "ess": ess.tolist(),
                   "acceptance": float(np.mean(sampler.acceptance_fraction)),
                   "walkers": walkers, "steps": steps, "burn_in": burn, "thin": thin,
                   "converged": bool(steps >= CONVERGED_TAUS * np.max(tau))}
    return Posterior(problem.columns, samples, median, low, high, "emcee", diagnostics, counted[0],
                     time.perf_counter() - start)


def describe(post: Posterior) -> list[str]:
    """The posterior and its diagnostics, one line a column and one for the chain."""
    d = post.diagnostics
    lines = [f"{name} = {m:.5g} [{lo:.5g}, {hi:.5g}] ({LEVEL:.0%} credible), ESS {ess:.0f}, tau {tau:.3g}"
             for name, m, lo, hi, ess, tau in zip(post.columns, post.median, post.low, post.high, d["ess"], d["tau"])]
    if post.method == "emcee":
        lines.append(f"emcee: {d['walkers']} walkers x {d['steps']} steps, burn-in {d['burn_in']}, thin {d['thin']}, "
                     f"acceptance {d['acceptance']:.2f}, "
                     + ("converged (>= 50 tau)" if d["converged"] else
                        f"NOT converged: the chain is shorter than {CONVERGED_TAUS} tau; run more --steps"))
    else:
        lines.append(f"grid: {d['grid_points']} points on [{d['grid_low']:.4g}, {d['grid_high']:.4g}], "
                     f"prior mass at the range's ends {d['prior_edge_mass']:.2g}")
    return lines


def predictive(problem: Problem, evaluate: Callable, post: Posterior, times: list[np.ndarray], *,
               draws: int = PREDICTIVE_DRAWS, seed: int = 0, level: float = LEVEL):
    """(median curve, its ``level`` credible band low and high, the posterior predictive band
    low and high) at ``times``: ``draws`` posterior samples in one batch. The predictive
    distribution of a measurement is the mixture of N(curve_k, σ_k²) over the draws; its
    quantiles are solved for exactly (bisection on the mixture's CDF), not drawn, so the
    band is as smooth as the curves."""
    from scipy.special import ndtr

    rng = np.random.default_rng(seed)
    pick = rng.choice(len(post.samples), size=min(draws, len(post.samples)), replace=False)
    X = post.samples[pick]
    curves = evaluate(X[:, :len(problem.names)], times)
    sigma = np.repeat(problem.sigmas(X), [len(t) for t in times], axis=1)
    q = np.array([0.5 - level / 2, 0.5 + level / 2])
    lo, hi = np.quantile(curves, q, axis=0)
    spread = 10 * sigma.max(axis=0)
    a = np.broadcast_to(curves.min(axis=0) - spread, (2, curves.shape[1])).copy()
    b = np.broadcast_to(curves.max(axis=0) + spread, (2, curves.shape[1])).copy()
    for _ in range(60):  # 2^-60 of the bracket: below the float's resolution
        mid = 0.5 * (a + b)
        below = np.mean(ndtr((mid[:, None, :] - curves[None]) / sigma[None]), axis=1) < q[:, None]
        a, b = np.where(below, mid, a), np.where(below, b, mid)
    return np.median(curves, axis=0), lo, hi, a[0], a[1]


def figure(path: Path, datasets, post: Posterior, times: list[np.ndarray], bands, title: str = "") -> Path:
    """The data, the posterior median curve, its credible band and the predictive band
    (with the noise), in % of CSA change."""
    median, lo, hi, plo, phi = bands
    plt = plot.pyplot()
    fig, ax = plt.subplots(figsize=(6, 4), constrained_layout=True)
    offset = 0
    for d, t in zip(datasets, times):
        part = slice(offset, offset + len(t))
        weeks = t / protocols.WEEK
        line, = ax.plot(weeks, 100 * (median[part] - 1), label=f"{d.name} ({d.protocol.name}) posterior median")
        colour = line.get_color()
        ax.fill_between(weeks, 100 * (lo[part] - 1), 100 * (hi[part] - 1), color=colour, alpha=0.35, lw=0,
                        label=f"{LEVEL:.0%} credible band")
        ax.fill_between(weeks, 100 * (plo[part] - 1), 100 * (phi[part] - 1), color=colour, alpha=0.12, lw=0,
                        label=f"{LEVEL:.0%} predictive band (with noise)")
        ax.plot(np.concatenate([[0], d.t]) / protocols.WEEK, 100 * (np.concatenate([[1], d.csa_ratio]) - 1), "o",
                color=colour, label=f"{d.name} data")
        offset += len(t)
    summary = "; ".join(f"{n} = {m:.4g} [{a:.4g}, {b:.4g}]" for n, m, a, b in
                        zip(post.columns, post.median, post.low, post.high))
    ax.set_xlabel("time (weeks)")
    ax.set_ylabel("CSA change (%)")
    ax.set_title("\n".join(textwrap.wrap((title + ". " if title else "") + f"{post.method}, {LEVEL:.0%} credible: "
                                          + summary, 110)), fontsize=7)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6)
    return plot.save(fig, path)
