"""Cross-sections of tetrahedral meshes by a plane: exact cut polygons and Nanson's area.

For anatomical meshes the reference cross-section is the plane through the mean of the
mesh vertices, normal to their first principal axis (MODEL.md §4). It cuts through
cells, so the reference area is the exact area of the polygons plane ∩ tetrahedron, and
the deformed area is Nanson's CSA = ∫ J |F⁻ᵀ N| dA over those polygons, with F = I + ∇u
evaluated exactly at the points of a triangle quadrature rule.

The numpy kernels (``principal_plane``, ``cut_triangles``, ``triangle_rule``) know
nothing of DOLFINx; ``CutSection`` ties them to a mesh and a displacement.
"""

from __future__ import annotations

import basix
import dolfinx
import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np
from mpi4py import MPI

# Regional CSA (MRI studies measure at fractions of a muscle's length): K sections at
# j/(K+1) of the length along the first principal axis, j = 1 … K.
SECTIONS = 9  # 10 %, 20 %, …, 90 %
MAX_SECTIONS = 99  # 1 % apart: finer than any MRI slice spacing of a muscle


def section_fractions(count: int) -> np.ndarray:
    """The ``count`` fractions j/(count+1) of the length, j = 1 … count (9: 0.1 … 0.9)."""
    return np.arange(1, count + 1) / (count + 1)


def axial_planes(points, fractions) -> tuple[np.ndarray, np.ndarray]:
    """(origins (K, 3), unit normal): planes normal to the first principal axis of
    ``points`` (`principal_plane`) at ``fractions`` of their extent along it, from the
    end whose points lie lowest on the normal (its largest component is positive)."""
    origin, normal = principal_plane(points)
    d = signed_distance(np.asarray(points, dtype=float), origin, normal)
    lo, hi = float(d.min()), float(d.max())
    offsets = lo + np.asarray(fractions, dtype=float) * (hi - lo)
    return origin + offsets[:, None] * normal, normal


def principal_plane(points) -> tuple[np.ndarray, np.ndarray]:
    """(origin, unit normal): the plane through the mean of ``points`` (n, 3), normal to
    their first principal axis (largest variance).

    Pass every vertex once. The points are put in lexicographic order first, so the
    result is bitwise the same however they were gathered (any number of ranks). The
    normal's largest component (in absolute value; the first of equals) is positive.
    """
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 4:
        raise ValueError(f"expected at least 4 points of shape (n, 3), got {pts.shape}")
    pts = pts[np.lexsort(pts.T[::-1])]
    origin = pts.mean(axis=0)
    centred = pts - origin
    return origin, first_axis(centred.T @ centred / len(pts))


def first_axis(covariance) -> np.ndarray:
    """The unit eigenvector of the largest eigenvalue of a 3x3 covariance, its largest
    component positive; ValueError where that eigenvalue is not unique."""
    variance, axes = np.linalg.eigh(covariance)
    if variance[2] - variance[1] <= 1e-12 * variance[2]:
        raise ValueError(f"no unique first principal axis (variances {variance})")
    normal = axes[:, 2]
    if normal[np.argmax(np.abs(normal))] < 0:
        normal = -normal
    return normal


def solid_moments(tet_coords, *, signed: bool = False) -> tuple[float, np.ndarray, np.ndarray]:
    """(V, ∫x dV (3,), ∫x xᵀ dV (3, 3)) of the solid filled by tetrahedra (n, 4, 3), exactly.

    A tetrahedron with corners v_i has ∫x dV = V Σv_i / 4 and ∫x xᵀ dV =
    V (Σ v_i v_iᵀ + s sᵀ) / 20 with s = Σ v_i. ``signed``: each cell counts with its
    signed volume (cones from a point to an oriented closed surface fill its inside);
    otherwise with its absolute volume (a mesh, whatever its cells' orientation).
    """
    x = np.asarray(tet_coords, dtype=float)
    volume = np.linalg.det(x[:, 1:] - x[:, :1]) / 6.0
    if not signed:
        volume = np.abs(volume)
    s = x.sum(axis=1)
    first = volume @ s / 4.0
    second = (np.einsum("n,nia,nib->ab", volume, x, x) + np.einsum("n,na,nb->ab", volume, s, s)) / 20.0
    return float(volume.sum()), first, second


