"""The original code's "box" measure of an anatomical cross-section (MODEL.md §9).

The paper's code did not cut the muscle by its mid-plane. It built a thin box mesh
there and measured on one face of it:

1. a box THICKNESS thick of CELLS (× 6 tetrahedra), PADDING × the transverse extent of
   the vertex cloud, centred at the vertex mean and aligned with the principal axes of
   the vertices, thin along the first;
2. the box cells that touch a muscle cell (GJK distance ≤ TOUCH) are kept; the
   measuring surface is the box's face at -THICKNESS/2 along the axis, restricted to
   those cells: a staircase that covers the section and overhangs it at the rim;
3. the muscle's displacement is interpolated into P2 on the box
   (`interpolate_nonmatching`). What the box nodes outside the muscle get is
   ``outside`` (`OUTSIDE`):
   - "extrapolate" (the default, what the original code got): u = 0, except at nodes
     inside the bounding box of a muscle cell, to which DOLFINx 0.11 extrapolates the
     closest cell's polynomial (DOLFINx issue #4450; the original's numbers, CSA
     +3.84 % on BFLH_VHF_Left, come out with it);
   - "zero" (what MODEL.md §9 says): u = 0 at every node that lies in no muscle cell,
     decided by the distance from the node to the cells (`in_cells`);
4. CSA = ∫ J |F⁻ᵀ N| dA over the staircase, F = I + ∇u of the box field.

Under "zero" the box cannot see growth: the staircase's edge lies on box cells that
touch no muscle cell, so u = 0 all along it, and ∫ cof(F) N · N dA (the in-plane
Jacobian) depends on the edge's values alone: it is the reference area, whatever the
growth. Nanson's J |F⁻ᵀ N| = ±|cof(F) N| differs from it by out-of-plane shear (second
order) and where J < 0 (the field's steep fall across the rim). What the original reads
as growth comes from the values extrapolated to the edge.

A staircase facet whose cell has every P2 node given the muscle's value is *inner*:
there the box field is the muscle's polynomial (or, under "extrapolate", its
extrapolation), and a uniform growth reads exactly. The others are the *rim*: the
displacement drops to zero across them, so they read as shrinking while the section
grows. `BoxSection` keeps the two apart (`INNER`, `RIM`) so that this can be seen and
tested; under "zero" the rim is larger (the cells with an extrapolated node join it).
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np
import ufl
from dolfinx import fem, geometry, la
from dolfinx import mesh as dmesh
from mpi4py import MPI

from hyper.core.params import InputError
from hyper.fem import growthfield, section
from hyper.model import tensors

THICKNESS = 1.0e-3  # m, along the first principal axis
CELLS = (2, 30, 30)  # hexahedra through the thickness and along the second and third axes
PADDING = 1.2  # box side / extent of the vertices along the second and third axes
TOUCH = 1e-13  # m, GJK distance up to which a box cell touches a muscle cell
# UFL's estimate for J |F⁻ᵀ N| with P2 displacements, which the original integrated with
# (it gave the form no degree); the inner facets are exact at any degree.
QUADRATURE_DEGREE = 15
INNER, RIM = 1, 2  # facet tags of the staircase
# what the box field is at box nodes outside the muscle (see the module's docstring)
OUTSIDE = ("extrapolate", "zero")
INSIDE_DISTANCE = 1e-12  # m, distance from a muscle cell up to which a point lies in it (round-off)


def file_order_vertices(mesh, comm=None) -> np.ndarray:
    """The coordinates of all vertices of ``mesh`` (affine cells), each once, in the
    order of the mesh file, on every rank. Collective over ``comm`` (default the mesh's)."""
    comm = mesh.comm if comm is None else comm
    n = mesh.geometry.index_map().size_local
    parts = comm.allgather((mesh.geometry.input_global_indices[:n], mesh.geometry.x[:n]))
    index = np.concatenate([p[0] for p in parts])
    return np.concatenate([p[1] for p in parts])[np.argsort(index)]


def box_frame(points, *, padding: float = PADDING, thickness: float = THICKNESS):
    """(centre, axes, half) of the box about ``points`` (every vertex once, in the mesh
    file's order): their mean, their principal axes (columns, largest variance first)
    and the half sides (3,) along them.

    The axes are numpy's SVD of the centred points, as in the original code, signs
    included: LAPACK's choice of sign decides on which side of the mid-plane the
    measuring face lies (BFLH_VHF_Left: the other side from `section.principal_plane`'s
    normal, a staircase 1.113 × the cut rather than 1.119 ×), and the file's order makes
    that choice the same on any number of ranks.
    """
    pts = np.asarray(points, dtype=float)
    centre = pts.mean(axis=0)
    centred = pts - centre
    axes = np.linalg.svd(centred, full_matrices=False)[2].T
    along = centred @ axes[:, 1:]
    half = np.concatenate([[0.5 * thickness], 0.5 * padding * np.ptp(along, axis=0)])
    return centre, axes, half


def box_mesh(comm, centre, axes, half, cells=CELLS):
    """The box mesh on ``comm`` and its local facets on the face at -half[0]."""
    box = dmesh.create_box(comm, [-half, half], list(cells), dmesh.CellType.tetrahedron)
    face = dmesh.locate_entities_boundary(box, 2, lambda x: np.isclose(x[0], -half[0], rtol=0,
                                                                            atol=1e-9 * half[0]))
    box.geometry.x[:] = centre + box.geometry.x @ axes.T
    return box, face


def cell_coordinates(mesh, cells) -> np.ndarray:
    """Vertex coordinates (n, 4, 3) of affine tetrahedra ``cells``."""
    return mesh.geometry.x[mesh.geometry.dofmaps[0][cells]]


def touching(box, muscle) -> np.ndarray:
    """Which cells of ``box`` (a mesh on COMM_SELF, all its cells) touch a cell of
    ``muscle`` owned by this rank: a bool per box cell, in the box's original numbering.

    Bounding boxes pick the candidate pairs, exact tests or GJK decide.
    """
    n_box = box.topology.index_map(3).size_local
    owned = np.arange(muscle.topology.index_map(3).size_local, dtype=np.int32)
    pairs = geometry.compute_collisions_trees(geometry.bb_tree(muscle, 3, entities=owned),
                                              geometry.bb_tree(box, 3))
    xm, xb = cell_coordinates(muscle, owned), cell_coordinates(box, np.arange(n_box))
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    # Cheap exact tests first, for all pairs at once, each only on the pairs of box cells
    # still undecided: a box cell touches a muscle cell (distance 0) where its centroid, or
    # a vertex of either cell, lies inside the other; a pair is apart where a face plane of
    # either cell separates them by more than TOUCH. GJK (40 µs a pair in Python) decides
    # the few left: about 60 of 73,000 pairs on BFLH_VHF_Left, where it decided 5,300 after
    # the centroid test alone (0.5 s of a run's set-up).
    touch = np.zeros(n_box, dtype=bool)
    tests = [lambda m, b: inside(m, b.mean(axis=1))]
    tests += [lambda m, b, k=k: inside(m, b[:, k]) | inside(b, m[:, k]) for k in range(4)]
    for test in tests:
        pairs = pairs[~touch[pairs[:, 1]]]
        touch[pairs[test(xm[pairs[:, 0]], xb[pairs[:, 1]]), 1]] = True
    pairs = pairs[~touch[pairs[:, 1]]]
    for m, b in pairs[~separated(xm[pairs[:, 0]], xb[pairs[:, 1]], TOUCH)]:
        if not touch[b] and np.linalg.norm(geometry.compute_distance_gjk(xm[m], xb[b])) <= TOUCH:
            touch[b] = True
    out = np.zeros(n_box, dtype=bool)
    out[np.asarray(box.topology.original_cell_index)[:n_box]] = touch
    return out


def separated(a, b, gap: float) -> np.ndarray:
    """Whether the tetrahedra a and b (n, 4, 3) lie more than ``gap`` apart across a face
    plane of either: a sufficient test of distance > gap, exact wherever it says so."""
    out = np.zeros(len(a), dtype=bool)
    for tet in (a, b):
        for i, j, k in ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)):
            normal = np.cross(tet[:, j] - tet[:, i], tet[:, k] - tet[:, i])
            length = np.linalg.norm(normal, axis=1)
            pa = np.einsum("nvk,nk->nv", a, normal)
            pb = np.einsum("nvk,nk->nv", b, normal)
            margin = gap * length
            out |= (pa.max(axis=1) + margin < pb.min(axis=1)) | (pb.max(axis=1) + margin < pa.min(axis=1))
    return out


