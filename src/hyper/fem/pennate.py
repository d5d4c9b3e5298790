"""Pennate fibres by rule: a Laplacian flow between the attachment areas of a muscle,
after Choi & Blemker 2013 (PLoS ONE 8:e77576, "Skeletal muscle fascicle arrangements can
be reconstructed using a Laplacian vector field simulation").

Fascicles run from the origin aponeurosis to the insertion aponeurosis. Choi & Blemker
take them as the streamlines of a rotation- and divergence-free field, the gradient of a
potential φ with a uniform flux through each attachment area and none through the rest
of the surface. Here, with Γo the origin patch, Γi the insertion patch and |Γ| their
areas (m²):

    -Δφ = 0                     in Ω
    ∂φ/∂n = -1/|Γo|             on Γo          (inflow: one unit of "fascicles" per muscle)
    ∂φ/∂n = +1/|Γi|             on Γi          (outflow), where Γi is part of the surface
    -Δφ = δ_Γi / |Γi|                          where Γi is an internal section (a central
                                                aponeurosis: a sheet sink, flow from both sides)
    ∂φ/∂n = 0                   on the rest of the surface

    a0 = ∇φ / |∇φ|

As in Choi & Blemker: the Laplace problem, uniform flux on the attachments (so every
unit of attachment area sends out, or takes in, the same number of fascicles), zero flux
elsewhere, fibres the normalized gradient. Where this differs:

- Internal aponeuroses. Choi & Blemker put the attachments on the muscle's surface
  (their aponeuroses are segmented surfaces). A bipennate muscle's central aponeurosis is
  inside the muscle; here it can be a plane section (`plane:`, `midplane`), imposed as a
  uniform sheet sink on the cut polygons plane ∩ tetrahedra (the mesh need not follow it).
- Discretisation: P1 Lagrange on the muscle's tetrahedra, the pure Neumann problem made
  unique by φ = 0 at one vertex (the data sum to zero, so the other equations still hold
  exactly); one MUMPS LU factorisation. The cells' gradients (constant per cell) are
  brought to the vertices as the principal direction of their volume-weighted structure
  tensor Σ V ĝĝᵀ, signed along their mean: on a central aponeurosis the two sides' fibres
  converge from opposite sides and a plain mean would cancel; elsewhere the two agree to
  the discretisation error. The stored field is this unit P1 field, as the Stokes fibres.
- Fascicle length: streamlines of the cells' gradients (piecewise constant, so a step
  inside a cell is exact), traced from the centroid of every origin triangle (sheets:
  from both sides) until they reach the insertion patch; weighted by the triangle's area.
- Pennation angle: the angle between a0 and the muscle's line of action, taken as the
  first principal axis of the vertices (the axis `hyper.fem.fibers` measures the Stokes
  fibres against), per cell (mean of its nodal fibres), weighted by cell volume.

Patches: the origin and the insertion are each a patch, written as `SYNTAX` says
(terms such as ``tags:1``, ``midplane``, ``plane:X,Y,Z,NX,NY,NZ``, ``along:A,B`` joined by
``&`` and ``|``)
(``hyper fibers --help`` shows it).

Tags: `tag_patches` puts the boundary facets of the origin and insertion and the mesh
facets lying in a plane section on facet tags `ORIGIN_TAG` and `INSERTION_TAG`, and the
cells a section cuts on cell tags; the fibre file keeps the tagged facets (their vertices
as mesh file node indices) and the patches' specifications and areas.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
import numpy as np
import ufl
from dolfinx import fem, la
from dolfinx import mesh as dmesh
from dolfinx.fem import petsc as fem_petsc
from dolfinx.la import petsc as la_petsc
from mpi4py import MPI
from petsc4py import PETSc
from scipy.spatial import cKDTree

from hyper.core.io import write_series
from hyper.core.params import InputError
from hyper.fem import fibers, section
from hyper.fem import geometry as geo
from hyper.fem import meshing as hm

STL_DISTANCE_MM = 1.0
SYNTAX = f"""\
Patches (--origin, --insertion): a union (|) of intersections (&) of terms; each intersection
has one selector and any number of filters. Coordinates are in millimetres, whatever the
mesh file's unit:

    boundary                       every boundary facet (implied by an intersection of filters only)
    tags:T[,T...]                  boundary facets with these facet tags (1 origin end, 2 insertion
                                   end, 3 lateral surface in the shipped meshes)
    stl:FILE[,D]                   boundary facets whose three vertices lie within D mm (default
                                   {STL_DISTANCE_MM:g}) of the surface in FILE (STL, millimetres)
    vertices:FILE                  boundary facets whose three vertices are all listed in FILE
                                   (mesh file node indices, from 0, separated by spaces, commas
                                   or new lines)
    plane:X,Y,Z,NX,NY,NZ           the muscle's section by the plane through (X, Y, Z) normal to
                                   (NX, NY, NZ): an internal aponeurosis
    midplane[:K]                   the section by the plane through the vertices' mean that holds
                                   the first principal axis and is normal to the K-th (2 or 3;
                                   default 3, the thinnest direction)
  filters:
    halfspace:X,Y,Z,NX,NY,NZ       keep what lies where (x - X)·N >= 0 (a triangle's centroid)
    along:A,B                      keep what lies between shares A and B of the muscle's length
                                   along the line of action, from 0 at the origin end (tag 1) to
                                   1 at the insertion end (tag 2)
    side:[-]K                      keep what lies on the + (or -) side of midplane:K (K 2 or 3;
                                   the axes' signs are those numpy's eigh gives: look at the picture)
"""
KIND = "pennate"
ORIGIN_TAG, INSERTION_TAG = 11, 12
SELECTORS = ("boundary", "tags", "stl", "vertices", "plane", "midplane")
FILTERS = ("halfspace", "along", "side")
# The default attachments, a bipennate rule for a long muscle: fascicles leave the proximal
# 80 % of its surface (the origin end and the lateral surface there) and converge on a central
# aponeurosis, the mid-plane across the thinnest direction, over the distal 80 %, and on the
# insertion end. The overlap of the two sets the pennation: docs/pennate.md shows it on the
# tibialis anterior for three extents.
DEFAULT_ORIGIN = "tags:1 | tags:3 & along:0,0.8"
DEFAULT_INSERTION = "tags:2 | midplane & along:0.2,1"
METHOD = ("pennate: Laplacian flow after Choi & Blemker 2013, -Δφ = 0 with uniform flux -1/|Γo| on the origin "
          "patch and +1/|Γi| on the insertion patch (a sheet sink on an internal section), zero flux elsewhere; "
          "P1, MUMPS LU; a0 = the principal direction of the cells' volume-weighted ∇φ/|∇φ| at each vertex (P1)")
REFERENCE = "Choi & Blemker 2013, PLoS ONE 8:e77576; hyper.fem.pennate"
MIN_SPEED = 1e-8  # of the mean |∇φ|: below it a cell has no direction
STEP = 0.25  # streamline step, of the cells' mean size (cube root of the mean volume)
MAX_LENGTH = 3.0  # a streamline longer than this many times the muscle's length is lost
PERCENTILES = (5, 50, 95)


# ------------------------------------------------------------------------------ patches


@dataclasses.dataclass(frozen=True)
class Term:
    name: str
    args: tuple = ()

    def text(self) -> str:
        return self.name + (":" + ",".join(str(a) for a in self.args) if self.args else "")


@dataclasses.dataclass(frozen=True)
class Patch:
    """A parsed patch specification (module docstring): a union of intersections."""

    spec: str
    groups: tuple[tuple[Term, ...], ...]

    @property
    def internal(self) -> bool:
        return any(g[0].name in ("plane", "midplane") for g in self.groups)


def _numbers(text: str, count: int, where: str) -> tuple[float, ...]:
    parts = [p.strip() for p in text.split(",")]
    if len(parts) != count:
        raise InputError(f"{where}: expected {count} numbers separated by commas, got {text!r}")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise InputError(f"{where}: expected {count} numbers separated by commas, got {text!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise InputError(f"{where}: the numbers must be finite, got {text!r}")
    return values


def _term(text: str, where: str) -> Term:
    name, _, args = text.strip().partition(":")
    name = name.strip()
    where = f"{where} {text.strip()!r}"
    if name in ("boundary",) and not args:
        return Term(name)
    if name == "tags":
        try:
            tags = tuple(int(t) for t in args.split(","))
        except ValueError:
            raise InputError(f"{where}: expected tags:T[,T...] with integer tags") from None
        return Term(name, tags)
    if name in ("plane", "halfspace"):
        values = _numbers(args, 6, where)
        if np.linalg.norm(values[3:]) == 0:
            raise InputError(f"{where}: the normal (NX, NY, NZ) is zero")
        return Term(name, values)
    if name == "midplane":
        k = args.strip() or "3"
        if k not in ("2", "3"):
            raise InputError(f"{where}: expected midplane, midplane:2 or midplane:3")
        return Term(name, (int(k),))
    if name == "side":
        k = args.strip()
        if k not in ("2", "3", "-2", "-3"):
            raise InputError(f"{where}: expected side:K or side:-K with K 2 or 3")
        return Term(name, (int(k),))
    if name == "along":
        a, b = _numbers(args, 2, where)
        if not 0.0 <= a < b <= 1.0:
            raise InputError(f"{where}: expected 0 <= A < B <= 1")
        return Term(name, (a, b))
    if name in ("stl", "vertices"):
        path, _, distance = args.partition(",")
        path = Path(path.strip())
        if not path.is_file():
            raise InputError(f"{where}: {path}: no such file")
        if name == "vertices":
            if distance:
                raise InputError(f"{where}: expected vertices:FILE")
            return Term(name, (path,))
        d = _numbers(distance, 1, where)[0] if distance.strip() else STL_DISTANCE_MM
        if not d > 0:
            raise InputError(f"{where}: the distance must be positive")
        return Term(name, (path, d))
    raise InputError(f"{where}: unknown term; selectors: {', '.join(SELECTORS)}; filters: {', '.join(FILTERS)} "
                     "(see --help)")


def parse(spec: str, option: str = "patch") -> Patch:
    """A patch from its specification (module docstring); InputError if malformed."""
    if not isinstance(spec, str) or not spec.strip():
        raise InputError(f"{option}: empty patch specification")
    groups = []
    for text in spec.split("|"):
        if not text.strip():
            raise InputError(f"{option} {spec!r}: an empty alternative between '|'")
        terms = [_term(t, option) for t in text.split("&")]
        selectors = [t for t in terms if t.name in SELECTORS]
        if len(selectors) > 1:
            raise InputError(f"{option} {text.strip()!r}: one selector per '&' group, got "
                             f"{', '.join(t.name for t in selectors)}")
        filters = [t for t in terms if t.name in FILTERS]
        groups.append((selectors[0] if selectors else Term("boundary"), *filters))
    return Patch(spec.strip(), tuple(groups))


class Frame:
    """What the patch terms need of a geometry, on this rank's owned cells and boundary
    facets: coordinates, facet tags, the line of action and the muscle's extent along it."""

    def __init__(self, geometry: geo.Geometry):
        mesh = geometry.mesh
        self.geometry = geometry
        self.comm = geometry.comm
        tdim = mesh.topology.dim
        mesh.topology.create_connectivity(tdim - 1, tdim)
        mesh.topology.create_connectivity(tdim, tdim - 1)
        exterior = dmesh.exterior_facet_indices(mesh.topology)
        self.facets = exterior[exterior < mesh.topology.index_map(tdim - 1).size_local].astype(np.int32)
        self.facet_nodes = dmesh.entities_to_geometry(mesh, tdim - 1, self.facets)
        x = mesh.geometry.x
        self.facet_x = x[self.facet_nodes]
        self.facet_centroid = self.facet_x.mean(axis=1)
        self.facet_area = section.triangle_areas(self.facet_x)
        tag = np.zeros(mesh.topology.index_map(tdim - 1).size_local + mesh.topology.index_map(tdim - 1).num_ghosts,
                       dtype=np.int64)
        tag[geometry.facet_tags.indices] = geometry.facet_tags.values
        self.facet_tag = tag[self.facets]
        f2c = mesh.topology.connectivity(tdim - 1, tdim)
        # the centroid of each facet's cell (owned or ghost: a facet's owner need not own its cell)
        cell = np.array([f2c.links(f)[0] for f in self.facets], dtype=np.int32)
        self.facet_cell_centroid = x[mesh.geometry.dofmaps[0][cell]].mean(axis=1)
        ncells = mesh.topology.index_map(tdim).size_local
        self.cell_nodes = mesh.geometry.dofmaps[0][:ncells]
        self.cell_x = x[self.cell_nodes]
        self.file_node = np.asarray(mesh.geometry.input_global_indices, dtype=np.int64)
        self.mean, axes = geo.principal_axes(mesh)
        self.axes = axes
        axis = axes[:, 0]
        ends = [geo.facet_centroid(geometry, t) for t in geometry.ends]
        self.axis = axis if np.dot(ends[1] - ends[0], axis) >= 0 else -axis
        s = geo.owned_vertex_coordinates(mesh) @ self.axis
        self.low = self.comm.allreduce(float(s.min(initial=np.inf)), op=MPI.MIN)
        self.high = self.comm.allreduce(float(s.max(initial=-np.inf)), op=MPI.MAX)

    def share(self, points: np.ndarray) -> np.ndarray:
        """Share of the length along the line of action, 0 at the origin end, 1 at the insertion end."""
        return (points @ self.axis - self.low) / (self.high - self.low)

    def total(self, value) -> float:
        return self.comm.allreduce(float(value), op=MPI.SUM)


@dataclasses.dataclass
class Selection:
    """A patch on one rank: owned boundary facets (a mask over `Frame.facets`), and the
    triangles of its plane sections in owned cells, with their planes."""

    patch: Patch
    facets: np.ndarray  # bool, over Frame.facets
    cells: np.ndarray  # (m,) local cell of each section triangle
    triangles: np.ndarray  # (m, 3, 3)
    planes: list  # [(origin, unit normal)] of the sections, metres
    area: float  # global, m²

    @property
    def triangle_area(self) -> np.ndarray:
        return section.triangle_areas(self.triangles)


def _segment_distance(p, a, b) -> np.ndarray:
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300), 0.0, 1.0)
    return np.linalg.norm(p - a - t[:, None] * ab, axis=1)


