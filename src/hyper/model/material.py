"""The Röhrle transversely isotropic muscle law (MODEL.md §3) as pure UFL functions.

Second Piola–Kirchhoff stress, activation α ∈ [0, 1], fibre stretch λ = √(a0·C a0):

    S = c1 I + c2 (I1 I - C) - p J C⁻¹
        + (σpass / I4) fpass(λ/λ0) a0⊗a0 + α (σact / I4) fact(λ/λ0) a0⊗a0

a0 is the unit reference fibre direction. With F = I the isotropic part is
(c1 + 2 c2) I, so the stress-free reference state carries the pressure
p = c1 + 2 c2 (`reference_pressure`), not zero.
"""

from __future__ import annotations

import dataclasses
import math

import ufl

from hyper.core.params import InputError, finite, read_toml, replace_from_mapping, shown


@dataclasses.dataclass(frozen=True)
class MaterialParams:
    """Table 1 of the paper (Röhrle et al. 2012). A TOML file (`load`) or a study's
    [material] table overrides fields by name."""

    c1: float = 1.0e4  # Pa, Mooney–Rivlin
    c2: float = 1.0e4  # Pa, Mooney–Rivlin
    sigma_pass: float = 3.0e5  # Pa, passive fibre stress scale (sigma_pass_ff)
    sigma_act: float = 3.0e5  # Pa, maximal active fibre stress (sigma_act_ff)
    lambda0: float = 1.4  # -, optimal fibre stretch
    g1: float = 0.05  # -, passive force-length amplitude
    g2: float = 6.6  # -, passive force-length exponent
    k_tendon: float = 1.0e5  # Pa/m, tendon spring stiffness on the ends

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not finite(value):
                raise InputError(f"expected a finite number, got {shown(value)}", field=f.name)
        for name in ("c1", "lambda0", "g2", "k_tendon"):
            if getattr(self, name) <= 0:
                raise InputError(f"expected a number > 0, got {getattr(self, name)!r}", field=name)
        for name in ("c2", "sigma_pass", "sigma_act", "g1"):
            if getattr(self, name) < 0:
                raise InputError(f"expected a number >= 0, got {getattr(self, name)!r}", field=name)


def from_mapping(values, source: str) -> MaterialParams:
    """Table 1 with the fields named in ``values`` replaced; errors start with ``source``."""
    return replace_from_mapping(MaterialParams(), values, source)


def load(path) -> MaterialParams:
    """Table 1 overridden by a TOML file whose keys are `MaterialParams` fields (--material)."""
    return from_mapping(read_toml(path), str(path))


def reference_pressure(params: MaterialParams) -> float:
    """The pressure of the stress-free state F = I (Pa): c1 + 2 c2."""
    return params.c1 + 2.0 * params.c2


def f_act(l):
    """Active force–length relation fact(ℓ), ℓ = λ/λ0 (piecewise quadratic, zero outside 0.4–1.6)."""
    return ufl.conditional(
        ufl.le(l, 0.4),
        0.0,
        ufl.conditional(
            ufl.le(l, 0.6),
            9.0 * (l - 0.4) ** 2,
            ufl.conditional(
                ufl.le(l, 1.4),
                1.0 - 4.0 * (1.0 - l) ** 2,
                ufl.conditional(ufl.le(l, 1.6), 9.0 * (l - 1.6) ** 2, 0.0),
            ),
        ),
    )


def f_pass(l, g1: float, g2: float):
    """Passive force–length relation fpass(ℓ): zero in compression, exponential, then linear past 1.4."""
    e = math.exp(0.4 * g2)
    return ufl.conditional(
        ufl.le(l, 1.0),
        0.0,
        ufl.conditional(
            ufl.le(l, 1.4),
            g1 * (ufl.exp(g2 * (l - 1.0)) - 1.0),
            g1 * g2 * e * l + g1 * ((1.0 - 1.4 * g2) * e - 1.0),
        ),
    )


def fibre_stretch(F, a0):
    """λ = √(a0·C a0)."""
    return ufl.sqrt(ufl.dot(a0, F.T * F * a0))


def second_piola(F, p, a0, alpha, params: MaterialParams):
    """S of MODEL.md §3 for deformation gradient F, pressure p, unit fibre a0, activation α."""
    dim = F.ufl_shape[0]
    I = ufl.Identity(dim)
    C = F.T * F
    I1 = ufl.tr(C)
    I4 = ufl.dot(a0, C * a0)
    ell = ufl.sqrt(I4) / params.lambda0
    fibre = params.sigma_pass * f_pass(ell, params.g1, params.g2) + alpha * params.sigma_act * f_act(ell)
    return (
        params.c1 * I
        + params.c2 * (I1 * I - C)
        - p * ufl.det(F) * ufl.inv(C)
        + fibre / I4 * ufl.outer(a0, a0)
    )


def first_piola(F, p, a0, alpha, params: MaterialParams):
    """P = F S."""
    return F * second_piola(F, p, a0, alpha, params)
