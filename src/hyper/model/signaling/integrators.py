"""Integrators of the signaling model: RK4 over a batch axis and a reference solution.

- ``integrate``: classical RK4 with fixed steps that land on every time where the
  right-hand side is known in advance to be non-smooth (``model.switch_times``) and on
  every requested output time. On each piece between such times the stimuli are
  evaluated on their smooth branch, so the method keeps its order there. Backends:
  ``numpy`` runs a batch on chunks of ``CHUNK`` members with in-place numpy updates and
  one member as plain Python floats; ``c`` runs the same step compiled at run time
  (``hyper.model.signaling.compiled``, about ten times faster per member); ``auto`` (the
  default) takes C for batches of at least ``AUTO_MIN_MEMBERS`` where a C compiler is at
  hand, numpy otherwise. All perform the same floating-point operations in the same
  order, so a member of a batch equals its single run, on either backend, bit for bit.
  ``failures="mask"`` turns a member whose state goes non-finite or negative into NaN
  and a flag instead of an error. N stops exactly at the bound of [Nmin, Nmax] that a
  step carries it across (``stop_at_bounds``), in every backend alike.
- ``reference``: SciPy's DOP853 at tight tolerance on the same pieces, for verification.
- ``original``: the original code's integration (MODEL.md §9), SciPy's RK45 at its loose
  default tolerances, for reproducing its numbers (``--signaling-method rk45-original``).
- ``run`` and ``first_day``: the sampled series of one protocol from the rest state.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from hyper.core.params import InputError, positive_hours
from hyper.model.protocols import Protocol
from hyper.model.signaling import compiled
from hyper.model.signaling.model import (
    STATES,
    BatchRhs,
    batch_size,
    bump_duration,
    g,
    rest_state,
    scalar_rhs,
    switch_times,
    timing_groups,
)
from hyper.model.signaling.params import Array, SignalingParams

# The smallest steps taken: 100x below the finest RK4 step measured (0.01 h, bench
# signaling), whose error is already at round-off; anything smaller only takes for ever.
SMALLEST_DT = 1e-4  # h
SMALLEST_SAMPLE = 1e-3  # h, between output samples

# Members per chunk of the batch integrator: the chunk's state and work arrays (about 25
# rows of CHUNK doubles) stay in a 2 MiB L2 cache, while numpy's per-call overhead
# (about 1 µs) is spread over enough members. Measured best on the development machine.
CHUNK = 8192


class SignalingError(RuntimeError):
    """The integration produced a non-finite or negative state."""


# --------------------------------------------------------------------------------------
# Pieces: [t0, t1] cut at the switch and output times; the right-hand side is smooth on each.


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


def stop_at_bounds(N_old: np.ndarray, N_new: np.ndarray, Nmin: Array, Nmax: Array) -> None:
    """N after a step, in place on N_new: stopped at the bound of [Nmin, Nmax] the step crossed.

    f = 0 outside the range makes the right-hand side jump there, and an RK4 step across
    it overshoots the bound (up to 1.6e-4 seen with Sobol samples): the exact solution
    stops at the bound and stays there until f points back inside. A member that starts
    outside the range (f = 0 there) keeps its value. NaNs pass through (the failure check
    sees them). The backends compute the same selects: min(N_old, Nmin) <= N <= max(N_old, Nmax).
    """
    np.maximum(N_new, np.minimum(N_old, Nmin), out=N_new)
    np.minimum(N_new, np.maximum(N_old, Nmax), out=N_new)


# One RK4 step with K_i = (h/2) k_i: y + K1, y + K2, y + 2 K3 are the stage states and
# y_new = y + ((K1 + K4) + 2 (K2 + K3)) / 3 = y + h/6 (k1 + 2 k2 + 2 k3 + k4).
THIRD = 1.0 / 3.0


def _rk4_single(y, p: SignalingParams, kM: float, pieces: list[_Piece], dt: float, out: np.ndarray, member: int):
    """RK4 for one member on plain floats: the same operations, in the same order, as _rk4_block."""
    inf, third = math.inf, THIRD
    Nmin, Nmax = float(p.Nmin), float(p.Nmax)
    x1, x2, x3, x4, N = (float(v) for v in y)
    for piece in pieces:
        steps, h = _steps(piece, dt)
        s = 0.5 * h
        f = scalar_rhs(p, kM, s)
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
            # stop_at_bounds on one member
            lo = N if N < Nmin else Nmin
            hi = N if N > Nmax else Nmax
            N = N + ((k15 + k45) + (s5 + s5)) * third
            N = lo if N < lo else (hi if N > hi else N)
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
    kernel = BatchRhs(p, kM, n)
    K, ACC, W, Ys = (np.empty(Y.shape) for _ in range(4))
    inner = (float(np.max(p.Nmin)), float(np.min(p.Nmax)))  # N in here for all: no bound is crossed
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
            N = ACC[4]
            np.add(Y[4], N, out=N)
            if not (N.min() >= inner[0] and N.max() <= inner[1]):
                stop_at_bounds(Y[4], N, p.Nmin, p.Nmax)
            np.add(Y[:4], ACC[:4], out=Y[:4])
            np.copyto(Y[4], N)
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
    try:
        compiled.kernel()
    except compiled.Unavailable as err:
        return str(err)
    return None


def _rk4_compiled(Y0: np.ndarray, p: SignalingParams, kM: Array, pieces: list[_Piece], tables, dt: float,
                  out: np.ndarray, members: np.ndarray, failed: np.ndarray | None):
    """``_rk4_block`` on the compiled kernel, for every member of a timing group at once.

    On a failure without ``failed`` the failing member's piece is run again by
    ``_rk4_single`` from the state the kernel started it at: the same bits, so the same
    step fails there and raises the numpy backend's error.
    """
    n = Y0.shape[1]
    plan = [(steps, h, _a1_value(piece, p), np.zeros(2 * steps + 1) if bumps is None else np.ascontiguousarray(bumps),
             piece.t0, piece.out) for piece, (steps, h, bumps) in zip(pieces, tables)]
    fail_t = np.empty(n)
    stopped = compiled.run(compiled.coefficients(p, kM, n), p.a20, Y0, plan, out, fail_t, THIRD,
                           stop=failed is None)
    if stopped is not None:
        k, i, y = stopped
        q = p.member(i) if p.size is not None else p
        _rk4_single(y, q, float(kM[i] if np.ndim(kM) else kM), [dataclasses.replace(pieces[k], out=-1)], dt,
                    np.empty((0, 5)), int(members[i]))
        raise AssertionError(f"the C kernel failed member {members[i]} on [{pieces[k].t0}, {pieces[k].t1}] h, "
                             "numpy did not")
    if failed is not None:
        failed[members[fail_t >= 0.0]] = True


def _batch(params, kM, y0, t0, t1, out_times):
    """What an integrator of a batch starts from: kM, the output times, whether one member
    was asked for, the (5, n) initial states and room for the states at the output times."""
    kM = params.kM if kM is None else kM
    y0 = np.asarray(y0, dtype=float)
    n = batch_size(params, kM, y0)
    times = _output_times(t0, t1, out_times)
    Y0 = np.broadcast_to(y0.reshape(5, -1), (5, n or 1))
    return kM, times, n is None, Y0, np.empty((len(times), 5, n or 1))


def integrate(params: SignalingParams, protocol: Protocol, y0, t0: float, t1: float, dt: float = 0.05, *,
              out_times=None, kM: Array | None = None, backend: str = "auto", failures: str = "raise"):
    """Classical RK4 from y0 at t0 to t1 with steps of at most dt (h) landing on every switch and output time.

    Returns (times, states): the output times (default [t0, t1]) and the states there,
    shape (len(times), 5, n), or (len(times), 5) for a 1-D y0 with scalar parameters.
    kM overrides params.kM (scalar or per member).

    backend: "numpy", "c" (compiled; raises ``compiled.Unavailable`` without a C
    compiler) or "auto" (C for at least ``AUTO_MIN_MEMBERS`` members where it can be
    built, else numpy, silently). Every backend gives the same bits; with several failing
    members "raise" may name another of them on C (the first to fail in the first block
    of ``compiled.BLOCK`` members that has one).

    failures: "raise" raises SignalingError when a step gives a member a non-finite or
    negative state (the message names the step, the member and its state). "mask" returns
    (times, states, failed) instead: ``failed`` flags those members, shape (n,) (a bool
    for one member), and their states are NaN at every output time; the other members
    are the same bits as in their own runs.
    """
    positive_hours(dt, "dt", SMALLEST_DT)
    if backend not in BACKENDS:
        raise InputError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if failures not in FAILURES:
        raise InputError(f"failures must be one of {', '.join(FAILURES)}, got {failures!r}")
    kM, times, single, Y0, states = _batch(params, kM, y0, t0, t1, out_times)
    n = Y0.shape[1]
    use_c = backend == "c" or (backend == "auto" and n >= AUTO_MIN_MEMBERS and c_backend_error() is None)
    if times[0] == t0:
        states[0] = Y0
    valid = slice(1, None) if times[0] == t0 else slice(None)
    failed = np.zeros(n, dtype=bool) if failures == "mask" else None
    # a failing step overflows or subtracts infinities on its way; the failure check reports
    # it, numpy's warnings would only repeat it
    with np.errstate(over="ignore", invalid="ignore"):
        for index, p in timing_groups(params, n):
            pieces = _pieces(protocol, p, t0, t1, times)
            k = kM[index] if np.ndim(kM) else kM
            if index.size == 1 and not use_c:
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
            if use_c:
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
    p = next(timing_groups(params, params.size or 1))[1]
    return sum(_steps(piece, dt)[0] for piece in _pieces(protocol, p, t0, t1, times))


def reference(params: SignalingParams, protocol: Protocol, y0, t0: float, t1: float, *, out_times=None,
              kM: Array | None = None, rtol: float = 1e-13, atol: float = 1e-15, method: str = "DOP853"
              ) -> tuple[np.ndarray, np.ndarray]:
    """A high-accuracy solution for verification: SciPy's ``method`` at tight tolerance, restarted
    on every piece between switch and output times (smooth right-hand side on each).

    N's bounds are located as events: N stops exactly at the bound it reaches and is held
    there while f points outside, a second event (f = 0) releases it.
    Same arguments and return convention as ``integrate``; members are solved one by one.
    """
    from scipy.integrate import solve_ivp

    kM, times, single, Y0, states = _batch(params, kM, y0, t0, t1, out_times)
    for m in range(Y0.shape[1]):
        p = params.member(m) if params.size is not None else params
        f = scalar_rhs(p, float(np.ravel(kM)[m] if np.ndim(kM) else kM))
        a20, t1_, tau_h = float(p.a20), float(p.t1), float(p.tau_h)
        Nmin, Nmax = float(p.Nmin), float(p.Nmax)
        inside = 0.5 * (Nmin + Nmax)  # where f is the net balance, unclipped
        g0 = g(-t1_, tau_h)
        y = Y0[:, m].copy()
        if times[0] == t0:
            states[0, :, m] = y
        for piece in _pieces(protocol, p, t0, t1, times):
            A1 = float(_a1_value(piece, p))

            def a2(t, t_ex=piece.t_ex):
                return a20 if t_ex is None else a20 + (g((t - t_ex) - t1_, tau_h) - g0)

            def balance(t, y, A1=A1):
                return f(y[0], y[1], y[2], y[3], inside, A1, a2(t))[4]

            def fun(t, y, A1=A1, held=None):
                k = f(*y, A1, a2(t))
                return k if held is None else (*k[:4], 0.0)

            def below(t, y):
                return y[4] - Nmin

            def above(t, y):
                return y[4] - Nmax

            def release(t, y):
                return balance(t, y)

            below.terminal, below.direction = True, -1
            above.terminal, above.direction = True, 1
            release.terminal = True
            t, released = piece.t0, False
            while t < piece.t1:
                # held at a bound where f points outside, unless it was just released there
                b = balance(t, y)
                held = None if released else Nmin if (y[4] == Nmin and b < 0) else \
                    Nmax if (y[4] == Nmax and b > 0) else None
                release.direction = 1 if held == Nmin else -1
                events = [release] if held is not None else [below, above]
                sol = solve_ivp(lambda t, y, held=held: fun(t, y, held=held), (t, piece.t1), y, method=method,
                                rtol=rtol, atol=atol, events=events)
                if not sol.success:
                    raise SignalingError(f"reference integrator failed on [{t}, {piece.t1}] h: {sol.message}")
                hit = [k for k, te in enumerate(sol.t_events) if te.size]
                if not hit:
                    t, y = piece.t1, sol.y[:, -1]
                    continue
                t, y = float(sol.t_events[hit[0]][0]), sol.y_events[hit[0]][0].copy()
                released = held is not None
                if held is None:
                    y[4] = Nmin if hit[0] == 0 else Nmax  # stopped exactly there
            if piece.out >= 0:
                states[piece.out, :, m] = y
    return times, (states[:, :, 0] if single else states)


# --------------------------------------------------------------------------------------
# The original code's integration (MODEL.md §9)

METHODS = ("rk4", "rk45-original")
ORIGINAL_N0 = 1.000768  # -, the original's initial N (its configuration file), with the rest state of x1..x4
# SciPy's defaults for solve_ivp, which the original kept; its max_step was its dt, 0.05 h
ORIGINAL_RTOL = 1e-3
ORIGINAL_ATOL = 1e-6


def original(params: SignalingParams, protocol: Protocol, y0, t0: float, t1: float, dt: float = 0.05, *,
             out_times=None, kM: Array | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The original code's signaling: SciPy's RK45 at rtol 1e-3, atol 1e-6 with steps of at
    most dt (h), restarted only at session starts and ends, not at the switches of the
    delayed stimulus (t + tau_d), across which its error control steps as it can.

    Same arguments and return convention as ``integrate`` (members one by one, about
    2 s each for nine weeks: meant for uniform runs). The states at output times come
    from RK45's dense output, which leaves its steps as they are; the original read f
    at the solver step nearest to each growth time instead (at most dt/2 away).
    Differs from the converged solution by 0.27 % of ΔN over nine weeks of ``mwf``.
    """
    from scipy.integrate import solve_ivp

    positive_hours(dt, "dt", SMALLEST_DT)
    kM, times, single, Y0, states = _batch(params, kM, y0, t0, t1, out_times)
    starts, ends = protocol.starts.tolist(), protocol.ends.tolist()
    cuts = sorted({t for t in starts + ends if t0 < t < t1})
    bounds = [float(t0), *cuts, float(t1)]
    for m in range(Y0.shape[1]):
        p = params.member(m) if params.size is not None else params
        f = scalar_rhs(p, float(np.ravel(kM)[m] if np.ndim(kM) else kM))
        a10, a20, t1_, tau_h, tau_d = (float(v) for v in (p.a10, p.a20, p.t1, p.tau_h, p.tau_d))
        stimulus = [float(p.beta * i * p.Fmax) for i in protocol.intensities.tolist()]
        g0 = float(g(-t1_, tau_h))
        y = Y0[:, m].copy()
        if times[0] == t0:
            states[0, :, m] = y
        for a, b in zip(bounds[:-1], bounds[1:]):
            k = bisect.bisect_right(starts, a) - 1
            t_ex = starts[k] if k >= 0 else None  # the latest session start, the same all over [a, b)

            def fun(t, y, t_ex=t_ex):
                i = bisect.bisect_right(starts, t - tau_d) - 1
                A1 = stimulus[i] if i >= 0 and t - tau_d < ends[i] else a10
                if t_ex is None:
                    A2 = a20
                else:
                    A2 = a20 + max(float(g(min((t - t_ex) - t1_, 0.0), tau_h)) - g0, 0.0)
                return f(*y, A1, A2)

            inner = (times > a) & (times < b)
            sol = solve_ivp(fun, (a, b), y, method="RK45", rtol=ORIGINAL_RTOL, atol=ORIGINAL_ATOL, max_step=dt,
                            dense_output=bool(inner.any()))
            y = sol.y[:, -1]
            if not (sol.success and np.all(np.isfinite(y)) and np.all(y >= 0.0)):
                state = ", ".join(f"{name}={float(v):.4g}" for name, v in zip(STATES, y))
                raise SignalingError(f"RK45 from t = {a:g} h to t = {b:g} h gave member {m} a non-finite or "
                                     f"negative state ({state}): {sol.message}")
            if inner.any():
                states[inner, :, m] = sol.sol(times[inner]).T
            at_end = times == b
            states[at_end, :, m] = y
    return times, (states[:, :, 0] if single else states)