def point_triangle_distance(p, a, b, c) -> np.ndarray:
    """Distance from points p (n, 3) to triangles (a, b, c) (each (n, 3)), pair by pair."""
    ab, ac, ap = b - a, c - a, p - a
    normal = np.cross(ab, ac)
    size = np.einsum("ij,ij->i", normal, normal)
    # barycentric coordinates of p's projection (Cramer's rule on the plane)
    v = np.einsum("ij,ij->i", np.cross(ap, ac), normal) / np.maximum(size, 1e-300)
    w = np.einsum("ij,ij->i", np.cross(ab, ap), normal) / np.maximum(size, 1e-300)
    inside = (size > 0) & (v >= 0) & (w >= 0) & (v + w <= 1)
    edges = np.minimum(np.minimum(_segment_distance(p, a, b), _segment_distance(p, b, c)), _segment_distance(p, c, a))
    plane = np.abs(np.einsum("ij,ij->i", ap, normal)) / np.sqrt(np.maximum(size, 1e-300))
    return np.where(inside, plane, edges)


def _stl_near(frame: Frame, path: Path, distance_mm: float) -> np.ndarray:
    """Over the frame's facets: all three vertices within ``distance_mm`` of the STL's
    surface (exact point-triangle distances, for the vertices a triangle's bounding
    sphere, widened by the distance, holds)."""
    try:
        points, triangles = hm.read_stl(path)
    except (InputError, ValueError, OSError) as err:
        raise InputError(f"stl:{path}: cannot read it as an STL: {err}") from None
    corners = points[triangles] * geo.MM
    distance = distance_mm * geo.MM
    vertices = frame.facet_x.reshape(-1, 3)
    near = np.zeros(len(vertices), dtype=bool)
    if len(vertices):
        tree = cKDTree(vertices)
        centre = corners.mean(axis=1)
        radius = np.linalg.norm(corners - centre[:, None], axis=2).max(axis=1) + distance
        for tri, found in enumerate(tree.query_ball_point(centre, radius)):
            if found:
                found = np.asarray(found)
                a, b, c = (np.broadcast_to(corners[tri, k], (len(found), 3)) for k in range(3))
                near[found[point_triangle_distance(vertices[found], a, b, c) <= distance]] = True
    return near.reshape(-1, 3).all(axis=1)