def inertia_plane(volume: float, first, second) -> tuple[np.ndarray, np.ndarray]:
    """(origin, unit normal): the plane through the centroid of a solid, normal to its
    first principal axis (largest second moment of the volume about the centroid), from
    ``solid_moments``' three numbers. The normal's largest component is positive.

    Unlike ``principal_plane`` this is a property of the shape, not of where a mesher put
    its vertices: any mesh filling the same solid gives the same plane.
    """
    centroid = np.asarray(first, dtype=float) / volume
    covariance = np.asarray(second, dtype=float) / volume - np.outer(centroid, centroid)
    return centroid, first_axis(covariance)


def solid_plane(mesh) -> tuple[np.ndarray, np.ndarray]:
    """``inertia_plane`` of a mesh's cells (each owned cell once); collective."""
    n_owned = mesh.topology.index_map(mesh.topology.dim).size_local
    moments = solid_moments(mesh.geometry.x[mesh.geometry.dofmaps[0][:n_owned]])
    volume, first, second = (mesh.comm.allreduce(m, op=MPI.SUM) for m in moments)
    return inertia_plane(volume, first, second)


def surface_solid_moments(points, triangles) -> tuple[float, np.ndarray, np.ndarray]:
    """``solid_moments`` of the inside of a closed, outward-oriented triangle surface:
    signed cones from the points' mean (near the solid, so little cancels) to each triangle."""
    pts = np.asarray(points, dtype=float)
    apex = pts.mean(axis=0)
    corners = pts[np.asarray(triangles)] - apex
    cones = np.concatenate([np.zeros((len(corners), 1, 3)), corners], axis=1)
    volume, first, second = solid_moments(cones, signed=True)
    # Back from the apex to the coordinates' origin.
    second = second + np.outer(first, apex) + np.outer(apex, first) + volume * np.outer(apex, apex)
    return volume, first + volume * apex, second


def surface_cut_area(points, triangles, origin, normal) -> float:
    """The area enclosed by the cut of a closed, consistently oriented triangle surface by a plane.

    Each triangle crossing the plane gives a segment from the point where its boundary
    (in the triangle's order) goes up through the plane to the point where it goes down;
    the segments form the oriented loops of the cut, whose enclosed area is
    |½ Σ (a × b)·n| (holes count negative). Above is d > 0, as in ``cut_triangles``.
    """
    pts = np.asarray(points, dtype=float)
    tri = np.asarray(triangles)
    normal = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    d = signed_distance(pts, np.asarray(origin, dtype=float), normal)
    above = d[tri] > 0
    start, end = tri, np.roll(tri, -1, axis=1)
    up = ~above & np.roll(above, -1, axis=1)  # edge i from below to above
    down = above & ~np.roll(above, -1, axis=1)
    crossing = up.any(axis=1)

    def point(mask):
        """The cut point on each crossing triangle's masked edge, computed from its above end
        so that the two triangles sharing the edge get the same point."""
        i = np.argmax(mask[crossing], axis=1)
        rows = np.flatnonzero(crossing)
        a, b = start[rows, i], end[rows, i]
        hi, lo = np.where(d[a] > 0, a, b), np.where(d[a] > 0, b, a)
        t = d[hi] / (d[hi] - d[lo])
        return pts[hi] + t[:, None] * (pts[lo] - pts[hi])

    a, b = point(up), point(down)
    return float(abs(0.5 * (np.cross(a, b) @ normal).sum()))


def signed_distance(x, origin, normal) -> np.ndarray:
    """(x - origin)·normal over the last axis of ``x``.

    Written elementwise rather than as a matrix product so that a vertex shared by
    several cells gets bitwise the same distance in each: the side a vertex lying on the
    plane is put on must not depend on the cell it is seen from.
    """
    return (
        (x[..., 0] - origin[0]) * normal[0]
        + (x[..., 1] - origin[1]) * normal[1]
        + (x[..., 2] - origin[2]) * normal[2]
    )