def in_cells(mesh, points, *, distance: float = INSIDE_DISTANCE) -> np.ndarray:
    """Which of ``points`` (n, 3), the same on every rank, lie in a cell of ``mesh``
    (within ``distance`` m of one): a bool per point, the same on every rank.

    Bounding boxes pick the candidate cells, the exact distance from the point to the
    cell decides. Collective over the mesh's communicator.
    """
    points = np.ascontiguousarray(points, dtype=mesh.geometry.x.dtype).reshape(-1, 3)
    owned = np.arange(mesh.topology.index_map(3).size_local, dtype=np.int32)
    tree = geometry.bb_tree(mesh, 3, entities=owned, padding=distance)
    candidates = geometry.compute_collisions_points(tree, points)
    which = np.repeat(np.arange(len(points)), np.diff(candidates.offsets))
    hit = np.zeros(len(points), dtype=np.int8)
    if len(which):
        # a point inside a candidate is at distance 0: the exact distance (a GJK each,
        # 0.3 s of an anatomical run's set-up for all candidates) only for the others
        cells = np.asarray(candidates.array, dtype=np.int32)
        hit[which[inside(cell_coordinates(mesh, cells), points[which])]] = 1
        rest = hit[which] == 0
        if np.any(rest):
            near = geometry.squared_distance(mesh, 3, cells[rest], points[which[rest]]) <= distance**2
            hit[which[rest][near]] = 1
    mesh.comm.Allreduce(MPI.IN_PLACE, hit, op=MPI.MAX)
    return hit.astype(bool)


