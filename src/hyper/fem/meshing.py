"""From a muscle's surface (STL) to a tagged tetrahedral mesh with its fibres:

    hyper mesh SURFACE.stl --output meshes/NAME/ [--unit mm|m] [--cells N]

writes the layout of a shipped mesh folder (geometry.py), so that ``--geometry NAME``
runs it once the folder is in the project's meshes/:

    NAME.xdmf, NAME.h5   the tetrahedra (millimetres, mesh "Grid") and the facet tags
                         "ft_small": 1 the origin, 2 the insertion, 3 the lateral surface
    fibers.h5            the fibres (step 5), in `hyper fibers`'s format
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
   Then what gmsh can mesh at --cells (`check_meshable`): at least 8 triangles, a mean
   thickness of at least 0.3 cells, one long axis; gmsh runs in a process of its own,
   stopped after --gmsh-budget seconds.
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
4. Ends, the rule: project the vertices on the first principal axis of the STL surface
   (``--end-rule surface``; of the mesh vertices under ``vertices``; ``--axis`` replaces
   it); an end is the boundary facets whose three vertices lie within
   ``--end-band`` (a share of the length, 3.75 %) of an extreme of the projection,
   except facets parallel to the axis (normal within PARALLEL_DEG of perpendicular to
   it: lateral surface, as a cylinder's side is). The origin, tag 1, is the end further
   along ``--origin-toward`` (+z: proximal in the Visible Human frame); tag 2 the other.
   The band reproduces the shipped tags: in all 12 shipped meshes the tagged facets are
   those whose vertices are within 3.6-3.75 % of an extreme, whatever their normals (up
   to 40 % of an end's area has normals that point inward along the axis, so a rule on
   normals would not reproduce them). Refused: an end without facets, no lateral surface
   left, a band of half the length or more (the ends would touch; below it they cannot).
5. Fibres: the potential (Laplace) flow from tag 1 to tag 2 (hyper.fem.laplace), solved
   on the surface meshed again by these steps at 4 times the cells and carried onto this
   mesh's nodes (``--flow-cells``; a coarse mesh's end patches are coarse: the fibres of
   the mesh itself are up to 4° (95th percentile) from the converged field, docs/
   convergence.md); ``--method stokes`` the paper's Stokes flow of hyper.fibers, smoothed
   over ``--fibers-smoothing`` (`hyper.fem.fibers.smoothed`); ``--method pennate`` between
   two aponeuroses (hyper.fem.pennate). Statistics of hyper.meshstats.
"""

from __future__ import annotations

import math
import struct
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
import numpy as np

from hyper.core import io
from hyper.core.params import InputError
from hyper.fem import gmshvolume

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
# The least surface `tetrahedralize` takes, checked before gmsh (`check_meshable`): as many
# triangles as a triangular prism, the fewest with two ends and a side between them (gmsh's
# classifySurfaces looped for ever on a tetrahedron's four); a mean thickness 2 V/A of at
# least MIN_THICKNESS cells of the size --cells gives (every shipped muscle has 0.48 or
# more at 200 cells; a 0.05 mm sheet had 0.1 and gmsh ran minutes); and one long axis,
# the surface's largest principal variance AXIS_MARGIN above the next (a cube has none,
# and the end rule and the mid-section need it).
MIN_TRIANGLES, MIN_THICKNESS, AXIS_MARGIN = 8, 0.3, 0.01
MAX_CELLS = 2_000_000
# gmsh's wall time, all tries together (`gmsh_budget`): about ten times what they take
GMSH_BUDGET_S, GMSH_BUDGET_S_PER_CELL = 60.0, 0.01


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


def cell_size(volume: float, cells: int) -> float:
    """The target edge (mm) that gives about ``cells`` cells in ``volume`` (mm³): the first guess."""
    return (CELLS_PER_H3 * volume / cells) ** (1.0 / 3.0)


