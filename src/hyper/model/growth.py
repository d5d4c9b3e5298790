"""Transverse (and along-fibre) volumetric growth: growth tensors, the cumulative update, feedback laws.

Kinematics (MODEL.md §4). Over a growth step the signaling model adds dN to the
myofibril population; with N = CSA/CSA0 the cross-section must grow by the area
multiplier

    ϑ = 1 + dN CSA0 / CSA,

which the incremental tensor G = √ϑ I + (1 - √ϑ) a0⊗a0 applies across the fibres only.
Increments act on the unloaded state (Goriely & Ben Amar 2007):

    Ḡ_k = A_{k-1}⁻¹ G_k A_{k-1} Ḡ_{k-1},   A_k = F_k Ḡ_k⁻¹.

The numpy kernels below work on stacks of 3×3 tensors (one per quadrature point);
`GrowthField` owns the DOLFINx function that carries Ḡ into the mechanics forms.
"""

from __future__ import annotations

import math

import numpy as np
import ufl
from scipy.special import lambertw

from hyper.model.signaling import net_balance
from hyper.model.tensors import inverse, solve

FEEDBACK_LAWS = ("hill", "linear", "none")


def feedback(x, law: str = "hill", n: float = 4.0, K: float = 1.0):
    """Synthesis factor h(CSA/CSA0): kM = kM0 h. Every law has h(1) = 1.

    hill: 2Kⁿ/(Kⁿ + xⁿ) (the paper's); linear: 3 - 2x; none: 1.
    """
    x = np.asarray(x, dtype=float)
    if law == "hill":
        return 2.0 * K**n / (K**n + x**n)
    if law == "linear":
        return 3.0 - 2.0 * x
    if law == "none":
        return np.ones_like(x)
    raise ValueError(f"unknown feedback law {law!r}; expected one of {', '.join(FEEDBACK_LAWS)}")


INCREMENTS = ("exact", "left-point")


def population_change(rule: str, y0, y1, dt: float, params, kM):
    """dN over a growth step of dt (h) from signaling states y0 to y1 ((5,) or (5, n)).

    exact: N's own change, y1[4] - y0[4]; left-point: f(y0) dt, the rate at the step's
    start times the step, as the original code grew (MODEL.md §9), with the synthesis
    rate kM the ODEs were integrated with; zero where N is held at a bound that f
    points beyond (there N does not change, and the original's f was zero too).
    """
    if rule == "exact":
        return y1[4] - y0[4]
    if rule == "left-point":
        f = net_balance(y0[2], y0[3], y0[4], params, kM)
        held = ((y0[4] <= params.Nmin) & (f < 0.0)) | ((y0[4] >= params.Nmax) & (f > 0.0))
        return np.where(held, 0.0, f)[()] * dt
    raise ValueError(f"unknown growth increment {rule!r}; expected one of {', '.join(INCREMENTS)}")


def detrained(N0, dN, dt: float, tau: float):
    """N at the end of a growth step of dt (h) from N0, with the step's dN (`population_change`)
    and a turnover of the gain with time constant tau (h): detraining, off by default.

    The paper's model keeps every gain: f = dN/dt vanishes below the thresholds and N, and
    with it the CSA, stays where training left it. With turnover the gain above the
    baseline N = 1 decays at the rate 1/τ,

        dN/dt = f(x3, x4) − (N − 1)/τ,

    at all times, sessions included: turnover is continual (Banister's impulse-response
    model of training has one time constant of decay, always on); only once training stops
    and f vanishes does it show alone, as N − 1 ∝ exp(−t/τ). It is a decay of N, not of a
    separate grown state, so the CSA follows N (ϑ = 1 + dN CSA0/CSA, with dN now < 0) and the
    feedback h(CSA/CSA0) sees the loss. f depends on x3, x4 only, never on N (but for the
    bounds Nmin, Nmax), so the signaling ODEs are integrated as they are and the term is added
    per growth step, exactly for f's share spread evenly over the step:

        N1 − 1 = (N0 − 1) e^(−Δtg/τ) + dN (1 − e^(−Δtg/τ)) τ/Δtg,

    exact where f vanishes (after training: e^(−Δtg/τ) per step) and first order in Δtg/τ
    otherwise (where in the step f's pulses fall).

    tau may be one τ per member (an array, as N0 and dN are): calibration fits it in a batch.
    """
    if np.ndim(tau) == 0:
        x = dt / tau
        kept, spread = math.exp(-x), -math.expm1(-x) / x  # (1 − e^(−x))/x without cancellation
    else:
        x = dt / np.asarray(tau, dtype=float)
        kept, spread = np.exp(-x), -np.expm1(-x) / x
    return 1.0 + (np.asarray(N0, dtype=float) - 1.0) * kept + np.asarray(dN, dtype=float) * spread