def integrator(method: str):
    """The integrator of a signaling method, with the signature of ``integrate``:
    "rk4" (``integrate``) or "rk45-original" (``original``)."""
    if method not in METHODS:
        raise InputError(f"must be one of {', '.join(METHODS)}, got {method!r}", field="signaling_method")
    return integrate if method == "rk4" else original


def start_state(method: str = "rk4") -> np.ndarray:
    """The state every run starts from: the baseline rest state (MODEL.md §1), with the
    original's N0 = 1.000768 under "rk45-original" (an offset: f does not depend on N inside
    its range, so ΔN is the same)."""
    y = rest_state()
    if integrator(method) is original:
        y[4] = ORIGINAL_N0
    return y


# --------------------------------------------------------------------------------------
# Series of one protocol


def run(params: SignalingParams, protocol: Protocol, dt: float = 0.05,
        sample_every: float = 0.5, method: str = "rk4") -> dict[str, np.ndarray]:
    """The series of one protocol from ``start_state``, sampled every ``sample_every`` h."""
    positive_hours(sample_every, "sample_every", SMALLEST_SAMPLE)
    times = np.arange(0.0, protocol.end, sample_every)
    times = np.append(times[times < protocol.end - 1e-9 * sample_every], protocol.end)
    t, y = integrator(method)(params, protocol, start_state(method), 0.0, protocol.end, dt, out_times=times)
    return {"t": t, **{name: y[:, k] for k, name in enumerate(STATES)}}


def first_day(params: SignalingParams, protocol: Protocol, dt: float = 0.05,
              every: float = 0.05, method: str = "rk4") -> dict[str, np.ndarray] | None:
    """The 24 h after the first session start, finely sampled (the figure's insets); None without sessions."""
    if not protocol.sessions:
        return None
    s0 = protocol.sessions[0].start
    stop = min(s0 + 24.0, protocol.end)
    times = s0 + np.arange(0.0, stop - s0 + 0.5 * every, every)
    t, y = integrator(method)(params, protocol, start_state(method), 0.0, protocol.end, dt,
                              out_times=times[times <= protocol.end])
    return {"t": t - s0, **{name: y[:, k] for k, name in enumerate(STATES)}}

