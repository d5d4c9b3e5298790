"""`GrowthField`: the total growth Ḡ as a DOLFINx field, and the tagged-facet section."""

from __future__ import annotations

import basix
import basix.ufl
import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI

from hyper.model.growth import elastic_part, fibre_directions_ufl, transverse_update

# Where G, Ḡ and A live: at the quadrature points of the forms, or at the nodes of
# cell-wise linear (DG1) fields, which the forms interpolate (the original code).
GROWTH_FIELDS = ("quadrature", "dg1")


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

    def state(self) -> dict[str, np.ndarray]:
        """Ḡ, one row per owned cell (quadrature point, 3, 3), for a checkpoint. What the
        next increment needs besides (`directions`) follows from the mechanics' solution."""
        return {"Gbar": self.Gbar}

    def restore(self, state) -> None:
        """Take over a `state` (rows of the local cells, owned then ghost, or of the owned
        ones) with the equilibrium now in the mechanics' solution (`set`)."""
        self.set(np.array(state["Gbar"][: len(self.cells)]))

    def cell_rows(self, values: np.ndarray) -> np.ndarray:
        """A local array of Ḡ's space (the function's, or a copy) as rows of the owned
        cells: (owned cell, quadrature point, 9)."""
        return values.reshape(-1, 9)[self.dofs]

    def from_cell_rows(self, rows: np.ndarray) -> np.ndarray:
        """The local array of Ḡ's space (ghosts filled) with the values of `cell_rows`
        (rows of the local or the owned cells)."""
        g = fem.Function(self.space)
        g.x.array.reshape(-1, 9)[self.dofs.ravel()] = rows[: len(self.cells)].reshape(-1, 9)
        g.x.scatter_forward()
        return g.x.array.copy()

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

    def grow(self, theta, fibre: float | None = None) -> None:
        """Apply one increment with area multiplier ϑ (scalar, or one value per owned cell)
        and, where ``fibre`` is given, the along-fibre stretch ϑ_f of the increment (a scalar:
        G = ϑ_f a0⊗a0 + √ϑ (I − a0⊗a0), `hyper.model.growth.fibre_growth`)."""
        theta = np.asarray(theta, dtype=float)
        if theta.ndim == 1:
            theta = theta[:, None]
        self._previous = self.Gbar
        self.Gbar = transverse_update(self.Gbar, *self.directions, theta, fibre)
        self._write(self.Gbar)

    def revert(self) -> None:
        """Undo the last `grow` (the solve for it failed)."""
        self.Gbar = self._previous
        self._write(self.Gbar)

    def accept(self) -> None:
        """Take the new equilibrium: its fibre directions at every quadrature point."""
        self.directions = self._fibre_directions()
        self._previous = self.Gbar

    def mean_fibre_stretch(self) -> float:
        """a0·Ḡ a0 averaged over the points of every cell and then the cells (collective):
        the fascicle length change the growth tensor carries (1: none), ϑ_f where the
        fibres grew uniformly."""
        stretch = np.einsum("...i,...ij,...j->...", self.a0, self.Gbar, self.a0) @ self.weights / self.weights.sum()
        comm = self.mesh.comm
        return comm.allreduce(float(stretch.sum()), op=MPI.SUM) / comm.allreduce(len(self.cells), op=MPI.SUM)

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
        return self._comm.allreduce(fem.assemble_scalar(form), op=MPI.SUM)

    def area(self) -> float:
        return self._assemble(self._area)