def area_multiplier(dN, csa_ratio):
    """ϑ = 1 + dN CSA0/CSA for a population change dN over one growth step."""
    return 1.0 + np.asarray(dN, dtype=float) / csa_ratio


def transverse_growth(theta, a0):
    """G = √ϑ I + (1 - √ϑ) a0⊗a0 for a stack of unit fibres a0 (..., 3)."""
    a0 = np.asarray(a0, dtype=float)
    s = np.sqrt(np.asarray(theta, dtype=float))[..., None, None]
    eye = np.broadcast_to(np.eye(3), a0.shape[:-1] + (3, 3))
    return s * eye + (1.0 - s) * a0[..., :, None] * a0[..., None, :]


def transverse_growth_ufl(theta, a0):
    """The UFL form of `transverse_growth`, for expressions and tests."""
    s = ufl.sqrt(theta)
    return s * ufl.Identity(3) + (1 - s) * ufl.outer(a0, a0)


def cumulative_update(Gbar, A, G):
    """Ḡ_new = A⁻¹ G A Ḡ: unload by A, grow by G, reload (stacks of 3×3 tensors)."""
    return inverse(A) @ (G @ A @ Gbar)


def fibre_growth(theta, fibre, a0):
    """G = ϑ_f a0⊗a0 + √ϑ (I − a0⊗a0): `transverse_growth` with the fibres lengthened by
    ϑ_f as well (``fibre``, the increment's along-fibre stretch; 1: `transverse_growth`)."""
    a0 = np.asarray(a0, dtype=float)
    s = np.sqrt(np.asarray(theta, dtype=float))[..., None, None]
    f = np.asarray(fibre, dtype=float)[..., None, None]
    eye = np.broadcast_to(np.eye(3), a0.shape[:-1] + (3, 3))
    return s * eye + (f - s) * a0[..., :, None] * a0[..., None, :]


def fibre_growth_ufl(theta, fibre, a0):
    """The UFL form of `fibre_growth`, for expressions and tests."""
    s = ufl.sqrt(theta)
    return s * ufl.Identity(3) + (fibre - s) * ufl.outer(a0, a0)


def transverse_update(Gbar, pulled, pushed, theta, fibre=None):
    """`cumulative_update` for G = `transverse_growth`(ϑ, a0), from the fibre directions
    F⁻¹a0 (``pulled``) and Fᵀa0 (``pushed``) of the last equilibrium F = A Ḡ:
    A⁻¹ G A Ḡ = Ḡ F⁻¹ G F = √ϑ Ḡ + (1 - √ϑ) (Ḡ F⁻¹a0) ⊗ (Fᵀa0), a few array
    operations per point where A⁻¹ G A Ḡ takes two inverses and three products.

    ``fibre`` (None: 1, today's transverse growth, the same operations): the increment's
    along-fibre stretch ϑ_f of G = `fibre_growth`(ϑ, ϑ_f, a0), whose update is the same with
    (ϑ_f - √ϑ) in place of (1 - √ϑ)."""
    s = np.sqrt(np.asarray(theta, dtype=float))[..., None, None]
    left = np.einsum("...ij,...j->...i", Gbar, pulled)
    along = 1.0 if fibre is None else np.asarray(fibre, dtype=float)[..., None, None]
    out = np.multiply((along - s) * left[..., :, None], pushed[..., None, :])
    out += s * Gbar
    return out


