"""3×3 tensor algebra on stacks (one tensor per quadrature point or vertex), by the adjugate."""

from __future__ import annotations

import numpy as np


def solve(M, v):
    """M⁻¹v for stacks of 3×3 tensors and 3-vectors, by the adjugate (`inverse`), with
    no inverse formed: half the work of inverse(M) @ v."""
    a, b, c = M[..., 0, 0], M[..., 0, 1], M[..., 0, 2]
    d, e, f = M[..., 1, 0], M[..., 1, 1], M[..., 1, 2]
    g, h, i = M[..., 2, 0], M[..., 2, 1], M[..., 2, 2]
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    c0, c1, c2 = e * i - f * h, f * g - d * i, d * h - e * g  # the first column of the adjugate
    out = np.empty(np.shape(v))
    out[..., 0] = c0 * x + (c * h - b * i) * y + (b * f - c * e) * z
    out[..., 1] = c1 * x + (a * i - c * g) * y + (c * d - a * f) * z
    out[..., 2] = c2 * x + (b * g - a * h) * y + (a * e - b * d) * z
    out /= (a * c0 + b * c1 + c * c2)[..., None]
    return out


def inverse(M):
    """M⁻¹ of a stack of 3×3 tensors by the adjugate: for the well-conditioned tensors
    of growth (det near 1) as exact as LAPACK's, and several times faster on stacks."""
    a, b, c = M[..., 0, 0], M[..., 0, 1], M[..., 0, 2]
    d, e, f = M[..., 1, 0], M[..., 1, 1], M[..., 1, 2]
    g, h, i = M[..., 2, 0], M[..., 2, 1], M[..., 2, 2]
    out = np.empty(np.shape(M))
    out[..., 0, 0], out[..., 0, 1], out[..., 0, 2] = e * i - f * h, c * h - b * i, b * f - c * e
    out[..., 1, 0], out[..., 1, 1], out[..., 1, 2] = f * g - d * i, a * i - c * g, c * d - a * f
    out[..., 2, 0], out[..., 2, 1], out[..., 2, 2] = d * h - e * g, b * g - a * h, a * e - b * d
    out /= (a * out[..., 0, 0] + b * out[..., 1, 0] + c * out[..., 2, 0])[..., None, None]
    return out