def surface_covariance(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """The covariance (3, 3) of the surface's area: its triangles' exact second moments,
    so that how a face is cut into triangles does not matter (∫ x xᵀ dA over a triangle
    a, b, c is A/12 (a aᵀ + b bᵀ + c cᵀ + s sᵀ), s = a + b + c)."""
    corners = points[triangles]
    area = facet_areas(points, triangles)
    total = corners.sum(axis=1)
    mean = (area[:, None] * total).sum(axis=0) / (3.0 * area.sum())
    second = np.einsum("f,fvi,fvj->ij", area, corners, corners) + np.einsum("f,fi,fj->ij", area, total, total)
    return second / (12.0 * area.sum()) - np.outer(mean, mean)


def check_meshable(path: Path, points_mm: np.ndarray, triangles: np.ndarray, cells: int) -> None:
    """InputError where a valid closed surface is too degenerate for ``cells`` cells: too
    few triangles, too thin, or without one long axis (the bounds above MIN_TRIANGLES)."""
    if len(triangles) < MIN_TRIANGLES:
        raise InputError(f"{path}: {len(triangles)} triangles; a muscle's surface has two ends and a side between "
                         f"them, at least {MIN_TRIANGLES} triangles (a triangular prism)")
    volume = enclosed_volume(points_mm, triangles)
    thickness = 2.0 * volume / float(facet_areas(points_mm, triangles).sum())
    size = cell_size(volume, cells)
    if thickness < MIN_THICKNESS * size:
        enough = math.ceil(CELLS_PER_H3 * volume * (MIN_THICKNESS / thickness) ** 3)
        remedy = (f"give --cells {enough} or more" if enough <= MAX_CELLS else
                  f"even --cells {MAX_CELLS} is too few: a sheet or a needle, not a muscle")
        raise InputError(f"{path}: too thin for {cells} cells: its mean thickness (2 volume / area) is "
                         f"{thickness:.3g} mm, {thickness / size:.2g} of their size ({size:.3g} mm), below "
                         f"{MIN_THICKNESS:g}; {remedy}")
    variance = np.linalg.eigvalsh(surface_covariance(points_mm, triangles))
    if variance[2] - variance[1] <= AXIS_MARGIN * variance[2]:
        raise InputError(f"{path}: no long axis: the surface is about as wide as it is long (its two largest "
                         f"principal variances are within {AXIS_MARGIN:.0%}), as a cube or a disc is; a muscle's "
                         "surface is longer than wide")


# ------------------------------------------------------------------------ tetrahedra


def tetrahedralize(points_mm: np.ndarray, triangles: np.ndarray, cells: int,
                   axis=None, budget_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(x (n, 3) mm, tetrahedra (m, 4)) near ``cells`` cells inside the surface (gmsh),
    finer at its two tips (`extremes` along ``axis``; by default the first principal axis
    of its vertices, as find_ends takes the mesh's). InputError when gmsh has not done
    within ``budget_s`` seconds, all its tries together (`gmsh_budget` by default)."""
    budget_s = gmsh_budget(cells) if budget_s is None else budget_s
    deadline = time.monotonic() + budget_s
    volume = enclosed_volume(points_mm, triangles)
    tips = extremes(points_mm, axis)
    corners = points_mm[triangles]
    finest = TIP_EDGE * float(np.median(np.linalg.norm(corners - corners[:, [1, 2, 0]], axis=2)))
    reach = TIP_REACH * float(np.linalg.norm(tips[1] - tips[0]))
    size = cell_size(volume, cells)
    x, tets = gmsh_volume(points_mm, triangles, size, tips, finest, reach, deadline, budget_s)
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
        x, tets = gmsh_volume(points_mm, triangles, size, tips, finest, reach, deadline, budget_s)
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


def gmsh_budget(cells: int) -> float:
    """The default wall time (s) of gmsh's tries for ``cells`` cells: GMSH_BUDGET_S, and
    GMSH_BUDGET_S_PER_CELL a cell (140 s for 8000, which take 3-15 s)."""
    return GMSH_BUDGET_S + GMSH_BUDGET_S_PER_CELL * cells


def gmsh_volume(points: np.ndarray, triangles: np.ndarray, size: float, tips: np.ndarray, finest: float,
                reach: float, deadline: float, budget_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedra of the surface at ``size``, falling to max(TIP_SIZE size, ``finest``) at
    ``tips`` and back to ``size`` within ``reach`` (mm) of them: gmsh in a process of its
    own (`gmshvolume`), stopped at ``deadline`` (time.monotonic), the end of ``budget_s``."""
    tip_size = min(size, max(TIP_SIZE * size, finest))
    try:
        return gmshvolume.tetrahedra(points, triangles, size=size, tip_size=tip_size, tips=tips, reach=reach,
                                     feature_deg=FEATURE_DEG, seconds=max(0.0, deadline - time.monotonic()))
    except gmshvolume.OverBudget:
        raise InputError(f"gmsh had not meshed the surface after {budget_s:g} s (--gmsh-budget) and was stopped: "
                         "a surface it cannot parametrize, or more cells than the budget allows") from None


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


END_RULES = ("surface", "vertices")  # `find_ends`: the end band measured along the surface's axis, or along
# the mesh vertices' (the rule of hyper mesh before, which the shipped new meshes have)


def surface_frame(points: np.ndarray, triangles: np.ndarray) -> dict:
    """The frame the `surface` end rule measures in: the area centroid and first principal
    axis of the surface (`surface_covariance`), of the STL and not of a mesh, so meshes of
    one surface at any resolution measure along one axis."""
    area = facet_areas(points, triangles)
    centre = (area[:, None] * points[triangles].mean(axis=1)).sum(axis=0) / area.sum()
    return {"centre": centre, "axis": np.linalg.eigh(surface_covariance(points, triangles))[1][:, -1]}


def find_ends(x: np.ndarray, facets: np.ndarray, *, band: float = END_BAND, axis=None,
              origin_toward=ORIGIN_TOWARD, frame: dict | None = None) -> tuple[np.ndarray, dict]:
    """The tag of each outward boundary facet (1 origin, 2 insertion, 3 lateral) by the
    rule of the module docstring, and what the rule used; InputError where it fails.

    A facet is in a band where all three of its vertices are, measured from the extremes of
    the mesh's vertices along the axis. ``frame`` (`surface_frame`; ``axis`` replaces its
    axis): the `surface` rule, along the surface's axis; without it the `vertices` rule,
    along the mesh vertices' first principal axis. Why the first where there is a surface
    (docs/convergence.md): the vertices' axis moves with the mesh (gmsh's tips are finer,
    and the share of surface vertices changes with the size), and the ends and the fibres'
    flow with it: on TA_VHF_Left the smoothed fibres at 8k cells are 4.6° (95th
    percentile) off the 64k field by the vertex frame, 2.9° by the surface's."""
    # Below half the length no vertex can be in both bands, so the ends never touch.
    if not 0.0 < band < 0.5:
        raise InputError(f"--end-band: expected a share of the length in (0, 0.5), got {band:g}: the two ends "
                         "would touch")
    if axis is None:
        axis = principal_axis(x) if frame is None else frame["axis"]
    axis = np.asarray(axis, dtype=float)
    if not np.linalg.norm(axis) > 0:
        raise InputError("--axis: expected a nonzero direction")
    axis = axis / np.linalg.norm(axis)
    toward = np.asarray(origin_toward, dtype=float)
    if abs(float(axis @ toward)) < 1e-9 * np.linalg.norm(toward):
        raise InputError(f"--origin-toward {tuple(toward)} is perpendicular to the axis {tuple(axis.round(4))}: "
                         "it cannot tell the origin from the insertion")
    if axis @ toward < 0:
        axis = -axis  # the origin is now at the high end of the projection
    along = (x - (x.mean(axis=0) if frame is None else frame["centre"])) @ axis
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
    return tags, {"rule": "vertices" if frame is None else "surface", "axis": axis.tolist(),
                  "length_mm": float(high - low), "band": band, "origin_toward": toward.tolist(),
                  "parallel_deg": PARALLEL_DEG}


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
    with io.room_checked_xdmf(comm, path) as xdmf:
        xdmf.write_mesh(mesh)
        xdmf.write_meshtags(facet_tags, mesh.geometry)


def gmsh_version() -> str:
    import gmsh

    return gmsh.__version__