def _vertices_listed(frame: Frame, path: Path) -> np.ndarray:
    try:
        ids = np.array(path.read_text().replace(",", " ").split(), dtype=np.int64)
    except (ValueError, OSError, UnicodeDecodeError) as err:
        raise InputError(f"vertices:{path}: expected mesh file node indices (integers): {err}") from None
    listed = np.isin(frame.file_node[frame.facet_nodes], ids)
    return listed.all(axis=1)


def _group(frame: Frame, group: tuple[Term, ...], where: str):
    """(facet mask, cells, triangles, planes) of one intersection."""
    selector, filters = group[0], group[1:]
    none = np.zeros(len(frame.facets), dtype=bool)
    cells, triangles, planes = np.empty(0, dtype=np.int32), np.empty((0, 3, 3)), []
    if selector.name == "boundary":
        mask = ~none
    elif selector.name == "tags":
        mask = np.isin(frame.facet_tag, selector.args)
    elif selector.name == "stl":
        mask = _stl_near(frame, *selector.args)
    elif selector.name == "vertices":
        mask = _vertices_listed(frame, *selector.args)
    else:
        if selector.name == "plane":
            origin = np.asarray(selector.args[:3]) * geo.MM
            normal = np.asarray(selector.args[3:], dtype=float)
        else:
            origin, normal = frame.mean, frame.axes[:, selector.args[0] - 1]
        normal = normal / np.linalg.norm(normal)
        cells, triangles = section.cut_triangles(frame.cell_x, origin, normal)
        area = section.triangle_areas(triangles)
        cells, triangles = cells[area > 0], triangles[area > 0]
        if frame.total(area.sum()) == 0:
            raise InputError(f"{where}: {selector.text()!r} does not cut the mesh (the plane misses the muscle)")
        mask = none
        planes = [(origin, normal)]
    tri_centroid = triangles.mean(axis=1)
    for term in filters:
        if term.name == "halfspace":
            origin = np.asarray(term.args[:3]) * geo.MM
            normal = np.asarray(term.args[3:])
            mask = mask & (section.signed_distance(frame.facet_centroid, origin, normal) >= 0)
            keep = section.signed_distance(tri_centroid, origin, normal) >= 0
        elif term.name == "side":
            k = term.args[0]
            normal = np.sign(k) * frame.axes[:, abs(k) - 1]
            mask = mask & (section.signed_distance(frame.facet_centroid, frame.mean, normal) >= 0)
            keep = section.signed_distance(tri_centroid, frame.mean, normal) >= 0
        else:
            a, b = term.args
            s = frame.share(frame.facet_centroid)
            mask = mask & (s >= a) & (s <= b)
            s = frame.share(tri_centroid)
            keep = (s >= a) & (s <= b)
        cells, triangles, tri_centroid = cells[keep], triangles[keep], tri_centroid[keep]
    return mask, cells, triangles, planes