def cut_triangles(tet_coords, origin, normal) -> tuple[np.ndarray, np.ndarray]:
    """The polygons plane ∩ tetrahedron, as triangles: (cell_index (m,), triangles (m, 3, 3)).

    ``tet_coords`` (n, 4, 3) are the cells' vertex coordinates. A vertex is above the
    plane if its signed distance is > 0, otherwise below (on the plane counts as below).
    A cell is cut when it has vertices on both sides; a triangle cut (1 or 3 vertices
    above) gives one triangle, a quadrilateral (2 above) two. With this convention a
    face lying in the plane belongs to the one cell above it only, and cells merely
    touching the plane give zero-area triangles, so nothing is counted twice. Cut
    points on an edge are computed from its above end, so two cells sharing the edge
    get the same point and their polygons tile the section exactly.
    """
    x = np.asarray(tet_coords, dtype=float)
    origin = np.asarray(origin, dtype=float)
    normal = np.asarray(normal, dtype=float)
    d = signed_distance(x, origin, normal)
    above = d > 0
    n_above = above.sum(axis=1)
    order = np.argsort(~above, axis=1, kind="stable")  # vertices above first
    xs = np.take_along_axis(x, order[..., None], axis=1)
    ds = np.take_along_axis(d, order, axis=1)

    def point(cells, a, b):
        """The cut point on the edge from vertex a (above) to vertex b (below)."""
        da, db = ds[cells, a], ds[cells, b]
        t = da / (da - db)
        return xs[cells, a] + t[:, None] * (xs[cells, b] - xs[cells, a])

    one = np.flatnonzero(n_above == 1)
    three = np.flatnonzero(n_above == 3)
    two = np.flatnonzero(n_above == 2)
    # The quadrilateral's corners in cyclic order: consecutive ones share a face.
    q = [point(two, 0, 2), point(two, 0, 3), point(two, 1, 3), point(two, 1, 2)]
    cells = np.concatenate([one, three, two, two])
    triangles = np.concatenate(
        [
            np.stack([point(one, 0, 1), point(one, 0, 2), point(one, 0, 3)], axis=1),
            np.stack([point(three, 0, 3), point(three, 1, 3), point(three, 2, 3)], axis=1),
            np.stack([q[0], q[1], q[2]], axis=1),
            np.stack([q[0], q[2], q[3]], axis=1),
        ]
    ).reshape(-1, 3, 3)
    by_cell = np.argsort(cells, kind="stable")
    return cells[by_cell], triangles[by_cell]


def triangle_areas(triangles) -> np.ndarray:
    t = np.asarray(triangles, dtype=float)
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)


def triangle_rule(degree: int) -> tuple[np.ndarray, np.ndarray]:
    """A symmetric rule on triangles, exact for polynomials of ``degree``.

    Returns barycentric coordinates (q, 3) and weights (q,) summing to 1, so that
    ∫_T f dA ≈ area(T) Σ_q w_q f(Σ_i λ_qi X_i) for a triangle with corners X_i.
    Basix's default rule (Xiao–Gimbutas up to degree 30, fully symmetric).
    """
    points, weights = basix.make_quadrature(basix.CellType.triangle, degree)
    bary = np.column_stack([1.0 - points.sum(axis=1), points[:, 0], points[:, 1]])
    return bary, 2.0 * weights


def global_vertices(mesh, comm=None) -> np.ndarray:
    """The coordinates of all vertices of ``mesh``, each once, on every rank.

    Each rank contributes its owned vertices; collective over ``comm`` (default the
    mesh's communicator).
    """
    comm = mesh.comm if comm is None else comm
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(0, tdim)
    owned = np.arange(mesh.topology.index_map(0).size_local, dtype=np.int32)
    nodes = dolfinx.mesh.entities_to_geometry(mesh, 0, owned).reshape(-1)
    return np.concatenate(comm.allgather(mesh.geometry.x[nodes]))


def nanson_density(F, N) -> np.ndarray:
    """|cof(F) N| = J |F⁻ᵀ N| for deformation gradients F (..., 3, 3).

    The cofactor's columns are cross products of F's columns: no inverse, so it stays
    exact and finite even where F is nearly singular.
    """
    c0, c1, c2 = F[..., :, 0], F[..., :, 1], F[..., :, 2]
    v = np.cross(c1, c2) * N[0] + np.cross(c2, c0) * N[1] + np.cross(c0, c1) * N[2]
    return np.linalg.norm(v, axis=-1)


