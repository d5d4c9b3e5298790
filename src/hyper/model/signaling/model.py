"""The signaling model itself (MODEL.md §1): states, rest state, stimuli, right-hand side.

State ``y = (igf1, akt, foxo, mtor, N)``, shape (5,) for one member or (5, n) for a
batch. The right-hand side is smooth except at known times (``switch_times``): the
integrators cut time there, and evaluate the stimuli on their smooth branch in between.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from hyper.core.params import InputError
from hyper.model.protocols import Protocol
from hyper.model.signaling.params import Array, SignalingParams

STATES = ("igf1", "akt", "foxo", "mtor", "N")


def rest_state(params: SignalingParams | None = None) -> np.ndarray:
    """The closed-form equilibrium without stimulus, with N0 = 1: shape (5,), or (5, n) for arrays.

    Every run starts from the rest state of the *baseline* parameters (MODEL.md §1),
    ``rest_state()``, also when its own parameters differ.
    """
    p = SignalingParams() if params is None else params
    x1 = p.a10 / p.b1
    x2 = (p.a20 + p.c21 * x1) / p.b2
    x3 = (p.a3 - p.c32 * x2) / p.b3
    x4 = (p.a4 + p.c42 * x2 - p.c43 * x3) / p.b4
    x = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (x1, x2, x3, x4, 1.0)))
    out = np.array(x)
    if np.any(out <= 0):
        raise InputError(
            "these parameters have no rest state with every species present "
            f"(closed form gives igf1, akt, foxo, mtor = {out[:4].tolist()}): "
            "need a3 > c32*akt* and a4 + c42*akt* > c43*foxo*"
        )
    return out


def g(s: Array, tau_h: Array) -> Array:
    """Antiderivative of the AKT bump: g(s) = -(s / (2 tau_h)) exp(s / tau_h)."""
    return -(s / (2.0 * tau_h)) * np.exp(s / tau_h)


def bump_duration(params: SignalingParams) -> float:
    """How long the AKT transient lasts after a session start: t1 + s*, with s* in (-tau_h, 0)
    the root of g(s) = g(-t1). Closed form via the principal branch of Lambert's W, since
    g(s) = c is (s/tau_h) exp(s/tau_h) = -2c. Zero when t1 <= tau_h (the bump never rises)."""
    u = -float(params.t1) / float(params.tau_h)
    if u >= -1.0:
        return 0.0
    return float(params.t1) + float(params.tau_h) * lambert_w0(u * math.exp(u))


# Halley's iteration converges cubically: a handful of steps from the series anywhere on (-1/e, 0)
LAMBERT_ITERATIONS = 50
EPS = float(np.finfo(float).eps)


def lambert_w0(z: float) -> float:
    """The principal branch of Lambert's W on (-1/e, 0), w in (-1, 0) with w exp(w) = z:
    Halley's iteration from the series at the branch point. Within an ulp or two of
    scipy.special.lambertw, whose import alone cost a growth run 0.4 s of CPU."""
    p = math.sqrt(max(2.0 * (math.e * z + 1.0), 0.0))
    w = -1.0 + p * (1.0 + p * (-1.0 / 3.0 + p * 11.0 / 72.0))
    for _ in range(LAMBERT_ITERATIONS):
        ew = math.exp(w)
        f = w * ew - z
        step = f / (ew * (w + 1.0) - (w + 2.0) * f / (2.0 * w + 2.0))
        w -= step
        if abs(step) <= 4.0 * EPS * abs(w):
            break
    return w


def a1(t: Array, protocol: Protocol, params: SignalingParams) -> Array:
    """The exercise stimulus at time t (h): beta * I * Fmax inside a session [s, e), a10 outside.

    The IGF1 equation sees it delayed, a1(t - tau_d).
    """
    t = np.asarray(t, dtype=float)
    if not protocol.sessions:
        return (params.a10 + np.zeros(t.shape))[()]
    i = np.searchsorted(protocol.starts, t, side="right") - 1
    j = np.maximum(i, 0)
    inside = (i >= 0) & (t < protocol.ends[j])
    return np.where(inside, params.beta * protocol.intensities[j] * params.Fmax, params.a10)[()]


def a2(t: Array, protocol: Protocol, params: SignalingParams) -> Array:
    """AKT growth rate: a20 + max(0, g(t - t_ex - t1) - g(-t1)), t_ex the latest session start <= t."""
    t = np.asarray(t, dtype=float)
    if not protocol.sessions:
        return (params.a20 + np.zeros(t.shape))[()]
    i = np.searchsorted(protocol.starts, t, side="right") - 1
    s = np.minimum(t - protocol.starts[np.maximum(i, 0)] - params.t1, 0.0)  # the bump lives at s < 0
    bump = np.maximum(g(s, params.tau_h) - g(-params.t1, params.tau_h), 0.0)
    return (params.a20 + np.where(i >= 0, bump, 0.0))[()]


def net_balance(x3: Array, x4: Array, N: Array, params: SignalingParams, kM: Array | None = None) -> Array:
    """dN/dt = kM max(x4 - thetaM, 0) - kF max(x3 - thetaF, 0) inside [Nmin, Nmax], else 0."""
    kM = params.kM if kM is None else kM
    f = (kM * np.maximum(np.asarray(x4) - params.thetaM, 0.0)
         - params.kF * np.maximum(np.asarray(x3) - params.thetaF, 0.0))
    inside = (np.asarray(N) >= params.Nmin) & (np.asarray(N) <= params.Nmax)
    return np.where(inside, f, 0.0)[()]


# --------------------------------------------------------------------------------------
# The right-hand side, twice: on plain floats for one member, in place on numpy arrays for
# a batch. The two must evaluate the same expression trees (IEEE +, -, * are exactly
# rounded and commutative, so a*b == b*a, but (a+b)+c != a+(b+c)); -c32 and -c43 enter as
# negated coefficients (x - c*y == x + (-c)*y exactly).
#
# Both return s times the derivative: RK4 wants (h/2) k at every stage, and scaling the
# rate constants by s once per piece is free, where scaling k would cost a pass over the
# batch per stage. The stimuli A1, A2 are passed already scaled.


def scalar_rhs(p: SignalingParams, kM: float, s: float = 1.0):
    """f(x1, x2, x3, x4, N, s*A1, s*A2) -> s times the five derivatives, for one member (plain floats)."""
    b1, b2, b3, b4 = s * float(p.b1), s * float(p.b2), s * float(p.b3), s * float(p.b4)
    a3, a4 = s * float(p.a3), s * float(p.a4)
    c21, mc32, c42, mc43 = s * float(p.c21), s * -float(p.c32), s * float(p.c42), s * -float(p.c43)
    thF, thM, kF, kM = float(p.thetaF), float(p.thetaM), s * float(p.kF), s * float(kM)
    Nmin, Nmax = float(p.Nmin), float(p.Nmax)

    def f(x1, x2, x3, x4, N, A1, A2):
        k1 = x1 * (A1 - b1 * x1)
        k2 = x2 * ((A2 - b2 * x2) + c21 * x1)
        k3 = x3 * ((a3 - b3 * x3) + mc32 * x2)
        k4 = x4 * (((a4 - b4 * x4) + c42 * x2) + mc43 * x3)
        if Nmin <= N <= Nmax:
            d3 = x3 - thF
            d4 = x4 - thM
            kN = (kM * d4 if d4 > 0.0 else 0.0) - (kF * d3 if d3 > 0.0 else 0.0)
        else:
            kN = 0.0
        return k1, k2, k3, k4, kN

    return f


def _column(values, n: int, wide: bool = False) -> np.ndarray:
    """Rows of coefficients: (rows, 1) when all are scalars (broadcast), else (rows, n)."""
    if not wide and all(np.ndim(v) == 0 for v in values):
        return np.array([float(v) for v in values]).reshape(-1, 1)
    return np.stack([np.broadcast_to(np.asarray(v, dtype=float), (n,)) for v in values])


class BatchRhs:
    """s times the right-hand side on a block of n members, in place into preallocated arrays."""

    def __init__(self, p: SignalingParams, kM: Array, n: int, wide_rates: bool = False):
        self.rates = {
            "B": _column([p.b1, p.b2, p.b3, p.b4], n),
            "C1": _column([p.c21, -np.asarray(p.c32)], n),
            "C2": _column([p.c42, -np.asarray(p.c43)], n),
            "KK": _column([p.kF, kM], n),
            "A34": _column([p.a3, p.a4], n),
        }
        # growth rates s*(a1(t - tau_d), a2(t), a3, a4): rows 0 and 1 are set per piece and
        # stage, per member where a stimulus parameter is
        wide_rates = wide_rates or any(np.ndim(v) for v in (p.a10, p.a20, p.beta, p.Fmax, p.a3, p.a4))
        self.G = _column([p.a10, p.a20, p.a3, p.a4], n, wide_rates).copy()
        self.TH = _column([p.thetaF, p.thetaM], n)
        self.Nmin, self.Nmax = p.Nmin, p.Nmax
        # N inside [max Nmin, min Nmax] for every member: the range test is a no-op
        self.inner = (float(np.max(p.Nmin)), float(np.min(p.Nmax)))
        self.a20 = p.a20
        self.T = np.empty((4, n))
        self.P = np.empty((2, n))
        self.scale(1.0)

    def scale(self, s: float) -> None:
        """Return s times the derivative from now on; set the stimuli after this."""
        self.s = s
        self.B, self.C1, self.C2, self.KK = (s * self.rates[k] for k in ("B", "C1", "C2", "KK"))
        np.multiply(s, self.rates["A34"], out=self.G[2:])

    def set_a1(self, value: Array) -> None:
        np.multiply(self.s, value, out=self.G[0])

    def set_a2(self, value: Array) -> None:
        np.multiply(self.s, value, out=self.G[1])

    def set_bump(self, bump: float) -> None:
        np.add(self.a20, bump, out=self.G[1])
        np.multiply(self.s, self.G[1], out=self.G[1])

    def __call__(self, Y: np.ndarray, K: np.ndarray) -> None:
        T, P = self.T, self.P
        np.multiply(self.B, Y[:4], out=T)
        np.subtract(self.G, T, out=T)  # a_i - b_i x_i
        np.multiply(self.C1, Y[0:2], out=P)  # c21 x1, -c32 x2
        np.add(T[1:3], P, out=T[1:3])
        np.multiply(self.C2, Y[1:3], out=P)  # c42 x2, -c43 x3
        np.add(T[3], P[0], out=T[3])
        np.add(T[3], P[1], out=T[3])
        np.multiply(Y[:4], T, out=K[:4])
        np.subtract(Y[2:4], self.TH, out=P)
        np.maximum(P, 0.0, out=P)
        np.multiply(P, self.KK, out=P)  # kF max(x3 - thetaF, 0), kM max(x4 - thetaM, 0)
        np.subtract(P[1], P[0], out=K[4])
        N = Y[4]
        if not (N.min() >= self.inner[0] and N.max() <= self.inner[1]):
            K[4] *= (N >= self.Nmin) & (N <= self.Nmax)


def rhs(t: float, y: np.ndarray, params: SignalingParams, protocol: Protocol, kM: Array | None = None) -> np.ndarray:
    """dy/dt at time t for y of shape (5,) or (5, n); kM overrides params.kM (scalar or per member)."""
    kM = params.kM if kM is None else kM
    y = np.asarray(y, dtype=float)
    A1 = a1(t - params.tau_d, protocol, params)
    A2 = a2(t, protocol, params)
    n = batch_size(params, kM, y)
    if n is None:
        return np.array(scalar_rhs(params, kM)(*y.tolist(), float(A1), float(A2)))
    Y = np.array(np.broadcast_to(y.reshape(5, -1), (5, n)))
    kernel = BatchRhs(params, kM, n, wide_rates=np.ndim(A1) > 0 or np.ndim(A2) > 0)
    kernel.set_a1(A1)
    kernel.set_a2(A2)
    K = np.empty_like(Y)
    kernel(Y, K)
    return K


def batch_size(params: SignalingParams, kM: Array, y: np.ndarray) -> int | None:
    """The common number of members of params, kM and y (None: one member, all scalar, y 1-D)."""
    if y.ndim not in (1, 2) or y.shape[0] != 5:
        raise ValueError(f"y must have shape (5,) or (5, n), got {y.shape}")
    sizes = {params.size, np.size(kM) if np.ndim(kM) else None, y.shape[1] if y.ndim == 2 else None} - {None}
    if len(sizes) > 1:
        raise ValueError(f"batch sizes differ between parameters, kM and y: {sorted(sizes)}")
    return sizes.pop() if sizes else None


# --------------------------------------------------------------------------------------
# Switch times: the right-hand side is smooth between consecutive ones.

TIMING = ("tau_d", "t1", "tau_h")


def timing_groups(p: SignalingParams, n: int):
    """(member indices, parameters with scalar timing) for each distinct (tau_d, t1, tau_h).

    Switch times depend on these three, so members that differ in them cannot share steps.
    """
    if not any(np.ndim(getattr(p, k)) for k in TIMING):
        # one group: skip the row sort of np.unique (0.1 s for 1e5 members) and the copies of take
        yield np.arange(n), p
        return
    keys = np.column_stack([np.broadcast_to(np.asarray(getattr(p, k), dtype=float), (n,)) for k in TIMING])
    unique, inverse = np.unique(keys, axis=0, return_inverse=True)
    for k, key in enumerate(unique):
        index = np.flatnonzero(inverse.ravel() == k)
        sub = p.take(index) if p.size is not None else p
        yield index, dataclasses.replace(sub, **dict(zip(TIMING, map(float, key))))


def switch_times(protocol: Protocol, params: SignalingParams, t0: float, t1: float) -> np.ndarray:
    """Sorted times in the open interval (t0, t1) where the right-hand side is not smooth.

    a1(t - tau_d) jumps at s_i + tau_d and e_i + tau_d; a2 has a kink (or resets) at every
    session start s_i and a kink where the bump ends, s_i + ``bump_duration`` (if that comes
    before the next start). Per-member timing parameters contribute all their distinct values.
    """
    if not protocol.sessions:
        return np.empty(0)
    starts, ends = protocol.starts, protocol.ends
    times = [starts]
    n = params.size or 1
    for _, p in timing_groups(params, n):
        times += [starts + p.tau_d, ends + p.tau_d]
        duration = bump_duration(p)
        if duration > 0:
            bump_end = starts + duration
            times.append(bump_end[bump_end < np.append(starts[1:], np.inf)])
    times = np.unique(np.concatenate(times))
    return times[(times > t0) & (times < t1)]


