"""From a muscle's surface (STL) to a tagged tetrahedral mesh with its fibres:

    hyper mesh SURFACE.stl --output meshes/NAME/ [--unit mm|m] [--cells N]

writes the layout of a shipped mesh folder (geometry.py), so that ``--geometry NAME``
runs it once the folder is in the project's meshes/:

    NAME.xdmf, NAME.h5   the tetrahedra (millimetres, mesh "Grid") and the facet tags
                         "ft_small": 1 the origin, 2 the insertion, 3 the lateral surface
    fibers.h5            the Stokes-flow fibres (hyper.fibers), as `hyper fibers` writes them
    mesh.json            source, unit, end rule, quality and the mesh statistics (hyper.meshstats)
    NAME.png             the surface with its ends coloured, and fibre glyphs on a mid-slice

Steps, each of which stops the job with one ``error:`` line (exit 2) and nothing written:

1. Reading: binary or ASCII STL; the vertex order of each triangle is its orientation
   (the stored normals are ignored); equal coordinates are one vertex. ``--unit``
   must give the surface a muscle's length (run.MUSCLE_LENGTH_M), as --mesh-unit must.
2. Surface checks: every edge shared by exactly two triangles (a hole otherwise, or a
   non-manifold edge), one connected body, every shared edge traversed in opposite
   directions by its two triangles (consistent orientation), the enclosed volume
   positive (normals outward), and no two triangles without a common vertex crossing
   (an edge of one through the other; pairs that share a vertex are not tested).
3. Tetrahedra by gmsh (Delaunay, then Netgen's optimizer, which lifts the minimum
   dihedral angle of the TA from 4-5° to 10-12°, as in the shipped meshes). Why gmsh:
   a PyPI wheel that builds everywhere; it remeshes the surface to the target size with
   its nodes on the STL's own triangles (sharp rims such as a cylinder's survive: feature
   angle FEATURE_DEG); and it is fast (an 8000-cell muscle in about 3 s). fTetWild
   (pytetwild), which made the shipped meshes, is more robust to broken surfaces, but
   step 2 refuses those, and it is slower. The size is
   chosen for ``--cells`` (up to CELL_CORRECTIONS more while the count is off by over 10 %),
   and falls to a tenth of it at the two tips (`extremes` along the axis of step 4),
   which the target size alone rounds off (TIP_SIZE): the length of all 11 meshes is
   then within 0.05 % of their STL's (it was up to 4.5 % short).
   Volume: gmsh's surface edges are chords of the STL, so the mesh would be 1.2-1.8 %
   smaller than the surface at 8000 cells; the boundary nodes are then moved outward
   along their normals by one distance (0.09-0.14 mm on the Visible Human surfaces,
   `fill_surface`) that gives the mesh the STL's enclosed volume.
   Quality: every cell positive with volume above 1e-9 of the bounding box's; the
   minimum dihedral angle is reported.
4. Ends, the rule: project the vertices on the first principal axis (``--axis``
   replaces it); an end is the boundary facets whose three vertices lie within
   ``--end-band`` (a share of the length, 3.75 %) of an extreme of the projection,
   except facets parallel to the axis (normal within PARALLEL_DEG of perpendicular to
   it: lateral surface, as a cylinder's side is). The origin, tag 1, is the end further
   along ``--origin-toward`` (+z: proximal in the Visible Human frame); tag 2 the other.
   The band reproduces the shipped tags: in all 12 shipped meshes the tagged facets are
   those whose vertices are within 3.6-3.75 % of an extreme, whatever their normals (up
   to 40 % of an end's area has normals that point inward along the axis, so a rule on
   normals would not reproduce them). Refused: an end without facets, no lateral surface
   left, a band of half the length or more (the ends would touch; below it they cannot).
5. Fibres: the Stokes flow of hyper.fibers (inflow at tag 1); statistics of hyper.meshstats.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import struct
import sys
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
import numpy as np

from hyper.commands import cli
from hyper.core.params import InputError

UNITS_MM = {"mm": 1.0, "m": 1.0e3}  # millimetres per unit: the folder stores millimetres, as the shipped ones
MUSCLE_LENGTH_MM = (10.0, 1000.0)  # run.MUSCLE_LENGTH_M: a muscle's longest side
DEFAULT_CELLS = 8000  # the shipped meshes have 6707-9668
END_BAND = 0.0375  # share of the length; the shipped tags' band (module docstring, step 4)
PARALLEL_DEG = 1.0
# Surface edges sharper than this stay edges when gmsh remeshes (a cylinder's rim is 90°);
# at 30-40° gmsh could not parametrize the patches of TA_VHM_Right.
FEATURE_DEG = 60.0
ORIGIN_TOWARD = (0.0, 0.0, 1.0)
MIN_VOLUME = 1e-9  # of the bounding box's volume: a cell below it is degenerate
ARRAYS = ("x", "tets", "facets", "tags")  # what `build` returns besides numbers
OFFSET_STEPS, OFFSET_RTOL = 5, 1e-9  # fill_surface: Newton steps, and the volume's relative tolerance
CELLS_PER_H3 = 9.0  # cells per volume/h³ after optimization, measured on the TA: the first guess of h
# Near the two tips the size falls to TIP_SIZE of the target, growing back over TIP_REACH
# of the length: at the target size alone gmsh's remeshed surface rounds the thin tips off
# (TA_VHF_Right 4.5 % short of its STL). Never below TIP_EDGE of the STL's median edge,
# though: finer cells find no more shape than the surface has, and at a coarse surface's
# tips they made slivers.
TIP_SIZE, TIP_REACH, TIP_EDGE = 0.1, 0.1, 0.25
TIP_BAND = 0.005  # share of the length: the points that make a tip (`extremes`)
CELL_CORRECTIONS = 4  # meshes after the first, while the count is off --cells by over 10 %


# ---------------------------------------------------------------------------- reading


def read_stl(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(points (n, 3) float64, triangles (m, 3) int64) of a binary or ASCII STL, equal
    coordinates merged into one vertex."""
    data = path.read_bytes()
    corners = None
    if len(data) >= 84:
        count = struct.unpack("<I", data[80:84])[0]
        if len(data) == 84 + 50 * count and count > 0:
            record = np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attribute", "<u2")])
            corners = np.frombuffer(data, dtype=record, count=count, offset=84)["corners"].astype(np.float64)
    if corners is None:
        corners = read_ascii(path, data)
    points, inverse = np.unique(corners.reshape(-1, 3), axis=0, return_inverse=True)
    return points, inverse.reshape(-1, 3).astype(np.int64)