def select(frame: Frame, patch: Patch, option: str) -> Selection:
    """The patch on the frame's geometry; InputError (on every rank) where a group selects nothing."""
    mask = np.zeros(len(frame.facets), dtype=bool)
    cells, triangles, planes = [], [], []
    for group in patch.groups:
        text = " & ".join(t.text() for t in group)
        g_mask, g_cells, g_tri, g_planes = _group(frame, group, f"{option} {patch.spec!r}")
        area = frame.total(frame.facet_area[g_mask].sum() + section.triangle_areas(g_tri).sum())
        if area == 0:
            raise InputError(f"{option} {patch.spec!r}: {text!r} selects nothing on {frame.geometry.name}")
        mask |= g_mask
        cells.append(g_cells)
        triangles.append(g_tri)
        planes += g_planes
    cells = np.concatenate(cells)
    triangles = np.concatenate(triangles)
    area = frame.total(frame.facet_area[mask].sum() + section.triangle_areas(triangles).sum())
    return Selection(patch, mask, cells, triangles, planes, area)


def check_apart(frame: Frame, origin: Selection, insertion: Selection) -> None:
    """InputError where the origin and insertion share boundary facets."""
    shared = frame.total(np.count_nonzero(origin.facets & insertion.facets))
    if shared:
        raise InputError(f"--origin {origin.patch.spec!r} and --insertion {insertion.patch.spec!r} overlap: "
                         f"{int(shared)} boundary facets are in both")


# ------------------------------------------------------------------------------ solving