def fibre_directions(F, a0):
    """(F⁻¹a0, Fᵀa0) for stacks of deformation gradients F and fibres a0 (..., 3): what
    `transverse_update` needs of the last equilibrium."""
    return solve(F, a0), np.einsum("...ji,...j->...i", F, a0)


def fibre_directions_ufl(F, a0):
    """`fibre_directions` as one UFL vector (F⁻¹a, Fᵀa) of six components, a = a0/|a0|."""
    a = a0 / ufl.sqrt(ufl.dot(a0, a0))
    pulled, pushed = ufl.inv(F) * a, F.T * a
    return ufl.as_vector([pulled[i] for i in range(3)] + [pushed[i] for i in range(3)])




FIBER_GROWTH = ("none", "stretch")


def fibre_stretch_step(theta_f, stretch: float, dt: float, tau: float, crit: float):
    """ϑ_f after dt (h) of a uniform passive stretch λ = ``stretch`` from ϑ_f = ``theta_f``:
    the along-fibre growth (sarcomerogenesis) law of Zöllner, Abilez, Böl & Kuhl 2012
    ("Stretching skeletal muscle: chronic muscle lengthening through sarcomerogenesis",
    PLoS ONE 7:e45661), without their saturation factor,

        dϑ_f/dt = (1/τ_f) ⟨λ_e − λ_crit⟩,   λ_e = λ/ϑ_f,

    with ⟨·⟩ the Macaulay bracket: the fibres grow while their elastic stretch λ_e exceeds
    the homeostatic λ_crit, and ϑ_f approaches λ/λ_crit, where λ_e is back at λ_crit (the
    law's own bound: no ϑ_max is needed). The elastic stretch is the kinematic estimate
    λ_e = λ/ϑ_f of a muscle stretched uniformly along its fibres by λ with F = λ a0⊗a0 + …
    and growth ϑ_f a0⊗a0 + …: F_e = F G⁻¹ has the fibre stretch λ/ϑ_f, exactly for the
    cylinder with axial fibres (a uniform stretch), and the fibre-mean for a muscle. It is
    not solved as a mechanics problem: a prescribed end displacement of the cylinder gives
    that same uniform stretch, and a session's passive stretch is a stimulus, not a load
    the growth equilibrium between sessions carries.

    Integrated exactly over the step: with s = λ − λ_crit ϑ_f the law reads
    ds/dt = −(λ_crit/τ_f) s/ϑ_f = −(λ_crit²/τ_f) s/(λ − s), whose solution keeps
    s − λ ln s − λ_crit² t/τ_f constant, so that s(t) = −λ W₀(−e^(−C/λ)/λ) with
    C = s₀ − λ ln s₀ + λ_crit² dt/τ_f (W₀ Lambert's principal branch: 0 < s < λ).
    Where λ_e ≤ λ_crit (no stretch, or ϑ_f at its bound) nothing grows.

    The cylinder's ends sit on tendon springs (`hyper.fem.mechanics`): the lengthened fibres
    push on them, so a grown length is partly compressed elastically and the body bulges.
    """
    theta_f = float(theta_f)
    s0 = stretch - crit * theta_f
    if s0 <= 0.0:
        return theta_f
    C = s0 - stretch * math.log(s0) + crit**2 * dt / tau
    s = -stretch * float(lambertw(-math.exp(-C / stretch) / stretch, 0).real)
    return (stretch - s) / crit


def elastic_part(F, Gbar):
    """A = F Ḡ⁻¹ (stacks of 3×3 tensors)."""
    return F @ inverse(Gbar)


def step_times(t0: float, t1: float, dt: float) -> np.ndarray:
    """[t0, …, t1] in equal steps no longer than dt (at least one step)."""
    n = max(1, math.ceil((t1 - t0) / dt - 1e-9))
    return np.linspace(t0, t1, n + 1)