def read_ascii(path: Path, data: bytes) -> np.ndarray:
    """The corners (m, 3, 3) of an ASCII STL; InputError if the file is not one."""
    try:
        text = data.decode("ascii")
    except UnicodeDecodeError:
        text = ""
    words = text.split()
    if not words or words[0] != "solid" or "endsolid" not in words:
        raise InputError(f"{path}: not an STL file (neither binary: 84-byte header and 50 bytes a triangle, "
                         "nor ASCII: 'solid … endsolid')")
    vertices = [i for i, word in enumerate(words) if word == "vertex"]
    try:
        corners = np.array([[float(w) for w in words[i + 1:i + 4]] for i in vertices])
    except ValueError:
        raise InputError(f"{path}: ASCII STL with a vertex that is not three numbers") from None
    if len(corners) == 0 or len(corners) % 3:
        raise InputError(f"{path}: ASCII STL with {len(corners)} vertices, not three a facet")
    return corners.reshape(-1, 3, 3)


def check_size(path: Path, points: np.ndarray, unit: str) -> None:
    """The surface's longest bounding-box side, in ``unit``, must be a muscle's length."""
    side = float(np.ptp(points, axis=0).max()) * UNITS_MM[unit]
    low, high = MUSCLE_LENGTH_MM
    if not low <= side <= high:
        raise InputError(f"{path}: the surface is {side / UNITS_MM[unit]:g} {unit} long (longest side of its "
                         f"bounding box), i.e. {side:g} mm, outside the {low:g}-{high:g} mm of a muscle: its "
                         f"length unit is not {unit!r}; declare it with --unit ({' or '.join(UNITS_MM)})")


# ---------------------------------------------------------------------- surface checks


def where(points: np.ndarray) -> str:
    """The mean of some points (any shape ending in 3), for a message."""
    return "(" + ", ".join(f"{c:.4g}" for c in np.reshape(points, (-1, 3)).mean(axis=0)) + ")"