def check_outside(outside: str) -> str:
    if outside not in OUTSIDE:
        raise InputError(f"expected one of {', '.join(OUTSIDE)}, got {outside!r}", field="outside")
    return outside


def inside(tets, points, margin: float = 1e-9) -> np.ndarray:
    """Whether each point (n, 3) lies inside its tetrahedron (n, 4, 3) with every
    barycentric coordinate above ``margin`` (False for a degenerate one)."""
    x0 = tets[:, 0]
    edges = np.transpose(tets[:, 1:] - x0[:, None, :], (0, 2, 1))  # columns x_i - x0
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = tensors.solve(edges, points - x0)
    return np.all(lam > margin, axis=1) & (1.0 - lam.sum(axis=1) > margin)


class BoxSection:
    """The box measure of a tetrahedral mesh's cross-section, for the displacement ``u``
    (a vector Lagrange function on ``mesh``) as it is at each call; ``outside`` (one of
    `OUTSIDE`) what the box field is at box nodes outside the muscle.

    Built once: the box on the mesh's communicator, its staircase facets tagged INNER or
    RIM, the P2 box field and the interpolation data, the forms. Every public method is
    collective over the mesh's communicator and returns reduced values.
    """

    def __init__(self, mesh, u, *, cells=CELLS, padding: float = PADDING, thickness: float = THICKNESS,
                 degree: int = QUADRATURE_DEGREE, outside: str = "extrapolate"):
        self.outside = check_outside(outside)
        comm = mesh.comm
        self.comm = comm
        self.muscle = mesh
        self.u = u
        self.centre, self.axes, self.half = box_frame(file_order_vertices(mesh, comm), padding=padding,
                                                      thickness=thickness)
        self.mesh, face = box_mesh(comm, self.centre, self.axes, self.half, cells)
        serial, _ = box_mesh(MPI.COMM_SELF, self.centre, self.axes, self.half, cells)
        kept = touching(serial, mesh).astype(np.int8)
        comm.Allreduce(MPI.IN_PLACE, kept, op=MPI.MAX)
        box = self.mesh
        imap = box.topology.index_map(3)
        local = np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32)
        kept = kept[np.asarray(box.topology.original_cell_index)[local]].astype(bool)
        # The staircase sees the box field on the kept cells with a face on it alone: only
        # those are interpolated (the other nodes keep u = 0, as outside the muscle), owned
        # and ghost alike, and never scattered: the owner of a dof need not have such a
        # cell about it, and would overwrite the value with its zero.
        depth = (cell_coordinates(box, local) - self.centre) @ self.axes[:, 0] + self.half[0]
        bottom = np.count_nonzero(np.abs(depth) <= 1e-9 * self.half[0], axis=1) == 3
        self._cells = local[kept & bottom]

        self.V = fem.functionspace(box, ("Lagrange", 2, (3,)))
        self._data = fem.create_interpolation_data(self.V, u.function_space, self._cells)
        Q = fem.functionspace(box, ("Lagrange", 2))  # V's nodes, numbered as V's blocks
        # the nodes of the measured cells in no muscle cell; "zero" sets them to 0 after
        # each interpolation, on every rank alike (the test is global)
        nodes = np.unique(Q.dofmap.list[self._cells])
        start = sum(comm.allgather(len(nodes))[:comm.rank])
        points = np.concatenate(comm.allgather(Q.tabulate_dof_coordinates()[nodes]))
        out = ~in_cells(mesh, points)[start:start + len(nodes)]
        self._zeroed = nodes[out] if self.outside == "zero" else np.empty(0, dtype=np.int32)

        # inner: every P2 node of the cell gets the muscle's value (an interpolated 1 is 1 there, 0 elsewhere)
        one = fem.Function(fem.functionspace(mesh, ("Lagrange", 1)))
        one.x.array[:] = 1.0
        found = fem.Function(Q)
        found.interpolate_nonmatching(one, self._cells, self._data)  # the same points as V's
        extrapolated = out & (found.x.array[nodes] > 0.5)
        numbers = Q.dofmap.index_map.local_to_global(nodes.astype(np.int32))
        # (outside nodes, those of them DOLFINx extrapolates to), each node once
        self.outside_nodes = tuple(len(np.unique(np.concatenate(comm.allgather(numbers[which]))))
                                   for which in (out, extrapolated))
        found.x.array[self._zeroed] = 0.0
        inside = np.all(found.x.array[Q.dofmap.list[local]] > 0.5, axis=1)

        box.topology.create_connectivity(2, 3)
        facet_cell = box.topology.connectivity(2, 3)
        cell_of = np.array([facet_cell.links(f)[0] for f in face], dtype=np.int32)
        on = kept[cell_of]
        facets = face[on]
        tags = np.where(inside[cell_of[on]], INNER, RIM).astype(np.int32)
        order = np.argsort(facets)
        self.tags = dmesh.meshtags(box, 2, facets[order], tags[order])

        self.field = fem.Function(self.V, name="u_box")
        ds = ufl.Measure("ds", domain=box, subdomain_data=self.tags, metadata={"quadrature_degree": degree})
        density = growthfield.nanson_area_density(ufl.Identity(3) + ufl.grad(self.field), ufl.FacetNormal(box))
        self._area0 = [fem.form(1.0 * ds(tag)) for tag in (INNER, RIM)]
        self._area = [fem.form(density * ds(tag)) for tag in (INNER, RIM)]
        # per cell: its staircase facet's reference and deformed area (a cell has one at most)
        v = ufl.TestFunction(fem.functionspace(box, ("DG", 0)))
        self._facet_forms = [fem.form(v * ds((INNER, RIM))), fem.form(density * v * ds((INNER, RIM)))]
        self.areas0 = self._reduce(self._area0)

    def _reduce(self, forms) -> np.ndarray:
        return self.comm.allreduce(np.array([fem.assemble_scalar(f) for f in forms]), op=MPI.SUM)

    def area0(self) -> float:
        """The staircase's area: the summed faces of the kept cells."""
        return float(self.areas0.sum())

    def update(self) -> None:
        """Interpolate the muscle's displacement into the box field (outside the muscle:
        as ``outside`` says)."""
        self.u.x.scatter_forward()
        self.field.interpolate_nonmatching(self.u, self._cells, self._data)
        self.field.x.array.reshape(-1, 3)[self._zeroed] = 0.0

    def deformed_areas(self) -> np.ndarray:
        """(inner, rim): Nanson's deformed area of each part of the staircase."""
        self.update()
        return self._reduce(self._area)

    def deformed_area(self) -> float:
        return float(self.deformed_areas().sum())

    def plane(self) -> tuple[np.ndarray, np.ndarray]:
        """(origin, normal) of the plane of the staircase (the box face)."""
        normal = self.axes[:, 0]
        return self.centre - self.half[0] * normal, normal

    def picture(self) -> dict | None:
        """The staircase in the plane of the box face, gathered on rank 0 (None elsewhere),
        in metres along the second and third axes about the centre: ``triangles`` (n, 3, 2),
        ``inner`` (n,) bool, ``ratio`` (n,) each facet's deformed / reference area at the
        current ``u``, and ``outline`` (m, 2, 2) the edges bounding the exact cut of the
        muscle by the same plane."""
        self.update()
        box = self.mesh
        ref, now = (fem.assemble_vector(f) for f in self._facet_forms)
        for b in (ref, now):
            b.scatter_reverse(la.InsertMode.add)
            b.scatter_forward()
        facets, tags = self.tags.indices, self.tags.values
        mine = facets < box.topology.index_map(2).size_local  # each facet once, on its owner
        facets, tags = facets[mine], tags[mine]
        facet_cell = box.topology.connectivity(2, 3)
        cells = np.array([facet_cell.links(f)[0] for f in facets], dtype=np.int32)
        nodes = dmesh.entities_to_geometry(box, 2, facets)
        plane = (box.geometry.x[nodes] - self.centre) @ self.axes[:, 1:]
        ratio = now.array[cells] / ref.array[cells]
        parts = self.comm.gather((plane.reshape(-1, 3, 2), tags == INNER, ratio), root=0)
        outline = cut_outline(self.muscle, *self.plane(), self.centre, self.axes[:, 1:])
        if self.comm.rank != 0:
            return None
        return {"triangles": np.concatenate([p[0] for p in parts]), "inner": np.concatenate([p[1] for p in parts]),
                "ratio": np.concatenate([p[2] for p in parts]), "outline": outline}