def _barycentric(cell_x: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(n, 4) barycentric coordinates of points (n, 3) in tetrahedra (n, 4, 3)."""
    lam = np.linalg.solve(np.swapaxes(cell_x[:, 1:] - cell_x[:, :1], 1, 2), (points - cell_x[:, 0])[..., None])[..., 0]
    return np.column_stack([1.0 - lam.sum(axis=1), lam])


def flux_vector(space: fem.FunctionSpace, frame: Frame, selection: Selection, total: float) -> la.Vector:
    """∫ g ψ_j over the patch for each P1 basis function ψ_j, g = total/area (exact: P1 on
    flat triangles); summed onto the owners."""
    vec = la.vector(space.dofmap.index_map, 1)
    dofs = _dof_of_node(space, frame)
    g = total / selection.area
    f_dofs = dofs[frame.facet_nodes[selection.facets]]
    np.add.at(vec.array, f_dofs.ravel(), np.repeat(g * frame.facet_area[selection.facets] / 3.0, 3))
    if len(selection.cells):
        centroid = selection.triangles.mean(axis=1)
        lam = _barycentric(frame.cell_x[selection.cells], centroid)
        c_dofs = space.dofmap.list[selection.cells]
        np.add.at(vec.array, c_dofs.ravel(), (g * selection.triangle_area[:, None] * lam).ravel())
    vec.scatter_reverse(la.InsertMode.add)
    return vec


def _dof_of_node(space: fem.FunctionSpace, frame: Frame) -> np.ndarray:
    mesh = space.mesh
    dofs = np.full(len(mesh.geometry.x), -1, dtype=np.int32)
    dofs[mesh.geometry.dofmaps[0].ravel()] = space.dofmap.list.ravel()
    return dofs


def potential(geometry: geo.Geometry, frame: Frame, origin: Selection, insertion: Selection) -> fem.Function:
    """φ of the module docstring (P1), zero at one vertex. Collective."""
    mesh = geometry.mesh
    V = fem.functionspace(mesh, ("Lagrange", 1))
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    # the dof of global index 0, on its owner and where it is a ghost: every rank assembling
    # its row or column must know the condition
    index_map = V.dofmap.index_map
    local = np.arange(index_map.size_local + index_map.num_ghosts, dtype=np.int32)
    pinned = local[index_map.local_to_global(local) == 0]
    bc = fem.dirichletbc(np.float64(0.0), pinned, V)
    A = fem_petsc.assemble_matrix(fem.form(ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx), bcs=[bc])
    A.assemble()
    rhs = flux_vector(V, frame, origin, -1.0)
    rhs.array[:] += flux_vector(V, frame, insertion, 1.0).array
    rhs.array[pinned] = 0.0
    b = la_petsc.create_vector_wrap(rhs)
    phi = fem.Function(V, name="phi")
    ksp = PETSc.KSP().create(geometry.comm)
    ksp.setOperators(A)
    ksp.setType("preonly")
    ksp.getPC().setType("lu")
    ksp.getPC().setFactorSolverType("mumps")
    ksp.solve(b, phi.x.petsc_vec)
    reason = ksp.getConvergedReason()
    ksp.destroy()
    A.destroy()
    b.destroy()
    if reason < 0:
        raise RuntimeError(f"{geometry.name}: the Laplace solve failed (KSP reason {reason})")
    phi.x.scatter_forward()
    return phi


def cell_gradients(frame: Frame, phi: fem.Function) -> tuple[np.ndarray, np.ndarray]:
    """(∇φ (n, 3), volume (n,)) of the owned cells."""
    values = phi.x.array[phi.function_space.dofmap.list[: len(frame.cell_x)]]
    edges = frame.cell_x[:, 1:] - frame.cell_x[:, :1]
    gradient = np.linalg.solve(edges, (values[:, 1:] - values[:, :1])[..., None])[..., 0]
    return gradient, np.abs(np.linalg.det(edges)) / 6.0


def nodal_fibers(frame: Frame, gradient: np.ndarray, volume: np.ndarray) -> tuple[fem.Function, fem.Function]:
    """(a0, speed) at the vertices (vector and scalar P1): a0 the principal direction of
    Σ V ĝĝᵀ over the cells around each vertex, signed along Σ V ĝ; speed the
    volume-weighted mean |∇φ| there over its mean in the muscle (docstring)."""
    geometry = frame.geometry
    comm = frame.comm
    length = np.linalg.norm(gradient, axis=1)
    mean = frame.total((length * volume).sum()) / frame.total(volume.sum())
    slowest = comm.allreduce(float(length.min(initial=np.inf)), op=MPI.MIN)
    if not slowest >= MIN_SPEED * mean:
        raise RuntimeError(f"{geometry.name}: ∇φ vanishes in a cell ({slowest / mean:.2g} of its mean), where the "
                           "flow has no direction; the patches may enclose a dead region")
    unit = gradient / length[:, None]
    V3 = fem.functionspace(geometry.mesh, ("Lagrange", 1, (3,)))
    cell_dofs = V3.dofmap.list[: len(unit)]
    index_map = V3.dofmap.index_map
    tensor = la.vector(index_map, 9)
    mean_dir = la.vector(index_map, 3)
    weight = la.vector(index_map, 2)
    outer = volume[:, None, None] * unit[:, :, None] * unit[:, None, :]
    for k in range(4):
        np.add.at(tensor.array.reshape(-1, 9), cell_dofs[:, k], outer.reshape(-1, 9))
        np.add.at(mean_dir.array.reshape(-1, 3), cell_dofs[:, k], volume[:, None] * unit)
        np.add.at(weight.array.reshape(-1, 2), cell_dofs[:, k], np.column_stack([volume, volume * length]))
    for vec in (tensor, mean_dir, weight):
        vec.scatter_reverse(la.InsertMode.add)
        vec.scatter_forward()
    _, vectors = np.linalg.eigh(tensor.array.reshape(-1, 3, 3))
    direction = vectors[:, :, -1]
    sign = np.sign(np.einsum("ij,ij->i", direction, mean_dir.array.reshape(-1, 3)))
    direction *= np.where(sign == 0, 1.0, sign)[:, None]
    a0 = fem.Function(V3, name="a0")
    a0.x.array[:] = direction.ravel()
    speed = fem.Function(fem.functionspace(geometry.mesh, ("Lagrange", 1)), name="speed")
    w = weight.array.reshape(-1, 2)
    speed.x.array[:] = w[:, 1] / w[:, 0] / mean
    return a0, speed


# ------------------------------------------------------------------------- fascicles


def weighted_summary(values: np.ndarray, weights: np.ndarray, prefix: str) -> dict:
    """Mean and `PERCENTILES` of ``values`` weighted by ``weights`` (the value at which the
    cumulative weight first reaches each share)."""
    order = np.argsort(values)
    v, w = values[order], weights[order]
    cumulative = np.cumsum(w) / w.sum()
    out = {f"{prefix}_mean": float(np.average(v, weights=w))}
    for p in PERCENTILES:
        out[f"{prefix}_p{p}"] = float(v[min(np.searchsorted(cumulative, p / 100.0), len(v) - 1)])
    return out


class Tracer:
    """Streamlines of a piecewise-constant field on a tetrahedral mesh held whole (rank 0).

    ``cell_x`` (n, 4, 3), ``direction`` (n, 3) unit; `locate` finds the cell of points
    among their nearest cell centroids.
    """

    # nearest centroids tried, in rounds for the points not found yet: a point near the
    # surface of the shipped meshes can lie in a flat cell whose centroid is the 30th nearest
    CANDIDATES = (16, 64, 256)

    def __init__(self, cell_x: np.ndarray, direction: np.ndarray):
        self.cell_x = cell_x
        self.direction = direction
        self.tree = cKDTree(cell_x.mean(axis=1))
        self.inverse = np.linalg.inv(np.swapaxes(cell_x[:, 1:] - cell_x[:, :1], 1, 2))

    def locate(self, points: np.ndarray) -> np.ndarray:
        """The cell holding each point, -1 outside the mesh."""
        found = np.full(len(points), -1, dtype=np.int64)
        todo = np.arange(len(points))
        for k in self.CANDIDATES:
            k = min(k, len(self.cell_x))
            if not len(todo):
                break
            _, near = self.tree.query(points[todo], k=k)
            near = near.reshape(len(todo), k)
            lam = np.einsum("pkij,pkj->pki", self.inverse[near], points[todo, None, :] - self.cell_x[near, 0])
            inside = (lam >= -1e-10).all(axis=2) & (lam.sum(axis=2) <= 1 + 1e-10)
            hit = inside.any(axis=1)
            found[todo[hit]] = near[hit, inside[hit].argmax(axis=1)]
            todo = todo[~hit]
        return found


def fascicle_lengths(cell_x, gradient, seeds, exterior, exterior_cell, exterior_insertion, planes, plane_triangles,
                     muscle_length: float) -> tuple[np.ndarray, np.ndarray]:
    """(length (m,) in metres, reached (m,) bool) of the streamlines of ∇φ from ``seeds``.

    A streamline ends on the insertion: where it crosses one of its ``planes`` next to one
    of the section's triangles, or where it leaves the mesh through a boundary facet of
    the insertion (``exterior`` (k, 3, 3) the boundary facets, ``exterior_cell`` (k, 3) the
    centroids of their cells, ``exterior_insertion`` the mask). Steps of `STEP` cells'
    size, the last one cut at the crossing or, bisected, at the exit. Where the discrete
    field points out through a zero-flux wall (by the discretisation error of ∇φ in a
    boundary cell), the rest of the step slides along the wall; a streamline longer than
    `MAX_LENGTH` muscle lengths is lost.
    """
    direction = gradient / np.linalg.norm(gradient, axis=1)[:, None]
    tracer = Tracer(cell_x, direction)
    volume = np.abs(np.linalg.det(cell_x[:, 1:] - cell_x[:, :1])) / 6.0
    h = STEP * float(np.cbrt(volume.mean()))
    centroid = exterior.mean(axis=1)
    exits = cKDTree(centroid)
    normal = np.cross(exterior[:, 1] - exterior[:, 0], exterior[:, 2] - exterior[:, 0])
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    normal *= np.where(np.einsum("ij,ij->i", exterior_cell - centroid, normal) > 0, -1.0, 1.0)[:, None]
    sheets = [(o, n, cKDTree(t.mean(axis=1)), float(np.linalg.norm(t - t.mean(axis=1)[:, None], axis=2).max()) + h)
              for (o, n), t in zip(planes, plane_triangles)]
    p = np.asarray(seeds, dtype=float).copy()
    cell = tracer.locate(p)
    length = np.zeros(len(p))
    reached = np.zeros(len(p), dtype=bool)
    active = np.flatnonzero(cell >= 0)
    for _ in range(int(MAX_LENGTH * muscle_length / h) + 1):
        if not len(active):
            break
        start = p[active]
        d = direction[cell[active]]
        q = start + h * d
        step = np.full(len(active), h)
        done = np.zeros(len(active), dtype=bool)
        for origin, n, tree, reach in sheets:
            before = section.signed_distance(start, origin, n)
            after = section.signed_distance(q, origin, n)
            crossing = (before * after <= 0) & (before != 0) & ~done
            t = np.where(crossing, before / np.where(crossing, before - after, 1.0), 1.0)
            crossing &= tree.query(start + t[:, None] * (q - start))[0] <= reach
            step = np.where(crossing, t * h, step)
            done |= crossing
        q_cell = tracer.locate(q)
        lost = np.zeros(len(active), dtype=bool)
        left = np.flatnonzero((q_cell < 0) & ~done)
        if len(left):
            inside, outside = start[left], q[left]
            for _ in range(20):
                middle = 0.5 * (inside + outside)
                found = tracer.locate(middle) >= 0
                inside = np.where(found[:, None], middle, inside)
                outside = np.where(found[:, None], outside, middle)
            facet = exits.query(inside)[1]
            travelled = np.linalg.norm(inside - start[left], axis=1)
            out = exterior_insertion[facet]
            done[left[out]] = True
            step[left[out]] = travelled[out]
            wall = left[~out]
            n = normal[facet[~out]]
            along = d[wall] - np.einsum("ij,ij->i", d[wall], n)[:, None] * n
            size = np.linalg.norm(along, axis=1)
            slid = inside[~out] + (h - travelled[~out])[:, None] * along / np.maximum(size, 1e-300)[:, None]
            # pushed off the wall, further where the slid point fell outside (an edge, a concave fold)
            q_wall, cell_wall = slid, np.full(len(wall), -1)
            for base, push in ((slid, 1e-3), (slid, 0.05), (slid, 0.3), (inside[~out], 0.05)):
                retry = cell_wall < 0
                q_wall[retry] = base[retry] - push * h * n[retry]
                cell_wall[retry] = tracer.locate(q_wall[retry])
            q[wall] = q_wall
            q_cell[wall] = cell_wall
            step[wall] = travelled[~out] + np.linalg.norm(q_wall - inside[~out], axis=1)
            lost[wall] = (cell_wall < 0) | (size < 1e-6)
        reached[active[done]] = True
        length[active] += step
        p[active] = q
        cell[active] = q_cell
        active = active[~(done | lost)]
    return length, reached


# ------------------------------------------------------------------------------- result


@dataclasses.dataclass
class PennateFibers:
    """The fibres of one geometry and how they were made."""

    a0: fem.Function
    speed: fem.Function
    origin: Selection
    insertion: Selection
    frame: Frame
    phi: fem.Function
    gradient: np.ndarray  # owned cells' ∇φ
    volume: np.ndarray

    def tags(self) -> tuple[dmesh.MeshTags, dmesh.MeshTags]:
        """(facet tags, cell tags) of the patches: `ORIGIN_TAG`, `INSERTION_TAG` (module docstring)."""
        return tag_patches(self.frame, self.origin, self.insertion)


def compute(geometry: geo.Geometry, origin: str | Patch = DEFAULT_ORIGIN,
            insertion: str | Patch = DEFAULT_INSERTION) -> PennateFibers:
    """The pennate fibres of ``geometry`` between two patches (specifications or parsed).
    InputError on every rank for a malformed, empty or overlapping patch. Collective."""
    origin = parse(origin, "--origin") if isinstance(origin, str) else origin
    insertion = parse(insertion, "--insertion") if isinstance(insertion, str) else insertion
    frame = Frame(geometry)
    o = select(frame, origin, "--origin")
    i = select(frame, insertion, "--insertion")
    check_apart(frame, o, i)
    phi = potential(geometry, frame, o, i)
    gradient, volume = cell_gradients(frame, phi)
    a0, speed = nodal_fibers(frame, gradient, volume)
    return PennateFibers(a0, speed, o, i, frame, phi, gradient, volume)


def _in_plane_facets(frame: Frame, selection: Selection) -> np.ndarray:
    """Local facets (owned) lying in a section's plane and carrying its triangles (filters applied)."""
    mesh = frame.geometry.mesh
    tdim = mesh.topology.dim
    nfacets = mesh.topology.index_map(tdim - 1).size_local
    c2f = mesh.topology.connectivity(tdim, tdim - 1)
    found = []
    scale = np.abs(frame.cell_x).max(initial=1.0)
    for cell, tri in zip(selection.cells, selection.triangles):
        for f in c2f.links(cell):
            if f < nfacets:
                corners = mesh.geometry.x[dmesh.entities_to_geometry(mesh, tdim - 1, np.array([f], dtype=np.int32))[0]]
                if np.allclose(np.sort(corners, axis=0), np.sort(tri, axis=0), atol=1e-12 * scale):
                    found.append(f)
    return np.unique(np.array(found, dtype=np.int32))


def tag_patches(frame: Frame, origin: Selection, insertion: Selection) -> tuple[dmesh.MeshTags, dmesh.MeshTags]:
    """Facet tags: the boundary facets of each patch and the mesh facets its sections run
    along; cell tags: the cells a section cuts through (module docstring)."""
    mesh = frame.geometry.mesh
    tdim = mesh.topology.dim
    facets, facet_values, cells, cell_values = [], [], [], []
    for tag, sel in ((ORIGIN_TAG, origin), (INSERTION_TAG, insertion)):
        along = _in_plane_facets(frame, sel)
        chosen = np.unique(np.concatenate([frame.facets[sel.facets], along]))
        facets.append(chosen)
        facet_values.append(np.full(len(chosen), tag, dtype=np.int32))
        cut = np.unique(sel.cells)
        cells.append(cut)
        cell_values.append(np.full(len(cut), tag, dtype=np.int32))

    def meshtags(dim, entities, values):
        entities, values = np.concatenate(entities), np.concatenate(values)
        order = np.argsort(entities, kind="stable")
        return dmesh.meshtags(mesh, dim, entities[order].astype(np.int32), values[order])

    return meshtags(tdim - 1, facets, facet_values), meshtags(tdim, cells, cell_values)


def _gather(comm, *arrays):
    parts = comm.gather(arrays, root=0)
    if comm.rank != 0:
        return None
    return [np.concatenate(p) for p in zip(*parts)]


def statistics(result: PennateFibers) -> dict:
    """The architecture of pennate fibres (`architecture`), with the patches' areas."""
    stats = architecture(result.frame, result.a0, result.gradient, result.origin, result.insertion)
    return {**stats, "origin_area_mm2": result.origin.area / geo.MM**2,
            "insertion_area_mm2": result.insertion.area / geo.MM**2}


def stokes_statistics(geometry: geo.Geometry, a0: fem.Function) -> dict:
    """`architecture` of a fibre field from end to end (the Stokes fibres): streamlines of
    the cells' mean fibre from the inflow end ``ends[0]`` to the outflow end ``ends[1]``."""
    frame = Frame(geometry)
    ends = [select(frame, parse(f"tags:{tag}"), "ends") for tag in geometry.ends]
    dofs = a0.function_space.dofmap.list[: len(frame.cell_x)]
    direction = a0.x.array.reshape(-1, 3)[dofs].mean(axis=1)
    return architecture(frame, a0, direction, *ends)


def architecture(frame: Frame, a0: fem.Function, direction: np.ndarray, origin: Selection,
                 insertion: Selection) -> dict:
    """Cells, vertices, the pennation angle (°, module docstring) and fascicle length (mm)
    distributions (mean and `PERCENTILES`), the share of the origin area whose streamline
    of ``direction`` (owned cells, piecewise constant) reached the insertion, and the
    statistics of `hyper.fem.fibers`. Collective; every rank gets the numbers."""
    geometry = frame.geometry
    comm = frame.comm
    cells = fibers.cell_fibers(geometry, a0)
    o, i = origin, insertion
    # seeds: the centroids of the origin's triangles, a boundary one nudged into its cell,
    # a section's on both sides (fibres leave a sheet both ways), each half its area
    f_seed = frame.facet_x[o.facets].mean(axis=1)
    f_seed = f_seed + 1e-6 * (frame.facet_cell_centroid[o.facets] - f_seed)
    t_seed = o.triangles.mean(axis=1)
    t_normal = np.zeros_like(t_seed)
    for origin_pt, normal in o.planes:
        t_normal[np.abs(section.signed_distance(t_seed, origin_pt, normal)) < 1e-9] = normal
    eps = 1e-6 * (frame.high - frame.low)
    seeds = np.concatenate([f_seed, t_seed + eps * t_normal, t_seed - eps * t_normal])
    areas = np.concatenate([frame.facet_area[o.facets], 0.5 * o.triangle_area, 0.5 * o.triangle_area])
    gathered = _gather(comm, frame.cell_x, direction)
    seeds_all = _gather(comm, seeds, areas)
    ext = _gather(comm, frame.facet_x, frame.facet_cell_centroid, i.facets)
    tri = [_gather(comm, i.triangles[np.abs(section.signed_distance(i.triangles.mean(axis=1), pt, n)) < 1e-9])
           for pt, n in i.planes]
    stats = None
    if comm.rank == 0:
        _, fiber, volume = cells
        angle = np.degrees(np.arccos(np.clip(np.abs(fiber @ frame.axis), 0.0, 1.0)))
        stats = {"cells": len(volume), "vertices": int(geometry.mesh.topology.index_map(0).size_global),
                 **weighted_summary(angle, volume, "pennation_deg")}
        cell_x, field = gathered
        seed_x, seed_area = seeds_all
        length, reached = fascicle_lengths(cell_x, field, seed_x, *ext, i.planes, [t[0] for t in tri],
                                           frame.high - frame.low)
        stats["fascicles"] = len(seed_x)
        stats["fascicles_reached_share"] = float(seed_area[reached].sum() / seed_area.sum())
        if reached.any():
            stats.update(weighted_summary(length[reached] / geo.MM, seed_area[reached], "fascicle_mm"))
    stats = comm.bcast(stats, root=0)
    stats["max_norm_error"] = fibers.max_norm_error(a0)
    stats["share_within_30deg"] = fibers.aligned_share(geometry, a0, frame.axis)
    return stats


def patch_facets(result: PennateFibers) -> dict[str, np.ndarray] | None:
    """The tagged facets of each patch as mesh file node triples (sorted rows), on rank 0."""
    frame = result.frame
    facet_tags, _ = result.tags()
    mesh = frame.geometry.mesh
    out = {}
    for name, tag in (("origin_facets", ORIGIN_TAG), ("insertion_facets", INSERTION_TAG)):
        facets = facet_tags.find(tag)
        nodes = frame.file_node[dmesh.entities_to_geometry(mesh, mesh.topology.dim - 1, facets)]
        parts = frame.comm.gather(np.sort(nodes, axis=1).reshape(-1, 3), root=0)
        if frame.comm.rank == 0:
            rows = np.concatenate(parts)
            out[name] = rows[np.lexsort(rows.T[::-1])] if len(rows) else rows
    return out if frame.comm.rank == 0 else None


def store(path: str | Path, result: PennateFibers, stats: dict, **attrs) -> None:
    """Write the fibres as a fibre file (`hyper.fem.fibers`'s format, its datasets node,
    a0, x, speed) with the patches' facets (``origin_facets``, ``insertion_facets``:
    mesh file node indices), the method, the patches and the statistics as attributes.
    Atomic, on rank 0. Collective."""
    geometry = result.frame.geometry
    data = fibers.gather_nodal(result.a0, result.speed)
    facets = patch_facets(result)
    if geometry.comm.rank == 0:
        numbers = {k: v for k, v in stats.items() if v is not None}
        write_series(path, {**data, **facets},
                     attrs={"geometry": geometry.name, "kind": KIND, "method": METHOD, "element": fibers.ELEMENT,
                            "reference": REFERENCE, "origin": result.origin.patch.spec,
                            "insertion": result.insertion.patch.spec, "origin_tag": ORIGIN_TAG,
                            "insertion_tag": INSERTION_TAG, "line_of_action": "first principal axis of the vertices",
                            "coordinates": "m", "ranks": geometry.comm.size, **numbers, **attrs})
    geometry.comm.barrier()