def check_surface(path: Path, points: np.ndarray, triangles: np.ndarray) -> None:
    """InputError naming the first problem of the surface (module docstring, step 2)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    degenerate = (triangles[:, 0] == triangles[:, 1]) | (triangles[:, 1] == triangles[:, 2]) | (
        triangles[:, 2] == triangles[:, 0])
    if degenerate.any():
        raise InputError(f"{path}: {degenerate.sum()} triangles with a repeated vertex, e.g. at "
                         f"{where(points[triangles[degenerate][0]])}")
    directed = np.stack([triangles, np.roll(triangles, -1, axis=1)], axis=2).reshape(-1, 2)
    edges, edge_of, count = np.unique(np.sort(directed, axis=1), axis=0, return_inverse=True, return_counts=True)
    if (count == 1).any():
        open_edges = edges[count == 1]
        raise InputError(f"{path}: the surface is not closed: a hole bounded by {len(open_edges)} edges that "
                         f"belong to one triangle only, e.g. at {where(points[open_edges[0]])}")
    if (count > 2).any():
        raise InputError(f"{path}: {np.sum(count > 2)} edges shared by more than two triangles (not a manifold), "
                         f"e.g. at {where(points[edges[count > 2][0]])}")
    # Triangles are connected through their shared edges: one component is one body.
    owner = np.repeat(np.arange(len(triangles)), 3)
    order = np.argsort(edge_of.ravel(), kind="stable")
    pairs = owner[order].reshape(-1, 2)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(triangles),) * 2)
    bodies, label = connected_components(graph, directed=False)
    if bodies > 1:
        sizes = np.bincount(label)
        raise InputError(f"{path}: {bodies} separate bodies ({', '.join(map(str, sorted(sizes, reverse=True)))} "
                         f"triangles), the second at {where(points[triangles[label == np.argsort(sizes)[-2]]])}; "
                         "mesh one muscle at a time")
    # On a consistently oriented surface each directed edge occurs once (its neighbour runs it backwards).
    runs, same_way = np.unique(directed, axis=0, return_counts=True)
    if (same_way > 1).any():
        bad = runs[same_way > 1]
        raise InputError(f"{path}: inconsistently oriented: {len(bad)} edges are traversed in the same direction "
                         f"by both their triangles (a flipped triangle or patch), e.g. at {where(points[bad[0]])}")
    volume = enclosed_volume(points, triangles)
    if volume <= 0:
        raise InputError(f"{path}: the triangles are oriented inward (enclosed volume {volume:.4g} < 0); "
                         "reverse the vertex order of every triangle")
    crossing = self_intersections(points, triangles)
    if len(crossing):
        raise InputError(f"{path}: the surface intersects itself: {len(crossing)} pairs of triangles cross, "
                         f"e.g. at {where(points[triangles[crossing[0]].reshape(-1)])}")


def enclosed_volume(points: np.ndarray, triangles: np.ndarray) -> float:
    """The signed volume inside a closed surface (divergence theorem): > 0 for outward normals."""
    a, b, c = (points[triangles[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def self_intersections(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Pairs (k, 2) of triangles without a common vertex where an edge of one crosses the other.

    Candidates: pairs whose bounding spheres (about the centroids) overlap, from a k-d tree.
    """
    from scipy.spatial import cKDTree

    corners = points[triangles]
    centroid = corners.mean(axis=1)
    radius = np.linalg.norm(corners - centroid[:, None], axis=2).max()
    pairs = cKDTree(centroid).query_pairs(2.0 * radius, output_type="ndarray")
    shared = (triangles[pairs[:, 0], :, None] == triangles[pairs[:, 1], None, :]).any(axis=(1, 2))
    pairs = pairs[~shared]
    hit = np.zeros(len(pairs), dtype=bool)
    for first, second in ((0, 1), (1, 0)):
        tri = corners[pairs[:, second]]
        for i in range(3):
            start = corners[pairs[:, first], i]
            end = corners[pairs[:, first], (i + 1) % 3]
            hit |= segment_hits_triangle(start, end, tri)
    return pairs[hit]


def segment_hits_triangle(start, end, tri) -> np.ndarray:
    """Möller–Trumbore for many segments and triangles at once: does start→end meet the triangle?"""
    direction = end - start
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, p)
    scale = np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1) * np.linalg.norm(direction, axis=1)
    ok = np.abs(det) > 1e-12 * scale  # a segment parallel to the plane does not cross it
    det = np.where(ok, det, 1.0)
    s = start - tri[:, 0]
    u = np.einsum("ij,ij->i", s, p) / det
    q = np.cross(s, e1)
    v = np.einsum("ij,ij->i", direction, q) / det
    t = np.einsum("ij,ij->i", e2, q) / det
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)


# ------------------------------------------------------------------------ tetrahedra