class CutSection:
    """The cut of a tetrahedral mesh (affine cells) by a plane, on this rank's owned cells.

    Built once per mesh: cut triangles, quadrature points, their weights and their
    reference coordinates in the cells. ``area0`` and ``deformed_area`` are collective
    over the mesh's communicator.
    """

    def __init__(self, mesh, origin, normal, *, degree: int = 4):
        if mesh.topology.cell_type != dolfinx.mesh.CellType.tetrahedron:
            raise ValueError(f"CutSection needs a tetrahedral mesh, got {mesh.topology.cell_type}")
        if mesh.geometry.cmaps[0].degree != 1:
            raise ValueError("CutSection needs affine cells (degree-1 geometry)")
        normal = np.asarray(normal, dtype=float)
        self.mesh = mesh
        self.origin = np.asarray(origin, dtype=float)
        self.normal = normal / np.linalg.norm(normal)

        n_owned = mesh.topology.index_map(mesh.topology.dim).size_local
        x = mesh.geometry.x[mesh.geometry.dofmaps[0][:n_owned]]
        cells, self.triangles = cut_triangles(x, self.origin, self.normal)
        areas = triangle_areas(self.triangles)
        self._area0 = float(areas.sum())

        bary, w = triangle_rule(degree)
        nq = len(w)
        points = np.einsum("qi,tij->tqj", bary, self.triangles)
        # Affine cells: X = X0 + J ξ, with J's columns the edges from vertex 0.
        x0 = x[cells, 0]
        jac = np.transpose(x[cells, 1:] - x0[:, None, :], (0, 2, 1))
        jinv = np.linalg.inv(jac) if len(cells) else np.zeros((0, 3, 3))
        ref = np.einsum("tij,tqj->tqi", jinv, points - x0[:, None, :])
        self.cells = cells  # owned cell of each triangle
        self._point_cells = np.repeat(cells, nq)
        self._ref_points = ref.reshape(-1, 3)
        self._weights = (areas[:, None] * w[None, :]).reshape(-1)
        self._jinv = np.repeat(jinv, nq, axis=0)
        self._space = None

    def area0(self, comm=None) -> float:
        """The exact area of the reference section (a sum of triangle areas)."""
        comm = self.mesh.comm if comm is None else comm
        return comm.allreduce(self._area0, op=MPI.SUM)

    def _basis(self, space):
        """Physical gradients of the basis at the quadrature points, and the cell dofs."""
        if space is not self._space:
            if space.value_shape != (3,) or space.element.needs_dof_transformations:
                raise ValueError("deformed_area needs a vector Lagrange displacement (3 components)")
            element = space.ufl_element().basix_element
            dref = element.tabulate(1, self._ref_points)[1:4, :, :, 0]  # (3, points, dofs)
            # ∂φ/∂X_j = Σ_k ∂φ/∂ξ_k (J⁻¹)_kj
            self._dphi = np.einsum("kpa,pkj->paj", dref, self._jinv)
            self._dofs = space.dofmap.list[self._point_cells]
            self._space = space
        return self._dphi, self._dofs

    def deformed_area(self, u) -> float:
        """∫ J |F⁻ᵀ N| dA over the reference cut, F = I + ∇u, N the plane's normal.

        Updates the ghost values of ``u`` first (a collective scatter).
        """
        dphi, dofs = self._basis(u.function_space)
        u.x.scatter_forward()
        values = u.x.array.reshape(-1, 3)[dofs]  # (points, dofs, 3)
        F = np.eye(3) + np.einsum("pai,paj->pij", values, dphi)
        local = float(self._weights @ nanson_density(F, self.normal))
        return self.mesh.comm.allreduce(local, op=MPI.SUM)


class AxialSections:
    """`CutSection`s of a mesh at ``fractions`` of its length along the first principal
    axis of its vertices (`axial_planes`); ``areas0`` and ``deformed_areas`` are collective."""

    def __init__(self, mesh, fractions, *, degree: int = 4):
        self.fractions = np.asarray(fractions, dtype=float)
        origins, normal = axial_planes(global_vertices(mesh, mesh.comm), self.fractions)
        self.cuts = [CutSection(mesh, origin, normal, degree=degree) for origin in origins]
        self.areas0 = np.array([cut.area0() for cut in self.cuts])

    def deformed_areas(self, u) -> np.ndarray:
        return np.array([cut.deformed_area(u) for cut in self.cuts])
