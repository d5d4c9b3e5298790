"""IGF1–AKT–FOXO–mTOR signaling (MODEL.md §1): parameters, stimuli, right-hand side, integrators.

State ``y = (igf1, akt, foxo, mtor, N)``, shape (5,) for one member or (5, n) for a batch.
The batch axis is later the mesh cells of one rank or the samples of a Sobol analysis:
every parameter may be a float or an array of n per-member values.

Integrators:

- ``integrate``: classical RK4 with fixed steps that land on every time where the
  right-hand side is known in advance to be non-smooth (``switch_times``) and on every
  requested output time. On each piece between such times the stimuli are evaluated on
  their smooth branch, so the method keeps its order there. Backends: ``numpy`` runs a
  batch on chunks of ``CHUNK`` members with in-place numpy updates and one member as
  plain Python floats; ``c`` runs the same step compiled at run time
  (``hyper.signaling_c``, about ten times faster per member); ``auto`` (the default)
  takes C for batches of at least ``AUTO_MIN_MEMBERS`` where a C compiler is at hand,
  numpy otherwise. All perform the same floating-point operations in the same order, so a
  member of a batch equals its single run, on either backend, bit for bit.
  ``failures="mask"`` turns a member whose state goes non-finite or negative into NaN
  and a flag instead of an error.
- ``reference``: SciPy's DOP853 at tight tolerance on the same pieces, for verification.

The CLI (``python -m hyper.signaling``) runs protocols, writes HDF5 series and the
Fig. 3A–E analog.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hyper import params as _params
from hyper.params import InputError
from hyper.protocols import NAMES, Protocol, load, named

STATES = ("igf1", "akt", "foxo", "mtor", "N")

# Members per chunk of the batch integrator: the chunk's state and work arrays (about 25
# rows of CHUNK doubles) stay in a 2 MiB L2 cache, while numpy's per-call overhead
# (about 1 µs) is spread over enough members. Measured best on the development machine.
CHUNK = 8192

Array = float | np.ndarray


class SignalingError(RuntimeError):
    """The integration produced a non-finite or negative state."""


@dataclass(frozen=True)
class SignalingParams:
    """Table 2 of the paper (MODEL.md §1). Every field is a float or an array of per-member values."""

    a10: Array = 0.09  # 1/h, IGF1 baseline growth rate
    a20: Array = 0.4875  # 1/h, AKT baseline growth rate
    a3: Array = 0.01068  # 1/h, FOXO growth rate
    a4: Array = 0.004635  # 1/h, mTOR growth rate
    b1: Array = 2.0  # 1/h, IGF1 self-inhibition
    b2: Array = 0.5  # 1/h, AKT self-inhibition
    b3: Array = 0.02  # 1/h, FOXO self-inhibition
    b4: Array = 0.01  # 1/h, mTOR self-inhibition
    c21: Array = 0.2846  # 1/h, IGF1 -> AKT
    c32: Array = 0.002  # 1/h, AKT -| FOXO
    c42: Array = 0.001139  # 1/h, AKT -> mTOR
    c43: Array = 0.0025  # 1/h, FOXO -| mTOR
    kM: Array = 0.01  # 1/h, protein synthesis rate
    kF: Array = 0.019  # 1/h, protein degradation rate
    Nmin: Array = 0.5  # -, lower end of the admissible myofibril range
    Nmax: Array = 1.3  # -, upper end of the admissible myofibril range
    thetaF: Array = 0.434  # -, FOXO threshold
    thetaM: Array = 0.469  # -, mTOR threshold
    tau_h: Array = 6.0  # h, AKT transient time scale
    t1: Array = 17.0  # h, AKT transient delay
    tau_d: Array = 12.0  # h, IGF1 stimulus delay
    beta: Array = 2.0 / 50.0  # 1/(h kgf), stimulus scale
    Fmax: Array = 150.0  # kgf, maximal force capacity

    # rates that vanish make the model degenerate (no equilibrium, a frozen species)
    POSITIVE = ("a10", "a20", "a3", "a4", "b1", "b2", "b3", "b4", "tau_h", "Fmax", "Nmax")

    def __post_init__(self):
        sizes = set()
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if np.ndim(value) == 0:
                value = _params.as_float(value.item() if isinstance(value, (np.ndarray, np.generic)) else value, f.name)
            else:
                value = np.array(value, dtype=float)
                if value.ndim != 1 or value.size == 0:
                    raise InputError(f"{f.name}: per-member values must be a non-empty 1-D array, got shape {value.shape}")
                if not np.all(np.isfinite(value)):
                    raise InputError(f"{f.name}: every per-member value must be finite")
                value.setflags(write=False)
                sizes.add(value.size)
            object.__setattr__(self, f.name, value)
        if len(sizes) > 1:
            raise InputError(f"per-member parameter arrays differ in length: {sorted(sizes)}")
        object.__setattr__(self, "_size", sizes.pop() if sizes else None)
        _params.check_positive(self, *self.POSITIVE)
        for name in ("c21", "c32", "c42", "c43", "kM", "kF", "Nmin", "thetaF", "thetaM", "t1", "tau_d", "beta"):
            if np.any(np.asarray(getattr(self, name)) < 0):
                raise InputError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if np.any(np.asarray(self.Nmin) >= np.asarray(self.Nmax)):
            raise InputError(f"Nmin must be < Nmax, got Nmin={self.Nmin!r}, Nmax={self.Nmax!r}")

    @property
    def size(self) -> int | None:
        """The number of members if some field is an array, else None."""
        return self._size

    def take(self, index) -> SignalingParams:
        """The members at ``index`` (an index array); scalar fields stay scalar."""
        return dataclasses.replace(
            self,
            **{
                f.name: getattr(self, f.name)[index]
                for f in dataclasses.fields(self)
                if isinstance(getattr(self, f.name), np.ndarray)
            },
        )

    def member(self, i: int) -> SignalingParams:
        """Member ``i`` with plain float fields."""
        return dataclasses.replace(
            self,
            **{
                f.name: float(getattr(self, f.name)[i])
                for f in dataclasses.fields(self)
                if isinstance(getattr(self, f.name), np.ndarray)
            },
        )


def load_params(path: str | Path | None = None, **overrides) -> SignalingParams:
    """Table values, overridden by a TOML file whose keys are field names, then by keywords."""
    return _params.load_params(SignalingParams, path, **overrides)


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
    from scipy.special import lambertw

    u = -float(params.t1) / float(params.tau_h)
    if u >= -1.0:
        return 0.0
    return float(params.t1) + float(params.tau_h) * float(lambertw(u * math.exp(u), 0).real)


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
    f = kM * np.maximum(np.asarray(x4) - params.thetaM, 0.0) - params.kF * np.maximum(np.asarray(x3) - params.thetaF, 0.0)
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


def _scalar_rhs(p: SignalingParams, kM: float, s: float = 1.0):
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


class _Kernel:
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
    n = _batch_size(params, kM, y)
    if n is None:
        return np.array(_scalar_rhs(params, kM)(*y.tolist(), float(A1), float(A2)))
    Y = np.array(np.broadcast_to(y.reshape(5, -1), (5, n)))
    kernel = _Kernel(params, kM, n, wide_rates=np.ndim(A1) > 0 or np.ndim(A2) > 0)
    kernel.set_a1(A1)
    kernel.set_a2(A2)
    K = np.empty_like(Y)
    kernel(Y, K)
    return K


def _batch_size(params: SignalingParams, kM: Array, y: np.ndarray) -> int | None:
    """The common number of members of params, kM and y (None: one member, all scalar, y 1-D)."""
    if y.ndim not in (1, 2) or y.shape[0] != 5:
        raise ValueError(f"y must have shape (5,) or (5, n), got {y.shape}")
    sizes = {params.size, np.size(kM) if np.ndim(kM) else None, y.shape[1] if y.ndim == 2 else None} - {None}
    if len(sizes) > 1:
        raise ValueError(f"batch sizes differ between parameters, kM and y: {sorted(sizes)}")
    return sizes.pop() if sizes else None


# --------------------------------------------------------------------------------------
# Pieces: the right-hand side is smooth between consecutive switch times.

TIMING = ("tau_d", "t1", "tau_h")


def _timing_groups(p: SignalingParams, n: int):
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
    for _, p in _timing_groups(params, n):
        times += [starts + p.tau_d, ends + p.tau_d]
        duration = bump_duration(p)
        if duration > 0:
            bump_end = starts + duration
            times.append(bump_end[bump_end < np.append(starts[1:], np.inf)])
    times = np.unique(np.concatenate(times))
    return times[(times > t0) & (times < t1)]


@dataclass(frozen=True)
class _Piece:
    t0: float
    t1: float
    intensity: float | None  # of the session driving a1(t - tau_d) on the piece; None at rest
    t_ex: float | None  # start of the session whose AKT bump is alive on the piece
    out: int  # index of t1 among the output times, or -1


def _pieces(protocol: Protocol, p: SignalingParams, t0: float, t1: float, out_times: np.ndarray) -> list[_Piece]:
    """Split [t0, t1] at the switch and output times (p has scalar timing)."""
    inner = out_times[(out_times > t0) & (out_times < t1)]
    cuts = np.unique(np.concatenate([switch_times(protocol, p, t0, t1), inner]))
    bounds = [float(t0), *cuts.tolist(), float(t1)]
    out_index = {float(t): k for k, t in enumerate(out_times)}
    duration = bump_duration(p)
    starts, ends, intensities = protocol.starts, protocol.ends, protocol.intensities
    pieces = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        # the stimulus branches are constant on the open piece: read them at its middle
        mid = 0.5 * (a + b)
        i = int(np.searchsorted(starts, mid - p.tau_d, side="right")) - 1
        intensity = float(intensities[i]) if i >= 0 and mid - p.tau_d < ends[i] else None
        k = int(np.searchsorted(starts, mid, side="right")) - 1
        t_ex = float(starts[k]) if k >= 0 and mid - starts[k] < duration else None
        pieces.append(_Piece(a, b, intensity, t_ex, out_index.get(b, -1)))
    return pieces


def _a1_value(piece: _Piece, p: SignalingParams) -> Array:
    return p.a10 if piece.intensity is None else p.beta * piece.intensity * p.Fmax


def _stage_bumps(piece: _Piece, p: SignalingParams, steps: int, h: float) -> np.ndarray | None:
    """a2 - a20 at the 2*steps + 1 stage times t0, t0 + h/2, ..., t1 of the piece (None: no bump)."""
    if piece.t_ex is None:
        return None
    tau = piece.t0 + np.arange(2 * steps + 1) * (0.5 * h)
    tau[-1] = piece.t1
    return g((tau - piece.t_ex) - p.t1, p.tau_h) - g(-p.t1, p.tau_h)


def _steps(piece: _Piece, dt: float) -> tuple[int, float]:
    length = piece.t1 - piece.t0
    # the tolerance keeps round-off in the length from adding a step (0.6000000000000001 / 0.05 = 12.000000000000002)
    steps = max(1, math.ceil(length / dt - 1e-9))
    return steps, length / steps


def _failure(t_from: float, t_to: float, member: int, y, dt: float) -> SignalingError:
    state = ", ".join(f"{name}={float(v):.4g}" for name, v in zip(STATES, y))
    return SignalingError(
        f"RK4 step from t = {t_from:.6g} h to t = {t_to:.6g} h gave member {member} a non-finite or "
        f"negative state ({state}): the step is beyond RK4's stability limit for this stretch; "
        f"use a smaller dt (now {dt:g} h)"
    )


# One RK4 step with K_i = (h/2) k_i: y + K1, y + K2, y + 2 K3 are the stage states and
# y_new = y + ((K1 + K4) + 2 (K2 + K3)) / 3 = y + h/6 (k1 + 2 k2 + 2 k3 + k4).
THIRD = 1.0 / 3.0


def _rk4_single(y, p: SignalingParams, kM: float, pieces: list[_Piece], dt: float, out: np.ndarray, member: int):
    """RK4 for one member on plain floats: the same operations, in the same order, as _rk4_block."""
    inf, third = math.inf, THIRD
    x1, x2, x3, x4, N = (float(v) for v in y)
    for piece in pieces:
        steps, h = _steps(piece, dt)
        s = 0.5 * h
        f = _scalar_rhs(p, kM, s)
        A1 = s * float(_a1_value(piece, p))
        bumps = _stage_bumps(piece, p, steps, h)
        a20 = float(p.a20)
        A2 = [s * a20] * (2 * steps + 1) if bumps is None else [s * (a20 + b) for b in bumps.tolist()]
        for j in range(steps):
            k11, k12, k13, k14, k15 = f(x1, x2, x3, x4, N, A1, A2[2 * j])
            k21, k22, k23, k24, k25 = f(x1 + k11, x2 + k12, x3 + k13, x4 + k14, N + k15, A1, A2[2 * j + 1])
            k31, k32, k33, k34, k35 = f(x1 + k21, x2 + k22, x3 + k23, x4 + k24, N + k25, A1, A2[2 * j + 1])
            s1, s2, s3, s4, s5 = k21 + k31, k22 + k32, k23 + k33, k24 + k34, k25 + k35
            k41, k42, k43, k44, k45 = f(
                x1 + (k31 + k31), x2 + (k32 + k32), x3 + (k33 + k33), x4 + (k34 + k34), N + (k35 + k35),
                A1, A2[2 * j + 2],
            )
            x1 = x1 + ((k11 + k41) + (s1 + s1)) * third
            x2 = x2 + ((k12 + k42) + (s2 + s2)) * third
            x3 = x3 + ((k13 + k43) + (s3 + s3)) * third
            x4 = x4 + ((k14 + k44) + (s4 + s4)) * third
            N = N + ((k15 + k45) + (s5 + s5)) * third
            if not (0.0 <= x1 < inf and 0.0 <= x2 < inf and 0.0 <= x3 < inf and 0.0 <= x4 < inf and 0.0 <= N < inf):
                ta = piece.t0 + j * h
                raise _failure(ta, ta + h, member, (x1, x2, x3, x4, N), dt)
        if piece.out >= 0:
            out[piece.out] = (x1, x2, x3, x4, N)


def _rk4_block(Y: np.ndarray, p: SignalingParams, kM: Array, pieces: list[_Piece], tables, dt: float,
               out: np.ndarray, members: np.ndarray, failed: np.ndarray | None):
    """RK4 for a block of members in place on Y (5, n); ``tables`` holds each piece's steps, h and bumps.

    A failing member raises SignalingError, or, given ``failed`` (indexed by ``members``), is
    flagged there and parked at the zero state, a fixed point of the right-hand side, so
    that it neither trips the check again nor spreads NaNs; the caller blanks its outputs.
    """
    n = Y.shape[1]
    kernel = _Kernel(p, kM, n)
    K, ACC, W, Ys = (np.empty(Y.shape) for _ in range(4))
    for piece, (steps, h, bumps) in zip(pieces, tables):
        kernel.scale(0.5 * h)
        kernel.set_a1(_a1_value(piece, p))
        if bumps is None:
            kernel.set_a2(p.a20)
        for j in range(steps):
            if bumps is not None:
                kernel.set_bump(bumps[2 * j])
            kernel(Y, ACC)  # K1
            np.add(Y, ACC, out=Ys)
            if bumps is not None:
                kernel.set_bump(bumps[2 * j + 1])
            kernel(Ys, K)  # K2
            np.add(Y, K, out=Ys)
            kernel(Ys, W)  # K3
            np.add(K, W, out=K)  # K2 + K3
            np.add(W, W, out=W)
            np.add(Y, W, out=Ys)
            if bumps is not None:
                kernel.set_bump(bumps[2 * j + 2])
            kernel(Ys, W)  # K4
            np.add(ACC, W, out=ACC)
            np.add(K, K, out=K)
            np.add(ACC, K, out=ACC)
            np.multiply(ACC, THIRD, out=ACC)
            np.add(Y, ACC, out=Y)
            if not (Y.min() >= 0.0 and Y.max() < math.inf):
                bad = ~(np.isfinite(Y) & (Y >= 0.0)).all(axis=0)
                if failed is None:
                    first = int(np.flatnonzero(bad)[0])
                    ta = piece.t0 + j * h
                    raise _failure(ta, ta + h, int(members[first]), Y[:, first], dt)
                failed[members[bad]] = True
                Y[:, bad] = 0.0
        if piece.out >= 0:
            out[piece.out] = Y


def _output_times(t0: float, t1: float, out_times) -> np.ndarray:
    if not (math.isfinite(t0) and math.isfinite(t1) and t0 < t1):
        raise ValueError(f"need finite t0 < t1, got t0={t0}, t1={t1}")
    times = np.array([t0, t1] if out_times is None else out_times, dtype=float).ravel()
    if times.size == 0 or np.any(np.diff(times) <= 0) or times[0] < t0 or times[-1] > t1:
        raise ValueError(f"out_times must increase strictly within [t0, t1] = [{t0}, {t1}]")
    return times


BACKENDS = ("numpy", "c", "auto")
FAILURES = ("raise", "mask")

# The smallest batch that backend="auto" integrates in C. The numpy batch pays about 0.2 ms
# per step in numpy's per-call overhead whatever its size, so from two members on C is a
# hundred times faster; one member runs as plain Python floats at a few µs per step (0.2 s
# for nine weeks), not worth the two seconds of a first build of the kernel.
AUTO_MIN_MEMBERS = 2


def c_backend_error() -> str | None:
    """None when the C backend can run here, else why not. Builds or loads it on the first call."""
    from hyper import signaling_c

    try:
        signaling_c.kernel()
    except signaling_c.Unavailable as err:
        return str(err)
    return None


def _rk4_compiled(Y0: np.ndarray, p: SignalingParams, kM: Array, pieces: list[_Piece], tables, dt: float,
                  out: np.ndarray, members: np.ndarray, failed: np.ndarray | None):
    """``_rk4_block`` on the compiled kernel, for every member of a timing group at once.

    On a failure without ``failed`` the failing member's piece is run again by
    ``_rk4_single`` from the state the kernel started it at: the same bits, so the same
    step fails there and raises the numpy backend's error.
    """
    from hyper import signaling_c

    n = Y0.shape[1]
    plan = [(steps, h, _a1_value(piece, p), np.zeros(2 * steps + 1) if bumps is None else np.ascontiguousarray(bumps),
             piece.t0, piece.out) for piece, (steps, h, bumps) in zip(pieces, tables)]
    fail_t = np.empty(n)
    stopped = signaling_c.run(signaling_c.coefficients(p, kM, n), p.a20, Y0, plan, out, fail_t, THIRD,
                              stop=failed is None)
    if stopped is not None:
        k, i, y = stopped
        q = p.member(i) if p.size is not None else p
        _rk4_single(y, q, float(kM[i] if np.ndim(kM) else kM), [dataclasses.replace(pieces[k], out=-1)], dt,
                    np.empty((0, 5)), int(members[i]))
        raise AssertionError(f"the C kernel failed member {members[i]} on [{pieces[k].t0}, {pieces[k].t1}] h, numpy did not")
    if failed is not None:
        failed[members[fail_t >= 0.0]] = True


def integrate(params: SignalingParams, protocol: Protocol, y0, t0: float, t1: float, dt: float = 0.05, *,
              out_times=None, kM: Array | None = None, backend: str = "auto", failures: str = "raise"):
    """Classical RK4 from y0 at t0 to t1 with steps of at most dt (h) landing on every switch and output time.

    Returns (times, states): the output times (default [t0, t1]) and the states there,
    shape (len(times), 5, n), or (len(times), 5) for a 1-D y0 with scalar parameters.
    kM overrides params.kM (scalar or per member).

    backend: "numpy", "c" (compiled; raises ``signaling_c.Unavailable`` without a C
    compiler) or "auto" (C for at least ``AUTO_MIN_MEMBERS`` members where it can be
    built, else numpy, silently). Every backend gives the same bits; with several failing
    members "raise" may name another of them on C (the first to fail in the first block
    of ``signaling_c.BLOCK`` members that has one).

    failures: "raise" raises SignalingError when a step gives a member a non-finite or
    negative state (the message names the step, the member and its state). "mask" returns
    (times, states, failed) instead: ``failed`` flags those members, shape (n,) (a bool
    for one member), and their states are NaN at every output time; the other members
    are the same bits as in their own runs.
    """
    if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
        raise InputError(f"dt must be a finite number > 0 h, got {dt!r}")
    if backend not in BACKENDS:
        raise InputError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if failures not in FAILURES:
        raise InputError(f"failures must be one of {', '.join(FAILURES)}, got {failures!r}")
    kM = params.kM if kM is None else kM
    y0 = np.asarray(y0, dtype=float)
    n = _batch_size(params, kM, y0)
    times = _output_times(t0, t1, out_times)
    single = n is None
    n = n or 1
    compiled = backend == "c" or (backend == "auto" and n >= AUTO_MIN_MEMBERS and c_backend_error() is None)
    Y0 = np.broadcast_to(y0.reshape(5, -1), (5, n))
    states = np.empty((len(times), 5, n))
    if times[0] == t0:
        states[0] = Y0
    valid = slice(1, None) if times[0] == t0 else slice(None)
    failed = np.zeros(n, dtype=bool) if failures == "mask" else None
    # a failing step overflows or subtracts infinities on its way; the failure check reports
    # it, numpy's warnings would only repeat it
    with np.errstate(over="ignore", invalid="ignore"):
        for index, p in _timing_groups(params, n):
            pieces = _pieces(protocol, p, t0, t1, times)
            k = kM[index] if np.ndim(kM) else kM
            if index.size == 1 and not compiled:
                q = p.member(0) if p.size is not None else p
                out = np.empty((len(times), 5))
                try:
                    _rk4_single(Y0[:, index[0]], q, float(np.ravel(k)[0]), pieces, dt, out, int(index[0]))
                except SignalingError:
                    if failed is None:
                        raise
                    failed[index[0]] = True
                states[valid, :, index[0]] = out[valid]
                continue
            tables = []
            for piece in pieces:
                steps, h = _steps(piece, dt)
                tables.append((steps, h, _stage_bumps(piece, p, steps, h)))
            if compiled:
                out = np.empty((len(times), 5, index.size))
                _rk4_compiled(Y0[:, index], p, k, pieces, tables, dt, out, index, failed)
                states[valid, :, index] = out[valid]
                continue
            size = -(-index.size // -(-index.size // CHUNK))  # equal chunks of at most CHUNK members
            for c in range(0, index.size, size):
                sel = index[c : c + size]
                Y = np.array(Y0[:, sel], order="C")  # rows contiguous: fancy indexing may transpose
                out = np.empty((len(times), 5, sel.size))
                pc = p.take(np.arange(c, c + sel.size)) if p.size is not None else p
                kc = k[c : c + sel.size] if np.ndim(k) else k
                _rk4_block(Y, pc, kc, pieces, tables, dt, out, sel, failed)
                states[valid, :, sel] = out[valid]
    if failed is None:
        return times, (states[:, :, 0] if single else states)
    states[:, :, failed] = np.nan
    return times, (states[:, :, 0] if single else states), (bool(failed[0]) if single else failed)


def step_count(params: SignalingParams, protocol: Protocol, t0: float, t1: float, dt: float = 0.05, *,
               out_times=None) -> int:
    """How many RK4 steps ``integrate`` takes from t0 to t1 (for one member; the cost of a
    batch is this times the number of members)."""
    times = _output_times(t0, t1, out_times)
    p = next(_timing_groups(params, params.size or 1))[1]
    return sum(_steps(piece, dt)[0] for piece in _pieces(protocol, p, t0, t1, times))


def reference(params: SignalingParams, protocol: Protocol, y0, t0: float, t1: float, *, out_times=None,
              kM: Array | None = None, rtol: float = 1e-13, atol: float = 1e-15, method: str = "DOP853"
              ) -> tuple[np.ndarray, np.ndarray]:
    """A high-accuracy solution for verification: SciPy's ``method`` at tight tolerance, restarted
    on every piece between switch and output times (smooth right-hand side on each).

    Same arguments and return convention as ``integrate``; members are solved one by one.
    """
    from scipy.integrate import solve_ivp

    kM = params.kM if kM is None else kM
    y0 = np.asarray(y0, dtype=float)
    n = _batch_size(params, kM, y0)
    times = _output_times(t0, t1, out_times)
    single = n is None
    n = n or 1
    Y0 = np.broadcast_to(y0.reshape(5, -1), (5, n))
    states = np.empty((len(times), 5, n))
    for m in range(n):
        p = params.member(m) if params.size is not None else params
        f = _scalar_rhs(p, float(np.ravel(kM)[m] if np.ndim(kM) else kM))
        a20, t1_, tau_h = float(p.a20), float(p.t1), float(p.tau_h)
        g0 = g(-t1_, tau_h)
        y = Y0[:, m].copy()
        if times[0] == t0:
            states[0, :, m] = y
        for piece in _pieces(protocol, p, t0, t1, times):
            A1 = float(_a1_value(piece, p))
            if piece.t_ex is None:
                def fun(t, y, A1=A1):
                    return f(*y, A1, a20)
            else:
                def fun(t, y, A1=A1, t_ex=piece.t_ex):
                    return f(*y, A1, a20 + (g((t - t_ex) - t1_, tau_h) - g0))
            sol = solve_ivp(fun, (piece.t0, piece.t1), y, method=method, rtol=rtol, atol=atol)
            if not sol.success:
                raise SignalingError(f"reference integrator failed on [{piece.t0}, {piece.t1}] h: {sol.message}")
            y = sol.y[:, -1]
            if piece.out >= 0:
                states[piece.out, :, m] = y
    return times, (states[:, :, 0] if single else states)


# --------------------------------------------------------------------------------------
# CLI

PAPER = ("mwf", "every3days", "weekly")  # the three protocols of the paper's Fig. 3


def run(params: SignalingParams, protocol: Protocol, dt: float = 0.05, sample_every: float = 0.5) -> dict[str, np.ndarray]:
    """The series of one protocol from the baseline rest state, sampled every ``sample_every`` h."""
    times = np.arange(0.0, protocol.end, sample_every)
    times = np.append(times[times < protocol.end - 1e-9 * sample_every], protocol.end)
    t, y = integrate(params, protocol, rest_state(), 0.0, protocol.end, dt, out_times=times)
    return {"t": t, **{name: y[:, k] for k, name in enumerate(STATES)}}


def first_day(params: SignalingParams, protocol: Protocol, dt: float = 0.05, every: float = 0.05) -> dict[str, np.ndarray] | None:
    """The 24 h after the first session start, finely sampled (the figure's insets); None without sessions."""
    if not protocol.sessions:
        return None
    s0 = protocol.sessions[0].start
    stop = min(s0 + 24.0, protocol.end)
    times = s0 + np.arange(0.0, stop - s0 + 0.5 * every, every)
    t, y = integrate(params, protocol, rest_state(), 0.0, protocol.end, dt, out_times=times[times <= protocol.end])
    return {"t": t - s0, **{name: y[:, k] for k, name in enumerate(STATES)}}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m hyper.signaling",
        description="Run the IGF1-AKT-FOXO-mTOR signaling model (MODEL.md §1) for exercise protocols: "
        "HDF5 time series and the Fig. 3A-E analog.",
    )
    which = parser.add_mutually_exclusive_group()
    which.add_argument("--protocol", default="mwf", choices=[*NAMES, "all"],
                       help=f"named protocol; 'all' runs {', '.join(PAPER)} (default: mwf)")
    which.add_argument("--protocol-file", type=Path, metavar="F.toml", help="a protocol of your own (see hyper.protocols.load)")
    parser.add_argument("--params", type=Path, metavar="F.toml", help="parameter overrides, keys as in MODEL.md's table")
    parser.add_argument("--dt", type=float, default=0.05, help="largest RK4 step in h (default: 0.05)")
    parser.add_argument("--sample-every", type=float, default=0.5, metavar="H", help="output sampling in h (default: 0.5)")
    parser.add_argument("--output", type=Path, default=Path("results/signaling"),
                        help="an .h5 file (one protocol) or a folder that gets <protocol>.h5 per protocol "
                        "(default: results/signaling)")
    parser.add_argument("--plot", type=Path, metavar="F.png", help="write the figure here")
    return parser


