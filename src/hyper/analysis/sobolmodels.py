"""The functions a Sobol analysis evaluates, one output per row of the sample matrix.

``signaling``: N(480 h) under ``daily15`` from the *baseline* rest state (MODEL.md §1), as a
function of the 14 parameters in ``PARAMETERS``; ``final_N``.

Evaluation. The rows are evaluated in chunks (jobs of ``hyper.runs.farm``, `hyper.analysis.chunks`),
each chunk one batch along the batch axis of the signaling model, through ``signaling.integrate``. The
default backend is its compiled RK4 step (``backend="c"``, C through cffi, the route
DOLFINx takes for its form kernels), bit for bit the numpy batch and an order of
magnitude faster (``python -m hyper.bench sobol``), with failures masked: a member that
fails (a non-finite or negative state) does not stop the others, its output becomes NaN.
The ``numpy`` backend is signaling's numpy batch with failures raised; there a failing
member fails its whole chunk.

The grown muscle (``csa-gain``, `csa_gain`): the 9-week CSA gain CSA/CSA0 - 1 at 1512 h
under ``mwf`` on the fast ODE growth model (`hyper.model.surrogate`: the signaling ODEs with the
Hill feedback kM = kM0 h(CSA/CSA0) at every period end, the idealized muscle's section
factor), as a function of the 17 parameters in ``GAIN_PARAMETERS``: the 12 signaling rates,
kM, kF, the thresholds thetaM and thetaF, and the feedback's Hill exponent ``hill_n``, each
uniform on [0.5, 2] x its baseline (hill_n on [2, 8] around the paper's 4). The Hill
constant K stays 1: h(1) = 1 needs it, and a K off 1 would change kM before any growth.
Batched like ``signaling``: a chunk is one batch of `surrogate.grow` (compiled RK4,
failures masked).

``ishigami``: the Ishigami test function, whose indices are known (`hyper.analysis.sobol.ishigami_exact`).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import numpy as np

from hyper.core.params import InputError
from hyper.model import signaling, surrogate
from hyper.model.protocols import Protocol, named

PARAMETERS = ("a10", "a20", "a3", "a4", "b1", "b2", "b3", "b4", "c21", "c32", "c42", "c43", "kM", "kF")
# csa-gain: the signaling rates, kM, kF, the thresholds and the feedback's Hill exponent
GAIN_PARAMETERS = (*PARAMETERS, "thetaM", "thetaF", "hill_n")
HILL_N = 4.0  # the paper's Hill exponent of the feedback (growth.feedback)
GAIN_PROTOCOL = "mwf"  # 9 weeks: the gain is read at its end, 1512 h
GAIN_GEOMETRY = "idealized"  # the section factor of surrogate.SECTION_FACTOR
ISHIGAMI_AB = (7.0, 0.1)

FUNCTIONS = ("signaling", "csa-gain", "ishigami")
SECTION_GEOMETRIES = ("idealized", "cylinder")
OUTPUT = {"signaling": "N(end)", "csa-gain": "CSA/CSA0 - 1 at the end", "ishigami": "the Ishigami function"}


def ishigami(X: np.ndarray, a: float = ISHIGAMI_AB[0], b: float = ISHIGAMI_AB[1]) -> np.ndarray:
    return np.sin(X[:, 0]) + a * np.sin(X[:, 1]) ** 2 + b * X[:, 2] ** 4 * np.sin(X[:, 0])


def sample_params(X: np.ndarray, names=PARAMETERS,
                  base: signaling.SignalingParams | None = None) -> signaling.SignalingParams:
    """The baseline parameters with the named fields replaced by the columns of X."""
    base = signaling.SignalingParams() if base is None else base
    return dataclasses.replace(base, **{name: X[:, k] for k, name in enumerate(names)})


def final_N(X: np.ndarray, *, names=PARAMETERS, protocol: Protocol | None = None, dt: float = 0.05,
            base: signaling.SignalingParams | None = None, backend: str = "c", at: float | None = None) -> np.ndarray:
    """N at ``at`` h (default: the end) of ``protocol`` (default daily15) for every row of X,
    from the baseline rest state, by RK4 with steps of at most dt. NaN marks a member whose
    trajectory failed (c backend); the numpy backend raises ``SignalingError`` instead."""
    protocol = named("daily15") if protocol is None else protocol
    end = protocol.end if at is None else at
    p = sample_params(np.atleast_2d(X), names, base)
    y0 = signaling.rest_state(base)
    if backend == "numpy":
        return signaling.integrate(p, protocol, y0, 0.0, end, dt, backend="numpy")[1][-1, 4]
    if backend != "c":
        raise InputError(f"backend must be 'c' or 'numpy', got {backend!r}")
    return signaling.integrate(p, protocol, y0, 0.0, end, dt, backend="c", failures="mask")[1][-1, 4]


def csa_gain(X: np.ndarray, *, names=GAIN_PARAMETERS, protocol: Protocol | None = None, dt: float = 0.05,
             geometry: str = GAIN_GEOMETRY, base: signaling.SignalingParams | None = None,
             backend: str = "c", at: float | None = None) -> np.ndarray:
    """CSA/CSA0 - 1 at ``at`` h (default: the end) of ``protocol`` (default mwf, 1512 h) for every row of X, on
    the fast growth model (`surrogate.grow`, Hill feedback). A column named ``hill_n`` is the
    feedback's exponent; the others replace SignalingParams fields. NaN marks a member whose
    trajectory failed (c backend); the numpy backend raises ``SignalingError`` instead."""
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


def settings(function: str, protocol: Protocol | None, *, dt: float, geometry: str = GAIN_GEOMETRY) -> dict:
    """What the outputs of ``function`` depend on besides the sample matrix (and, for the
    model functions, the problem and the time, which the caller adds): the digest's settings."""
    if function == "ishigami":
        return {"function": "ishigami", "a_b": ISHIGAMI_AB}
    if function == "csa-gain":
        return {"function": "csa-gain", "dt": dt, "protocol": protocol.to_attributes(),
                "baseline": dataclasses.asdict(signaling.SignalingParams()), "start": "baseline rest state",
                "names": list(GAIN_PARAMETERS), "feedback": "hill", "K": 1.0, "geometry": geometry,
                "section_factor": surrogate.section_factor(geometry), "model": "surrogate.grow"}
    return {"function": "signaling", "dt": dt, "protocol": protocol.to_attributes(),
            "baseline": dataclasses.asdict(signaling.SignalingParams()), "start": "baseline rest state"}


def evaluator(function: str, *, names, protocol: Protocol | None, dt: float, geometry: str = GAIN_GEOMETRY,
              backend: str = "c", at: float | None = None) -> Callable[[np.ndarray], np.ndarray]:
    """The rows' function of ``function`` (one of `FUNCTIONS`) with its settings bound:
    `ishigami`, `csa_gain` or `final_N`."""
    if function == "ishigami":
        return ishigami
    if function == "csa-gain":
        return functools.partial(csa_gain, names=names, protocol=protocol, dt=dt, geometry=geometry,
                                 backend=backend, at=at)
    return functools.partial(final_N, names=names, protocol=protocol, dt=dt, backend=backend, at=at)