def tetrahedralize(points_mm: np.ndarray, triangles: np.ndarray, cells: int,
                   axis=None) -> tuple[np.ndarray, np.ndarray]:
    """(x (n, 3) mm, tetrahedra (m, 4)) near ``cells`` cells inside the surface (gmsh),
    finer at its two tips (`extremes` along ``axis``; by default the first principal axis
    of its vertices, as find_ends takes the mesh's)."""
    volume = enclosed_volume(points_mm, triangles)
    tips = extremes(points_mm, axis)
    corners = points_mm[triangles]
    finest = TIP_EDGE * float(np.median(np.linalg.norm(corners - corners[:, [1, 2, 0]], axis=2)))
    reach = TIP_REACH * float(np.linalg.norm(tips[1] - tips[0]))
    size = (CELLS_PER_H3 * volume / cells) ** (1.0 / 3.0)
    x, tets = gmsh_volume(points_mm, triangles, size, tips, finest, reach)
    # The count is not cubic in 1/h (the surface and the tips count too): the exponent
    # is measured from the last two meshes, a secant on log(count) against log(h).
    slope, tried = -3.0, [(size, len(tets))]
    for _ in range(CELL_CORRECTIONS):
        if abs(len(tets) / cells - 1.0) <= 0.1:
            break
        if len(tried) > 1:
            (h0, n0), (h1, n1) = tried[-2:]
            if h1 != h0 and n1 != n0:
                slope = min(-1.0, math.log(n1 / n0) / math.log(h1 / h0))
        size *= (cells / len(tets)) ** (1.0 / slope)
        x, tets = gmsh_volume(points_mm, triangles, size, tips, finest, reach)
        tried.append((size, len(tets)))
    return x, tets


def principal_axis(x: np.ndarray) -> np.ndarray:
    _, vectors = np.linalg.eigh(np.cov((x - x.mean(axis=0)).T))
    return vectors[:, -1]


def extremes(x: np.ndarray, axis=None) -> np.ndarray:
    """The two tips of ``x`` along ``axis`` (the principal axis by default): the mean of the
    points within TIP_BAND of the length from each extreme, the extreme point of a tapered
    end, the middle of a flat one (a cylinder's cap, not a point of its rim)."""
    along = x @ (principal_axis(x) if axis is None else np.asarray(axis, dtype=float))
    width = TIP_BAND * (along.max() - along.min())
    return np.array([x[along <= along.min() + width].mean(axis=0), x[along >= along.max() - width].mean(axis=0)])