def main(argv=None) -> int:
    from hyper import io

    args = _parser().parse_args(argv)
    try:
        for name, value in (("--dt", args.dt), ("--sample-every", args.sample_every)):
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"{name} must be a finite number > 0 h, got {value}")
        if args.plot is not None and args.plot.suffix != ".png":
            raise InputError(f"--plot must name a .png file, got {args.plot}")
        params = load_params(args.params)
        if args.protocol_file is not None:
            protocols = [load(args.protocol_file)]
        elif args.protocol == "all":
            protocols = [named(n) for n in PAPER]
        else:
            protocols = [named(args.protocol)]
        if args.output.suffix == ".h5":
            if len(protocols) > 1:
                raise InputError(f"--output {args.output}: with several protocols give a folder, not an .h5 file")
            paths = [args.output]
        else:
            paths = [args.output / f"{p.name}.h5" for p in protocols]
        runs = {p.name: run(params, p, args.dt, args.sample_every) for p in protocols}
        insets = {p.name: first_day(params, p, args.dt) for p in protocols}
    except InputError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except SignalingError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    for protocol, path in zip(protocols, paths):
        series = runs[protocol.name]
        io.write_series(
            path,
            series,
            attrs={"model": "signaling (MODEL.md §1)", "integrator": "RK4", "dt": args.dt,
                   "sample_every": args.sample_every, "N_final": float(series["N"][-1])},
            groups={"parameters": _params.as_attributes(params), "protocol": protocol.to_attributes()},
        )
        print(f"{protocol.name}: N({protocol.end:g} h) = {series['N'][-1]:.6f} -> {path}")
    if args.plot is not None:
        import matplotlib.pyplot as plt

        from hyper.signaling_plot import figure_protocols

        fig = figure_protocols(runs, {p.name: p for p in protocols}, params, insets)
        with io.atomic_path(args.plot) as tmp:
            fig.savefig(tmp, format="png", dpi=130)
        plt.close(fig)
        print(f"figure: {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
