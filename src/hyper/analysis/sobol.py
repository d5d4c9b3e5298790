"""Sobol sensitivity analysis of the signaling model (MODEL.md §7): the design and the indices.

What is analysed: N(480 h) under ``daily15`` from the *baseline* rest state (MODEL.md §1),
as a function of the 14 parameters in ``PARAMETERS``, each uniform on [0.5, 2] x its
baseline value; or the 9-week CSA gain on the fast growth model, or the Ishigami test
function (the functions of `hyper.analysis.sobolmodels`). All of it can be changed, in
SALib's problem form (`design`): the parameters, their bounds or multiples of the
baselines, the protocol, the time of the output, or a TOML file (`read_config`) with the
keys of `CONFIG_KEYS`, at its top level or in a study file's [sobol] table:

    [sobol]
    function = "signaling"            # or csa-gain
    protocol = "mwf"
    at = 336.0                        # h; the protocol's end by default
    names = ["kM", "kF", "a10"]       # SALib's problem: names and absolute bounds
    bounds = [[0.005, 0.02], [0.01, 0.04], [0.045, 0.18]]
    samples = 4096

SALib draws a Saltelli/Sobol design with second-order terms (`sample`), N (2D + 2) rows
for N base samples, and estimates first-order, total and second-order indices with
bootstrap confidence intervals (`analyze`).

Failures. Members whose trajectory fails are counted and reported, never dropped
silently. SALib needs every output, so by default (``on_failure="abort"``) no indices
are computed while any member failed; ``"drop"`` removes every base sample that has a
failed row (its whole block of 2D + 2 rows, which keeps SALib's design intact) and
says how many.

The rows are evaluated in chunks (`hyper.analysis.chunks`); the figures are
`hyper.analysis.sobolplot`'s; the job is `hyper.commands.sobol`. `store` writes the
results: sobol.h5 and indices.csv.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hyper.analysis.sobolmodels import FUNCTIONS, GAIN_PARAMETERS, HILL_N, ISHIGAMI_AB, PARAMETERS
from hyper.core import io
from hyper.core.params import InputError, as_float, as_int, positive_hours, read_toml, shown
from hyper.model import protocols, signaling

LOW, HIGH = 0.5, 2.0  # bounds as multiples of the baseline value
# base samples: N (2D + 2) rows of D parameters are drawn at once; 1e7 is about 25 GB
MAX_SAMPLES = 10**7
# the default: a power of two, where the Sobol sequence is balanced, near the paper's 10,000
SAMPLES = 2**13


# --------------------------------------------------------------------------------------
# The design


def problem(base: signaling.SignalingParams | None = None, names=PARAMETERS, low: float = LOW,
            high: float = HIGH) -> dict:
    """SALib's problem: each parameter uniform on [low, high] x its baseline value."""
    base = signaling.SignalingParams() if base is None else base
    return {
        "num_vars": len(names),
        "names": list(names),
        "bounds": [[low * float(getattr(base, n)), high * float(getattr(base, n))] for n in names],
    }


def gain_problem(base: signaling.SignalingParams | None = None, low: float = LOW, high: float = HIGH) -> dict:
    """SALib's problem of the CSA gain: ``GAIN_PARAMETERS`` each uniform on [low, high] x its
    baseline (the Hill exponent's baseline is ``HILL_N``)."""
    base = signaling.SignalingParams() if base is None else base
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
    known = [f.name for f in dataclasses.fields(signaling.SignalingParams)]
    known += ["hill_n"] if function == "csa-gain" else []
    unknown = [n for n in names if n not in known]
    if unknown or not names or len(set(names)) != len(names):
        raise InputError(f"expected distinct parameters of {', '.join(known)}; got {', '.join(names) or 'none'}",
                         field="names")
    if bounds is None:
        base = signaling.SignalingParams()
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
        "names": lambda v: isinstance(v, list) and all(isinstance(n, str) for n in v),
        "bounds": lambda v: isinstance(v, list) and all(isinstance(b, list) and len(b) == 2 for b in v),
    }
    expected = {"function": f"one of {', '.join(FUNCTIONS)}", "protocol": "a protocol name or file",
                "names": "an array of parameter names", "bounds": "an array of [lower, upper] pairs"}
    for key, value in data.items():
        if key in checks and not checks[key](value):
            raise InputError(f"{where}: {key}: expected {expected[key]}, got {shown(value)}")
    # the numbers, by the one numeric reader: finite, representable, in range
    if "at" in data:
        data["at"] = positive_hours(data["at"], f"{where}: at")
    if "samples" in data:
        data["samples"] = as_int(data["samples"], f"{where}: samples", 2, MAX_SAMPLES)
    if "num_vars" in data:
        data["num_vars"] = as_int(data["num_vars"], f"{where}: num_vars", 1)
    if "bounds" in data:
        data["bounds"] = [[as_float(x, f"{where}: bounds") for x in b] for b in data["bounds"]]
    if "num_vars" in data and data["num_vars"] != len(data.get("names", ())):
        raise InputError(f"{where}: num_vars: {data['num_vars']} does not count names ({len(data.get('names', ()))})")
    if "bounds" in data and "names" not in data:
        raise InputError(f"{where}: bounds: give the names they belong to")
    if "names" in data or "bounds" in data:
        # checked here, against the file's function (the widest set, csa-gain's, where the
        # file names none: --function may choose it), not only when the analysis starts
        try:
            design(data.get("function", "csa-gain"), data.get("names"), data.get("bounds"))
        except InputError as err:
            raise InputError(f"{where}: {err}") from None
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
# Storage

# the units of sobol.h5's datasets: the indices are fractions of the output's variance
INDEX_UNITS = {"parameters": "name", "X": "the parameters' own (see the bounds group)", "Y": "the output's own",
               "failed_rows": "index", **{k: "1" for k in ("S1", "S1_conf", "ST", "ST_conf", "S2", "S2_conf",
                                                          "S1_bootstrap", "ST_bootstrap")}}


def store(out: Path, prob: dict, X: np.ndarray, Y: np.ndarray, failed: np.ndarray, ind: Indices, *,
          attrs: dict, groups: dict) -> None:
    """Write ``out``/sobol.h5 (the design, the outputs, the indices and their bootstrap, with
    ``attrs`` and ``groups``) and ``out``/indices.csv (S1 and ST with their intervals)."""
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