def gmsh_volume(points: np.ndarray, triangles: np.ndarray, size: float, tips: np.ndarray, finest: float,
                reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedra of the surface at ``size``, falling to max(TIP_SIZE size, ``finest``) at
    ``tips`` and back to ``size`` within ``reach`` (mm) of them."""
    import gmsh

    tip_size = min(size, max(TIP_SIZE * size, finest))

    gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.model.add("surface")
        surface = gmsh.model.addDiscreteEntity(2)
        gmsh.model.mesh.addNodes(2, surface, np.arange(1, len(points) + 1), points.ravel())
        gmsh.model.mesh.addElementsByType(surface, 2, [], (triangles + 1).ravel())
        gmsh.model.mesh.classifySurfaces(math.radians(FEATURE_DEG), True, True, math.pi)
        gmsh.model.mesh.createGeometry()
        loop = gmsh.model.geo.addSurfaceLoop([tag for _, tag in gmsh.model.getEntities(2)])
        gmsh.model.geo.addVolume([loop])
        points_at = [gmsh.model.geo.addPoint(*tip) for tip in tips]
        gmsh.model.geo.synchronize()
        field = gmsh.model.mesh.field
        distance = field.add("Distance")
        field.setNumbers(distance, "PointsList", points_at)
        ramp = field.add("Threshold")
        field.setNumber(ramp, "InField", distance)
        field.setNumber(ramp, "SizeMin", tip_size)
        field.setNumber(ramp, "SizeMax", size)
        field.setNumber(ramp, "DistMin", 0.0)
        field.setNumber(ramp, "DistMax", reach)
        field.setAsBackgroundMesh(ramp)
        # the field alone sets the size: not the STL's own points, nor the surface's spacing
        gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
        gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
        gmsh.option.setNumber("Mesh.MeshSizeMin", tip_size)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.model.mesh.generate(3)
        gmsh.model.mesh.optimize("Netgen")
        node_tags, coords, _ = gmsh.model.mesh.getNodes()
        _, tet_nodes = gmsh.model.mesh.getElementsByType(4)
    except Exception as err:  # gmsh raises a bare Exception with its last error
        raise InputError(f"gmsh could not mesh the surface: {err}") from None
    finally:
        gmsh.finalize()
    position = np.full(int(node_tags.max()) + 1, -1, dtype=np.int64)
    position[node_tags] = np.arange(len(node_tags))
    tets = position[np.asarray(tet_nodes, dtype=np.int64).reshape(-1, 4)]
    used, compact = np.unique(tets, return_inverse=True)
    return coords.reshape(-1, 3)[used], compact.reshape(-1, 4)


def fill_surface(x: np.ndarray, tets: np.ndarray, volume: float) -> tuple[np.ndarray, float]:
    """(x with the boundary nodes moved outward along their normals by one common distance,
    that distance in mm) so that the mesh's volume is ``volume`` (the STL's).

    Why: gmsh puts its surface nodes on the STL, so its surface edges are chords and the
    mesh is inscribed in the STL, 1.2-1.8 % short of its volume at 8000 cells (finer
    surface meshes cost cells: sizing by curvature gave 10⁵ cells). One offset of about
    0.1 mm, a fiftieth of an edge, removes that bias without changing the cells' shape.
    The volume is cubic in the offset: Newton's method from 0 (two or three steps).
    """
    tets = np.where((signed_volumes(x, tets) < 0)[:, None], tets[:, [0, 2, 1, 3]], tets)
    facets = boundary_facets(tets)
    corners = x[facets]
    area_normal = 0.5 * np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal = np.zeros_like(x)
    for i in range(3):
        np.add.at(normal, facets[:, i], area_normal)
    nodes = np.unique(facets)
    normal = normal[nodes] / np.linalg.norm(normal[nodes], axis=1)[:, None]
    offset, moved = 0.0, x
    for _ in range(OFFSET_STEPS):
        moved = x.copy()
        moved[nodes] += offset * normal
        c = moved[facets]
        gap = volume - enclosed_volume(moved, facets)
        if abs(gap) <= OFFSET_RTOL * volume:
            break
        # dV/d(offset) = the surface's area-weighted mean of n_vertex·n_facet, times its area
        area = 0.5 * np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
        shift = np.zeros_like(x)
        shift[nodes] = normal
        slope = float(np.einsum("fij,fj->", shift[facets], area) / 3.0)
        offset += gap / slope
    return moved, offset


def signed_volumes(x: np.ndarray, tets: np.ndarray) -> np.ndarray:
    a = x[tets]
    return np.linalg.det(a[:, 1:] - a[:, :1]) / 6.0


def min_dihedral_deg(x: np.ndarray, tets: np.ndarray) -> float:
    """The smallest angle between two faces of a tetrahedron, over all cells."""
    a = x[tets]
    faces = ((1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1))  # face i is opposite vertex i
    normals = []
    for i, j, k in faces:
        n = np.cross(a[:, j] - a[:, i], a[:, k] - a[:, i])
        normals.append(n / np.linalg.norm(n, axis=1)[:, None])
    smallest = np.pi
    for f in range(4):
        for g in range(f + 1, 4):
            cosine = np.einsum("ij,ij->i", normals[f], normals[g])
            # the dihedral angle is π minus the angle between the two outward face normals
            smallest = min(smallest, float(np.min(np.pi - np.arccos(np.clip(cosine, -1.0, 1.0)))))
    return math.degrees(smallest)


def check_quality(x: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, dict]:
    """Tetrahedra with positive orientation, and the quality numbers; InputError for degenerate cells."""
    volume = signed_volumes(x, tets)
    if np.median(volume) < 0:
        tets, volume = tets[:, [0, 2, 1, 3]], -volume
    box = float(np.prod(np.ptp(x, axis=0)))
    bad = volume <= MIN_VOLUME * box
    if bad.any():
        raise InputError(f"the mesher made {bad.sum()} inverted or near-zero-volume cells, e.g. at "
                         f"{where(x[tets[bad][0]])}; try another --cells")
    return tets, {"min_dihedral_deg": min_dihedral_deg(x, tets), "min_cell_volume_mm3": float(volume.min()),
                  "max_cell_volume_mm3": float(volume.max())}


# ------------------------------------------------------------------------------- ends


def boundary_facets(tets: np.ndarray) -> np.ndarray:
    """The exterior triangles of a tetrahedral mesh, oriented outward (positive cells)."""
    faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]])
    _, first, count = np.unique(np.sort(faces, axis=1), axis=0, return_index=True, return_counts=True)
    return faces[first[count == 1]]


def find_ends(x: np.ndarray, facets: np.ndarray, *, band: float = END_BAND, axis=None,
              origin_toward=ORIGIN_TOWARD) -> tuple[np.ndarray, dict]:
    """The tag of each outward boundary facet (1 origin, 2 insertion, 3 lateral) by the
    rule of the module docstring, and what the rule used; InputError where it fails."""
    # Below half the length no vertex can be in both bands, so the ends never touch.
    if not 0.0 < band < 0.5:
        raise InputError(f"--end-band: expected a share of the length in (0, 0.5), got {band:g}: the two ends "
                         "would touch")
    centre = x.mean(axis=0)
    axis = principal_axis(x) if axis is None else np.asarray(axis, dtype=float)
    if not np.linalg.norm(axis) > 0:
        raise InputError("--axis: expected a nonzero direction")
    axis = axis / np.linalg.norm(axis)
    toward = np.asarray(origin_toward, dtype=float)
    if abs(float(axis @ toward)) < 1e-9 * np.linalg.norm(toward):
        raise InputError(f"--origin-toward {tuple(toward)} is perpendicular to the axis {tuple(axis.round(4))}: "
                         "it cannot tell the origin from the insertion")
    if axis @ toward < 0:
        axis = -axis  # the origin is now at the high end of the projection
    along = (x - centre) @ axis
    low, high = along.min(), along.max()
    width = band * (high - low)
    corners = x[facets]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    side = np.abs(normal @ axis) < math.sin(math.radians(PARALLEL_DEG))
    tags = np.full(len(facets), 3, dtype=np.int32)
    tags[(along[facets] >= high - width).all(axis=1) & ~side] = 1
    tags[(along[facets] <= low + width).all(axis=1) & ~side] = 2
    for tag, name in ((1, "origin"), (2, "insertion")):
        if not (tags == tag).any():
            raise InputError(f"no {name} (tag {tag}): no boundary facet lies within --end-band {band:g} of the "
                             f"length from that end of the axis {tuple(axis.round(4))}; widen the band or give --axis")
    if not (tags == 3).any():
        raise InputError("the two ends cover the whole surface: no lateral surface is left; narrow --end-band")
    return tags, {"axis": axis.tolist(), "length_mm": float(high - low), "band": band,
                  "origin_toward": toward.tolist(), "parallel_deg": PARALLEL_DEG}


def facet_areas(x: np.ndarray, facets: np.ndarray) -> np.ndarray:
    corners = x[facets]
    return 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)


# ------------------------------------------------------------------------------ output


def write_xdmf(comm, path: Path, x_mm: np.ndarray, tets: np.ndarray, facets: np.ndarray, tags: np.ndarray) -> None:
    """The mesh ("Grid", millimetres) and its facet tags ("ft_small") as a shipped folder has them."""
    import basix.ufl
    import ufl
    from dolfinx import mesh as dmesh
    from dolfinx.graph import adjacencylist
    from dolfinx.io import XDMFFile
    from dolfinx.io.utils import distribute_entity_data

    if comm.rank != 0:
        x_mm, tets = np.empty((0, 3)), np.empty((0, 4), dtype=np.int64)
        facets, tags = np.empty((0, 3), dtype=np.int64), np.empty(0, dtype=np.int32)
    domain = ufl.Mesh(basix.ufl.element("Lagrange", "tetrahedron", 1, shape=(3,)))
    mesh = dmesh.create_mesh(comm, tets, domain, x_mm)
    mesh.name = "Grid"
    local_facets, local_tags = distribute_entity_data(mesh, 2, facets, tags.astype(np.int32))
    mesh.topology.create_connectivity(2, 3)
    facet_tags = dmesh.meshtags_from_entities(mesh, 2, adjacencylist(local_facets), local_tags.astype(np.int32))
    facet_tags.name = "ft_small"
    with XDMFFile(comm, str(path), "w") as xdmf:
        xdmf.write_mesh(mesh)
        xdmf.write_meshtags(facet_tags, mesh.geometry)


def figure(name: str, x_mm, facets, tags, centroid_m, fiber, axis):
    """Left: the surface seen across its axis, ends coloured; right: fibre glyphs on the mid-slab."""
    from matplotlib.collections import LineCollection, PolyCollection

    from hyper.runs.plot import pyplot

    plt = pyplot()
    centre = x_mm.mean(axis=0)
    across = np.linalg.svd((x_mm - centre) - np.outer((x_mm - centre) @ axis, axis), full_matrices=False)[2][0]
    depth = np.cross(axis, across)
    basis = np.vstack([axis, across, depth])
    p = (x_mm - centre) @ basis.T
    # As high as the muscle's side view needs: a fixed height left most of a long muscle's picture blank.
    aspect = np.ptp(p[:, 1]) / np.ptp(p[:, 0])
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 1.4 + 5.6 * aspect), layout="constrained")
    corners = p[facets]
    order = np.argsort(corners[:, :, 2].mean(axis=1))  # far facets first: the near ones cover them
    colours = np.array(["#c0392b", "#1f5f99", "#cccccc"])[tags[order] - 1]
    left.add_collection(PolyCollection(corners[order][:, :, :2], facecolors=colours, edgecolors="0.5",
                                       linewidths=0.1))
    left.autoscale()
    left.set_aspect("equal")
    left.set_title("surface: red origin (1), blue insertion (2), grey lateral (3)", fontsize=10)
    q = (centroid_m * 1e3 - centre) @ basis.T
    d = fiber @ basis.T
    slab = np.abs(q[:, 2]) < 0.08 * np.ptp(q[:, 2])
    glyph = 0.012 * np.ptp(q[:, 0])
    uv = d[slab][:, :2] / np.maximum(np.linalg.norm(d[slab][:, :2], axis=1), 1e-12)[:, None] * glyph
    angle = np.degrees(np.arccos(np.clip(np.abs(d[slab][:, 0]), 0.0, 1.0)))
    cmap, norm = plt.get_cmap("viridis"), plt.Normalize(0.0, 45.0)
    right.add_collection(LineCollection(np.stack([q[slab][:, :2] - uv, q[slab][:, :2] + uv], axis=1),
                                        colors=cmap(norm(angle)), linewidths=1.0))
    right.set_xlim(left.get_xlim())
    right.set_ylim(left.get_ylim())
    right.set_aspect("equal")
    right.set_title(f"Stokes fibres on the mid-slab ({slab.sum()} cells), colour: angle to the axis (0-45°)",
                    fontsize=10)
    for ax in (left, right):
        ax.set_xlabel("along the axis, toward the origin (mm)")
    left.set_ylabel("across (mm)")
    fig.suptitle(name)
    return fig


# -------------------------------------------------------------------------------- job


def parser() -> cli.Parser:
    p = cli.Parser("mesh", __doc__)
    p.add_argument("surface", type=Path, help="the muscle's closed surface (STL, binary or ASCII)")
    p.add_argument("--output", type=Path, required=True, help="the folder to write, meshes/NAME/; NAME is the "
                   "geometry's identifier")
    p.add_argument("--unit", choices=tuple(UNITS_MM), default="mm", help="length unit of the STL")
    p.add_argument("--cells", type=cli.integer(200, 2_000_000), default=DEFAULT_CELLS, help="target cell count")
    p.add_argument("--end-band", type=float, default=END_BAND, help="an end: the facets within this share of "
                   "the length from an extreme along the axis")
    p.add_argument("--axis", type=float, nargs=3, metavar=("X", "Y", "Z"), help="the muscle's long axis "
                   "(the first principal axis of the mesh vertices by default)")
    p.add_argument("--origin-toward", type=float, nargs=3, metavar=("X", "Y", "Z"), default=ORIGIN_TOWARD,
                   help="the origin (tag 1) is the end further along this direction")
    p.add_argument("--force", action="store_true", help="replace an existing output folder")
    return p


def build(args) -> dict:
    """Read, check, mesh and tag on rank 0 (module docstring, steps 1-4); the arrays in mm."""
    path = args.surface
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    start = time.perf_counter()
    points, triangles = read_stl(path)
    check_size(path, points, args.unit)
    check_surface(path, points, triangles)
    checked = time.perf_counter()
    points_mm = points * UNITS_MM[args.unit]
    x, tets = tetrahedralize(points_mm, triangles, args.cells, args.axis)
    x, offset = fill_surface(x, tets, enclosed_volume(points_mm, triangles))
    tets, quality = check_quality(x, tets)
    quality["surface_offset_mm"] = offset
    facets = boundary_facets(tets)
    tags, rule = find_ends(x, facets, band=args.end_band, axis=args.axis, origin_toward=args.origin_toward)
    areas = facet_areas(x, facets)
    return {"x": x, "tets": tets, "facets": facets, "tags": tags, "rule": rule, "quality": quality,
            "surface_triangles": len(triangles), "check_s": checked - start,
            "mesh_s": time.perf_counter() - checked,
            "end_area_mm2": [float(areas[tags == 1].sum()), float(areas[tags == 2].sum())],
            "sha256": hashlib.sha256(path.read_bytes()).hexdigest()}


def run(comm, args) -> int:
    from hyper.core.io import atomic_path, write_series
    from hyper.core.log import info
    from hyper.core.params import as_attributes
    from hyper.fem import fibers, meshstats
    from hyper.fem import geometry as geo
    from hyper.runs import plot

    out = args.output
    name = out.name
    if out.suffix or not name:
        raise InputError(f"--output {out}: expected a folder, meshes/NAME/")
    if out.exists() and not args.force:
        raise InputError(f"--output {out}: exists; give --force to replace it")
    built = error = None
    if comm.rank == 0:
        try:
            built = build(args)
        except InputError as err:
            error = str(err)
    error = comm.bcast(error, root=0)
    if error is not None:
        raise InputError(error)
    # The arrays stay on rank 0, which hands the cells to DOLFINx; every rank gets the rest.
    arrays = {k: built.pop(k) for k in ARRAYS} if comm.rank == 0 else dict.fromkeys(ARRAYS)
    built = comm.bcast(built, root=0)
    stage = out.with_name(name + ".partial")
    if comm.rank == 0:
        shutil.rmtree(stage, ignore_errors=True)
        stage.mkdir(parents=True)
    comm.barrier()
    try:
        start = time.perf_counter()
        write_xdmf(comm, stage / f"{name}.xdmf", *(arrays[k] for k in ARRAYS))
        geometry = geo.load_file(stage / f"{name}.xdmf", comm, name=name, scale=geo.MM)
        params = fibers.StokesParams()
        a0, speed = fibers.compute(geometry, params)
        stats = {**fibers.statistics(geometry, a0, speed), "solve_s": time.perf_counter() - start}
        data = fibers.gather_nodal(a0, speed)
        row = meshstats.statistics(geometry)
        cells = fibers.cell_fibers(geometry, a0)
        if comm.rank == 0:
            write_series(stage / fibers.FILE_NAME, data,
                         attrs={"geometry": name, "mesh": f"{name}/{name}.xdmf", "method": fibers.METHOD,
                                "element": fibers.ELEMENT, "reference": "Varvik et al. 2021; MODEL.md §5",
                                "inflow_tag": 1, "outflow_tag": 2, "lateral_tag": 3, "coordinates": "m",
                                "ranks": comm.size, **stats},
                         groups={"parameters": as_attributes(params)})
            record = {"source": str(args.surface), "source_sha256": built["sha256"], "unit": args.unit,
                      "mesher": f"gmsh {gmsh_version()}", "cells_target": args.cells,
                      "surface_triangles": built["surface_triangles"], "ends": built["rule"],
                      "end_area_mm2": built["end_area_mm2"], "quality": built["quality"],
                      "statistics": {k: v for k, v in row.items() if k != "geometry"},
                      "fibers": {k: float(v) for k, v in stats.items()},
                      "check_s": built["check_s"], "mesh_s": built["mesh_s"]}
            with atomic_path(stage / "mesh.json") as tmp:
                tmp.write_text(json.dumps(record, indent=2) + "\n")
            axis = np.asarray(built["rule"]["axis"])
            plot.save(figure(name, arrays["x"], arrays["facets"], arrays["tags"], cells[0], cells[1], axis),
                      stage / f"{name}.png", dpi=110)
            if out.exists():
                shutil.rmtree(out)
            os.replace(stage, out)
    finally:
        if comm.rank == 0:
            shutil.rmtree(stage, ignore_errors=True)
        comm.barrier()
    q = built["quality"]
    info(comm, f"{name}: {row['cells']} cells, {row['vertices']} vertices, min dihedral angle "
               f"{q['min_dihedral_deg']:.1f}°; volume {row['volume_cm3']:.2f} cm³, CSA0 {row['csa0_cm2']:.2f} cm², "
               f"length {row['length_cm']:.2f} cm; ends {built['end_area_mm2'][0]:.0f} and "
               f"{built['end_area_mm2'][1]:.0f} mm²; fibres within 30° of the axis "
               f"{100 * stats['share_within_30deg']:.1f} %; checks {built['check_s']:.1f} s, mesh "
               f"{built['mesh_s']:.1f} s, fibres {stats['solve_s']:.1f} s")
    info(comm, f"wrote {out}/")
    return cli.EXIT_OK


def gmsh_version() -> str:
    import gmsh

    return gmsh.__version__


main = cli.entry(parser, run, locks=lambda args: [args.output])

if __name__ == "__main__":
    sys.exit(main())
