"""The growth of a uniformly signaling muscle without a mesh: the signaling ODEs with the CSA feedback.

Why no mechanics is needed. With uniform parameters every cell has the same ϑ, and a growth
step multiplies the section by ϑ = 1 + dN CSA0/CSA (MODEL.md §4). Where that growth is
compatible (the cylinder) the section grows exactly by ϑ, so CSA/CSA0 gains dN at every step
and stays equal to N. On the fusiform idealized muscle the fibres fan out and the mid-section
grows by a nearly constant fraction of the growth, CSA/CSA0 - 1 = ρ (N - 1) with ρ the
``SECTION_FACTOR`` below; the volume follows N.

The feedback is applied the way `hyper.fem.coupled.CoupledModel.run` applies it: each period (a
session, a rest) is integrated with the kM set at its start, kM0 h(CSA/CSA0) from the section
at the end of the period before. The growth step only decides where the coupled model
measures; here the states can be read anywhere.

Batches. Every parameter may be per member (`signaling.SignalingParams`); protocols that
share their session times and differ only in intensity are one batch too: a1 = β I Fmax
during a session, so a member's intensity becomes its β on a protocol of intensity 1
(`intensity_batch`), the same product in the same order (β I) Fmax, the same bits.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from hyper.core.params import InputError, positive_hours
from hyper.model import growth, signaling
from hyper.model.protocols import Protocol, Session

# (CSA/CSA0 - 1) / (N - 1) at 9 weeks of coupled runs with uniform parameters (Δtg = 168 h,
# RK4 0.05 h, hill feedback), `python -m hyper.bench calibrate` (results/bench/calibrate.json,
# surrogate_check): 0.99710 (mwf), 0.99716 (every3days), 0.99726 (weekly) on the idealized
# muscle. 1 on the cylinder by construction (compatible growth).
SECTION_FACTOR = {"cylinder": 1.0, "idealized": 0.99712}
# The surrogate's error against coupled idealized runs with the same steps: the largest
# |CSA - CSA_coupled| over a run, as a fraction of the run's 9-week growth CSA_coupled - 1.
# Measured at the table's kM 5.0e-5 (mwf), 6.5e-5 (every3days), 1.3e-4 (weekly) (bench
# calibrate: surrogate_check), and 1.3e-4 at the DeFreitas optimum kM = 0.0145 1/h (hyper
# calibrate's check): ρ drifts a little with the protocol. Rounded up; --accuracy weighs it.
SURROGATE_ERROR = 2e-4


def section_factor(geometry: str) -> float:
    """ρ of a geometry; InputError for one the surrogate has not been measured on."""
    if geometry not in SECTION_FACTOR:
        raise InputError(f"the ODE growth model has no measured section factor for geometry {geometry!r} "
                         f"(known: {', '.join(SECTION_FACTOR)}); fit on the coupled model instead")
    return SECTION_FACTOR[geometry]


@dataclass(frozen=True)
class Growth:
    """The growth at the output times: arrays (times, members), or (times,) for one member."""

    t: np.ndarray  # h
    csa_ratio: np.ndarray  # CSA/CSA0
    N: np.ndarray  # the myofibril population, also V/V0
    kM: np.ndarray  # 1/h, the synthesis rate after the feedback at each time (as coupled reports it)


def grow(params: signaling.SignalingParams, protocol: Protocol, out_times, *, signaling_dt: float = 0.05,
         feedback: str = "hill", factor: float = 1.0, hill_n=4.0, backend: str = "auto",
         failures: str = "raise", detraining: float | None = None, growth_dt: float = 168.0) -> Growth:
    """CSA/CSA0, N and kM at ``out_times`` (sorted, within [0, protocol.end]) from the
    baseline rest state, with kM = kM0 h(CSA/CSA0) updated at every period end.

    ``hill_n``: the Hill feedback's exponent n (float or per member; the paper's 4).
    ``backend`` and ``failures`` go to `signaling.integrate`; with ``failures="mask"`` a
    member whose trajectory fails is NaN from then on, the others are their own bits.

    ``detraining`` τ (h, or one per member; None: none, the paper's model): the gain's turnover of
    `growth.detrained`, applied as the coupled model applies it, per growth step of at most
    ``growth_dt`` (its `growth.step_times`, with the output times among the steps)."""
    if feedback not in growth.FEEDBACK_LAWS:
        raise InputError(f"feedback must be one of {', '.join(growth.FEEDBACK_LAWS)}, got {feedback!r}")
    times = np.asarray(out_times, dtype=float)
    if times.ndim != 1 or np.any(np.diff(times) <= 0) or times[0] < 0 or times[-1] > protocol.end:
        raise InputError(f"output times must increase strictly within [0, {protocol.end:g}] h")
    if detraining is not None:
        for tau in np.ravel(detraining):  # one τ, or one per member
            positive_hours(float(tau), "detraining")
        positive_hours(growth_dt, "growth_dt", signaling.SMALLEST_DT)
    n = params.size
    y = signaling.rest_state() if n is None else np.repeat(signaling.rest_state()[:, None], n, axis=1)
    kM0 = np.asarray(params.kM, dtype=float)
    kM = kM0
    N = np.empty((len(times),) + (() if n is None else (n,)))
    km = np.empty_like(N)
    N[times == 0.0] = 1.0
    km[times == 0.0] = kM0
    for t0, t1, _ in protocol.periods():
        inside = (times > t0) & (times <= t1)
        sample = np.union1d(times[inside], [t0, t1])
        if detraining is not None:
            # the growth steps, but for those the round-off of their sum puts beside an output time
            steps = growth.step_times(t0, t1, growth_dt)
            apart = np.abs(steps[:, None] - sample[None, :]).min(axis=1) > 1e-9 * max(1.0, t1)
            sample = np.union1d(sample, steps[apart])
        # masked failures come back NaN: a failed member stays NaN (and masked) in later periods
        ys = signaling.integrate(params, protocol, y, t0, t1, signaling_dt, out_times=sample, kM=kM,
                                 backend=backend, failures=failures)[1]
        if detraining is not None:  # the turnover, step by step from the N the last period left
            ys = ys.copy()
            raw = ys[:, 4].copy()
            for k in range(1, len(sample)):
                ys[k, 4] = growth.detrained(ys[k - 1, 4], raw[k] - raw[k - 1], sample[k] - sample[k - 1], detraining)
        N[inside] = ys[np.searchsorted(sample, times[inside]), 4]
        km[inside] = kM
        y = ys[-1]
        kM = kM0 * growth.feedback(1.0 + factor * (y[4] - 1.0), feedback, n=hill_n)
        km[times == t1] = kM
    return Growth(times, 1.0 + factor * (N - 1.0), N, km)


def intensity_batch(protocol: Protocol, intensities, params: signaling.SignalingParams | None = None
                    ) -> tuple[Protocol, signaling.SignalingParams]:
    """One batch for ``protocol``'s sessions at each of ``intensities``: the protocol at
    intensity 1 and the parameters with β I per member (every session of a member at its I)."""
    params = signaling.SignalingParams() if params is None else params
    intensities = np.asarray(intensities, dtype=float)
    if intensities.ndim != 1 or np.any((intensities < 0) | (intensities > 1)):
        raise InputError("intensities must be a 1-D array of values in [0, 1]")
    unit = Protocol(tuple(Session(s.start, s.duration, 1.0) for s in protocol.sessions), protocol.end,
                    protocol.name)
    return unit, dataclasses.replace(params, beta=np.asarray(params.beta) * intensities)
