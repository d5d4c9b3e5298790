"""Transverse volumetric growth: growth tensors, the cumulative update, feedback laws.

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

import basix
import basix.ufl
import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
import numpy as np
import ufl
from dolfinx import fem

from hyper.signaling import net_balance

FEEDBACK_LAWS = ("hill", "linear", "none")
# Where G, Ḡ and A live: at the quadrature points of the forms, or at the nodes of
# cell-wise linear (DG1) fields, which the forms interpolate (the original code).
GROWTH_FIELDS = ("quadrature", "dg1")


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


def transverse_update(Gbar, pulled, pushed, theta):
    """`cumulative_update` for G = `transverse_growth`(ϑ, a0), from the fibre directions
    F⁻¹a0 (``pulled``) and Fᵀa0 (``pushed``) of the last equilibrium F = A Ḡ:
    A⁻¹ G A Ḡ = Ḡ F⁻¹ G F = √ϑ Ḡ + (1 - √ϑ) (Ḡ F⁻¹a0) ⊗ (Fᵀa0), a few array
    operations per point where A⁻¹ G A Ḡ takes two inverses and three products."""
    s = np.sqrt(np.asarray(theta, dtype=float))[..., None, None]
    left = np.einsum("...ij,...j->...i", Gbar, pulled)
    out = np.multiply((1.0 - s) * left[..., :, None], pushed[..., None, :])
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


def elastic_part(F, Gbar):
    """A = F Ḡ⁻¹ (stacks of 3×3 tensors)."""
    return F @ inverse(Gbar)


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


class GrowthField:
    """Total growth Ḡ at the quadrature points of a mesh, and what its next increment
    needs of the last equilibrium.

    Ḡ lives in a DOLFINx quadrature space of the same degree as the forms, so the
    mechanics sees exactly the tensors computed here. The elastic tensor A = F Ḡ⁻¹ of
    MODEL.md §4 enters an increment only through A⁻¹ G A Ḡ = Ḡ F⁻¹ G F, so the field
    keeps the fibre directions F⁻¹a0 and Fᵀa0 of the last equilibrium instead of A: they
    follow from the solution (`set` reads them from it), and an increment costs no
    inverse of Ḡ or A. Arrays are kept for the owned cells, laid out (owned cell,
    quadrature point, 3, 3) and (…, 3); ghost values of Ḡ come from a scatter.

    ``fields="dg1"`` (`GROWTH_FIELDS`): the same tensors at the four vertices of each
    cell instead, Ḡ a cell-wise linear (DG1) function that the forms interpolate (the
    original code's choice, MODEL.md §9); "quadrature point" then reads "vertex".
    """

    def __init__(self, mesh, a0, degree: int, fields: str = "quadrature"):
        if fields not in GROWTH_FIELDS:
            raise ValueError(f"fields must be one of {', '.join(GROWTH_FIELDS)}, got {fields!r}")
        self.mesh = mesh
        cell = mesh.basix_cell()
        if fields == "dg1":
            element = basix.ufl.element("DG", cell, 1, shape=(3, 3))
            self.space = fem.functionspace(mesh, element)
            self.points = self.space.element.interpolation_points
            self.weights = np.full(self.points.shape[0], 1.0 / self.points.shape[0])
        else:
            element = basix.ufl.quadrature_element(cell, value_shape=(3, 3), degree=degree)
            self.space = fem.functionspace(mesh, element)
            self.points, self.weights = basix.make_quadrature(cell, degree)
        self.cells = np.arange(mesh.topology.index_map(mesh.topology.dim).size_local, dtype=np.int32)
        self.dofs = self.space.dofmap.list[self.cells]  # (owned cell, quadrature point)
        nq = self.points.shape[0]
        if self.dofs.shape[1] != nq:
            raise RuntimeError("quadrature space and rule disagree on the number of points")

        fib = fem.Expression(a0, self.points).eval(mesh, self.cells).reshape(-1, nq, 3)
        self.a0 = fib / np.linalg.norm(fib, axis=-1, keepdims=True)
        eye = np.broadcast_to(np.eye(3), (len(self.cells), nq, 3, 3))
        self.Gbar = eye.copy()
        # F = I: both directions are a0
        self.directions = (self.a0, self.a0)
        self._previous = self.Gbar
        self._cell_det = (None, None)  # (the Ḡ it is of, det Ḡ per cell)
        self.function = fem.Function(self.space, name="Gbar")
        # the owned points numbered in order (quadrature spaces): a copy instead of a scatter by index
        self._in_order = bool(np.array_equal(self.dofs.ravel(), np.arange(self.dofs.size)))
        self._write(self.Gbar)
        self._a0_ufl, self._F_ufl = a0, None  # the fibres, and F of `set_deformation`
        self._directions_expr = self._F_expr = None

    def _write(self, Gbar) -> None:
        values = self.function.x.array.reshape(-1, 9)
        if self._in_order:
            values[: self.dofs.size] = Gbar.reshape(-1, 9)
        else:
            values[self.dofs.ravel()] = Gbar.reshape(-1, 9)
        self.function.x.scatter_forward()

    def set(self, Gbar) -> None:
        """Take over Ḡ (a saved state, or the one before a failed step) with the
        equilibrium now in the mechanics' solution."""
        self.Gbar = Gbar
        self._previous = Gbar
        self._write(Gbar)
        self.directions = self._fibre_directions()

    def set_deformation(self, F) -> None:
        """Give the UFL deformation gradient whose values the next increment reads after each solve."""
        self._F_ufl = F
        # in the compiled kernel: on BFLH_VHF_Left half the time of evaluating F, then F⁻¹a0 and Fᵀa0 in numpy
        self._directions_expr = fem.Expression(fibre_directions_ufl(F, self._a0_ufl), self.points)

    def _fibre_directions(self) -> tuple[np.ndarray, np.ndarray]:
        nq = self.points.shape[0]
        both = self._directions_expr.eval(self.mesh, self.cells).reshape(-1, nq, 6)
        return both[..., :3], both[..., 3:]

    def elastic_tensor(self) -> np.ndarray:
        """A = F Ḡ⁻¹ at every point, from the mechanics' current solution."""
        if self._F_expr is None:
            self._F_expr = fem.Expression(self._F_ufl, self.points)
        nq = self.points.shape[0]
        return elastic_part(self._F_expr.eval(self.mesh, self.cells).reshape(-1, nq, 3, 3), self.Gbar)

    def grow(self, theta) -> None:
        """Apply one increment with area multiplier ϑ (scalar, or one value per owned cell)."""
        theta = np.asarray(theta, dtype=float)
        if theta.ndim == 1:
            theta = theta[:, None]
        self._previous = self.Gbar
        self.Gbar = transverse_update(self.Gbar, *self.directions, theta)
        self._write(self.Gbar)

    def revert(self) -> None:
        """Undo the last `grow` (the solve for it failed)."""
        self.Gbar = self._previous
        self._write(self.Gbar)

    def accept(self) -> None:
        """Take the new equilibrium: its fibre directions at every quadrature point."""
        self.directions = self._fibre_directions()
        self._previous = self.Gbar

    def cell_det(self) -> np.ndarray:
        """det Ḡ averaged over each owned cell (the volume growth per cell; with DG1
        fields, the mean of its vertex values). Read-only: computed once per Ḡ (which is
        replaced, never changed in place), as the Newton solve and the snapshot both ask."""
        G = self.Gbar
        if self._cell_det[0] is not G:
            det = (G[..., 0, 0] * (G[..., 1, 1] * G[..., 2, 2] - G[..., 1, 2] * G[..., 2, 1])
                   - G[..., 0, 1] * (G[..., 1, 0] * G[..., 2, 2] - G[..., 1, 2] * G[..., 2, 0])
                   + G[..., 0, 2] * (G[..., 1, 0] * G[..., 2, 1] - G[..., 1, 1] * G[..., 2, 0]))
            det = det @ self.weights / self.weights.sum()
            det.flags.writeable = False
            self._cell_det = (G, det)
        return self._cell_det[1]


def nanson_area_density(F, N):
    """J |F⁻ᵀ N|: the deformed area per reference area of a surface with normal N."""
    return ufl.det(F) * ufl.sqrt(ufl.dot(ufl.inv(F).T * N, ufl.inv(F).T * N))


class FacetSection:
    """A reference cross-section given as tagged interior facets (idealized, cylinder).

    The deformed area is integrated by Nanson's formula on the facets' '+' side; the
    deformation gradient is cellwise polynomial, and either side gives the same area
    to discretization error, so one side is enough.
    """

    def __init__(self, geometry, F):
        comm = geometry.mesh.comm
        n = ufl.FacetNormal(geometry.mesh)
        dS = geometry.dS(geometry.midsection)
        self._comm = comm
        self._area0 = fem.form(1.0 * dS)
        self._area = fem.form(nanson_area_density(F("+"), n("+")) * dS)
        self.area0 = self._assemble(self._area0)

    def _assemble(self, form) -> float:
        from mpi4py import MPI

        return self._comm.allreduce(fem.assemble_scalar(form), op=MPI.SUM)

    def area(self) -> float:
        return self._assemble(self._area)