def cut_outline(mesh, origin, normal, frame_origin, frame_axes) -> np.ndarray | None:
    """The boundary edges (m, 2, 2) of the exact cut of ``mesh`` by the plane, in the
    coordinates along ``frame_axes`` (3, 2) about ``frame_origin``: the edges of the cut
    triangles that no other one shares (`section.cut_triangles` makes shared points
    bitwise equal). Gathered on rank 0 (None elsewhere)."""
    n_owned = mesh.topology.index_map(mesh.topology.dim).size_local
    _, triangles = section.cut_triangles(cell_coordinates(mesh, np.arange(n_owned)), origin, normal)
    gathered = mesh.comm.gather(triangles, root=0)
    if mesh.comm.rank != 0:
        return None
    triangles = np.concatenate(gathered)
    triangles = triangles[section.triangle_areas(triangles) > 0]
    a = np.concatenate([triangles[:, 0], triangles[:, 1], triangles[:, 2]])
    b = np.concatenate([triangles[:, 1], triangles[:, 2], triangles[:, 0]])
    first = np.array([tuple(p) <= tuple(q) for p, q in zip(a, b)])  # each edge one way round
    key = np.where(first[:, None], np.hstack([a, b]), np.hstack([b, a]))
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    once = counts[inverse.ravel()] == 1
    edges = np.stack([a[once], b[once]], axis=1)
    return (edges - frame_origin) @ frame_axes
