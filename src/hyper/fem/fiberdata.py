"""Fibres from data (issue 34): a DTI image, tractography streamlines, a point cloud of
vectors or a hyper fibre file (`hyper.fem.fiberread`) made into the nodal unit fibre
field a run uses, the vector P1 function `hyper.fem.fibers.load` returns.

Method, at the nodes of the loaded mesh (docs/fibres-from-data.md):

1. Sample orientation tensors, never vectors: an eigenvector has no sign, and the
   average of v and -v is 0, while that of v v^T is v v^T. An image is sampled
   trilinearly at each node from its 8 surrounding voxels, each voxel's tensor v v^T (a
   vector image, v normalised) or its diffusion tensor D (a tensor image); a voxel counts
   only where it has tissue (not all zero) and, with an FA image or for tensors, FA >=
   ``min_fa``; the node has data where the voxels that count carry at least a quarter of the
   trilinear weight (the rest renormalised). Streamlines (each segment: midpoint, unit
   tangent, length) and point clouds are averaged as tensors over the samples within
   ``radius`` of the node, weighted by (1 - d/radius) and the segment length.
2. Fill the nodes without data: each tensor component harmonic on the mesh's edge graph
   (the graph Laplacian, uniform weights) with the nodes that have data fixed; a part of
   the mesh with no data at all is an error.
3. The fibre is the tensor's principal eigenvector (the primary eigenvector of the
   interpolated D, for a tensor image).
4. Signs: the eigenvectors' signs made consistent along a minimum spanning tree of the
   edges weighted by 1 - |a_i . a_j| (the best-aligned neighbours first), from the node
   most nearly along the line of action, which is set to point along it; so the field
   is continuous wherever it can be, and along the line of action where it is aligned
   with it. Mechanics and growth see a0 ⊗ a0, but the P1 interpolant between two nodes
   of opposite sign would pass through zero.

The line of action is the first principal axis of the mesh's vertex coordinates,
oriented from ends[0] to ends[1]; the pennation angle of a node is the angle between its
fibre and that axis (0-90°). Statistics are over the mesh's nodes, unweighted.

Parallel: rank 0 gathers the mesh (nodes by file node index, cells by their nodes) and
the data, does steps 1-4 and broadcasts the field, which each rank takes at its own
nodes by file node index, so the field on any number of ranks equals the serial one
bit for bit (the mesh's own node coordinates, every step ordered by file node index,
never by partition).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np
import scipy.sparse as sp
from dolfinx import fem
from scipy.sparse import csgraph
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

from hyper.core.collective import on_rank0
from hyper.core.io import is_complete, write_series
from hyper.core.params import InputError
from hyper.fem import fiberread as fr
from hyper.fem import fibers
from hyper.fem import geometry as geo

ELEMENT = fibers.ELEMENT
HAS_DATA = 0.25  # the share of a node's trilinear weight that must fall on voxels that count:
# a node on a face of the tissue has about half, on an edge a quarter
MIN_COVERAGE = 0.1  # below this share of nodes with data, the data hardly lies on the mesh
RADIUS_EDGES = 1.5  # the default radius of streamline and cloud samples, in mean edge lengths
LINE_OF_ACTION = "the first principal axis of the mesh's vertices, from ends[0] to ends[1]"
PERCENTILES = (5, 25, 50, 75, 95)


@dataclasses.dataclass(frozen=True)
class Nodes:
    """The loaded mesh on rank 0: ``node`` file node indices (sorted), ``x`` (n, 3) m,
    ``tets`` (m, 4) positions in ``node``, ``axis`` the line of action (unit)."""

    node: np.ndarray
    x: np.ndarray
    tets: np.ndarray
    axis: np.ndarray

    def edges(self) -> np.ndarray:
        pairs = np.concatenate([self.tets[:, [i, j]] for i in range(4) for j in range(i + 1, 4)])
        return np.unique(np.sort(pairs, axis=1), axis=0)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.x.min(axis=0), self.x.max(axis=0)


@dataclasses.dataclass(frozen=True)
class Field:
    """Fibres from data at the nodes (rank 0): unit ``a0`` (n, 3), ``has`` (n,) bool
    (the node had data), the line of action (unit) and what to record about them."""

    a0: np.ndarray
    has: np.ndarray
    line_of_action: np.ndarray
    reader: str
    report: dict

    @property
    def coverage(self) -> float:
        return float(self.has.mean())


# ---------------------------------------------------------------------- sampling (numpy)


def outer(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3): the outer products v v^T."""
    return v[..., :, None] * v[..., None, :]


def sample_image(image: fr.Image, x: np.ndarray, min_fa: float) -> tuple[np.ndarray, np.ndarray]:
    """(tensors (n, 3, 3), has (n,)) of the image at the points ``x`` (m), step 1."""
    inverse = np.linalg.inv(image.affine)
    ijk = x @ inverse[:3, :3].T + inverse[:3, 3]
    low = np.floor(ijk).astype(np.int64)
    frac = ijk - low
    shape = np.array(image.values.shape[:3])
    tensor = np.zeros((len(x), 3, 3))
    weight = np.zeros(len(x))
    for corner in np.ndindex(2, 2, 2):
        idx = low + corner
        w = np.prod(np.where(corner, frac, 1.0 - frac), axis=1)
        inside = np.all((idx >= 0) & (idx < shape), axis=1)
        i, j, k = np.where(inside[:, None], idx, 0).T
        values = image.values[i, j, k]
        if image.kind == "vector":
            length = np.linalg.norm(values, axis=1)
            counts = inside & (length > 0)
            t = outer(values / np.where(length > 0, length, 1.0)[:, None])
            if image.fa is not None:
                counts &= image.fa[i, j, k] >= min_fa
        else:
            t = fr.full_tensors(values, image.order)
            counts = inside & np.any(values != 0, axis=1) & (fr.tensor_fa(t) >= min_fa)
        w = np.where(counts, w, 0.0)
        tensor += w[:, None, None] * t
        weight += w
    has = weight >= HAS_DATA
    tensor[has] /= weight[has, None, None]
    return tensor, has


def sample_points(samples: fr.Samples, x: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(tensors (n, 3, 3), has (n,)) of streamline or cloud samples within ``radius`` of
    the points ``x``, weighted by (1 - d/radius) and the samples' weights, step 1."""
    near = cKDTree(samples.points).query_ball_point(x, radius)
    rows = np.repeat(np.arange(len(x)), [len(n) for n in near])
    cols = np.fromiter((j for n in near for j in n), dtype=np.int64, count=len(rows))
    d = np.linalg.norm(x[rows] - samples.points[cols], axis=1)
    w = np.maximum(1.0 - d / radius, 0.0) * samples.weights[cols]
    matrix = sp.csr_matrix((w, (rows, cols)), shape=(len(x), len(samples.points)))
    total = np.asarray(matrix.sum(axis=1)).ravel()
    tensor = (matrix @ outer(samples.directions).reshape(-1, 9)).reshape(-1, 3, 3)
    has = total > 0
    tensor[has] /= total[has, None, None]
    return tensor, has


# ------------------------------------------------------------------- filling and signs


def laplacian(n: int, edges: np.ndarray) -> sp.csr_matrix:
    ones = np.ones(len(edges))
    adjacency = sp.csr_matrix((np.r_[ones, ones], (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])),
                              shape=(n, n))
    return (sp.diags(np.asarray(adjacency.sum(axis=1)).ravel()) - adjacency).tocsr()


def fill(tensor: np.ndarray, has: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The tensors with those of the nodes without data harmonic on the edge graph, step 2."""
    n = len(tensor)
    free = np.flatnonzero(~has)
    if free.size == 0:
        return tensor
    parts, label = csgraph.connected_components(laplacian(n, edges) != 0, directed=False)
    empty = sorted(set(range(parts)) - set(label[has]))
    if empty:
        raise InputError(f"{int(np.isin(label, empty).sum())} mesh node(s) lie in a part of the mesh without any "
                         "fibre data")
    lap = laplacian(n, edges)
    fixed = np.flatnonzero(has)
    rhs = -(lap[free][:, fixed] @ tensor[fixed].reshape(-1, 9))
    out = tensor.copy()
    out[free] = splu(lap[free][:, free].tocsc()).solve(rhs).reshape(-1, 3, 3)
    return out


def principal(tensor: np.ndarray) -> np.ndarray:
    """The unit eigenvector of each tensor's largest eigenvalue, step 3."""
    _, vectors = np.linalg.eigh(tensor)
    return vectors[:, :, -1]


def oriented(a: np.ndarray, edges: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """``a`` with signs consistent along the minimum spanning tree of step 4."""
    n = len(a)
    along = a @ axis
    root = int(np.argmax(np.abs(along)))
    # 1 - |cos| + a floor: an exactly parallel pair must still be an edge of the graph
    cost = 1.0 - np.abs(np.einsum("ij,ij->i", a[edges[:, 0]], a[edges[:, 1]])) + 1e-12
    graph = sp.csr_matrix((cost, (edges[:, 0], edges[:, 1])), shape=(n, n))
    tree = csgraph.minimum_spanning_tree(graph)
    order, parent = csgraph.breadth_first_order(tree, root, directed=False, return_predecessors=True)
    sign = np.ones(n)
    sign[root] = 1.0 if along[root] >= 0 else -1.0
    for i in order[1:]:
        sign[i] = sign[parent[i]] * (1.0 if a[i] @ a[parent[i]] >= 0 else -1.0)
    return a * sign[:, None]


# ------------------------------------------------------------------------- statistics


def angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (°, 0-90) between the lines of unit vectors (sign-free)."""
    b = np.broadcast_to(b, a.shape)
    return np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", a, b)), 0.0, 1.0)))


def distribution(values: np.ndarray) -> dict:
    return {"mean_deg": float(values.mean()), **{f"p{p}_deg": float(np.percentile(values, p)) for p in PERCENTILES}}


def check_overlap(nodes: Nodes, low: np.ndarray, high: np.ndarray, what: str, unit: str, path: Path) -> None:
    """InputError if the data's box [low, high] (m) misses the mesh's: the unit or the frame is wrong."""
    mlow, mhigh = nodes.bounds()
    if np.all((low <= mhigh) & (high >= mlow)):
        return
    per_unit = fr.UNITS.get(unit) or fr.NIFTI_UNITS.get({"m": "meter", "µm": "micron"}.get(unit, unit), 1.0)

    def box(lo, hi, factor):
        return " x ".join(f"[{a / factor:.4g}, {b / factor:.4g}]" for a, b in zip(lo, hi))

    hint = ""
    for other, metres in (("mm", 1e-3), ("m", 1.0)):
        if other != unit:
            ratio = metres / per_unit
            if np.all((low * ratio <= mhigh) & (high * ratio >= mlow)):
                hint = f": is the unit {other}? (declare it with --fibers-unit {other})"
    if not hint:
        hint = (": a unit would not make them overlap; the data is in another frame (register it to the mesh's "
                "coordinates)")
    raise InputError(f"{path}: the {what}'s bounding box {box(low, high, per_unit)} {unit} does not overlap the "
                     f"mesh's {box(mlow, mhigh, 1.0)} m{hint}")


def from_data(nodes: Nodes, source: fr.Source, data) -> Field:
    """Steps 1-4 on rank 0 for data read by `hyper.fem.fiberread` (an Image or Samples)."""
    edges = nodes.edges()
    check_overlap(nodes, *data.bounds(), "image" if isinstance(data, fr.Image) else data.what, data.unit,
                  source.path)
    params = {}
    if isinstance(data, fr.Image):
        tensor, has = sample_image(data, nodes.x, source.min_fa)
        threshold = (f"FA >= {source.min_fa:g}" if data.kind == "tensor" or data.fa is not None
                     else "no FA threshold (no FA image)")
        reader = (f"NIfTI {data.kind} image {data.values.shape[:3]} (unit {data.unit}), trilinear orientation "
                  f"tensors at the nodes, voxels with tissue and {threshold}")
        params = {"min_fa": source.min_fa}
    else:
        h = float(np.linalg.norm(nodes.x[edges[:, 1]] - nodes.x[edges[:, 0]], axis=1).mean())
        radius = source.radius if source.radius is not None else RADIUS_EDGES * h
        tensor, has = sample_points(data, nodes.x, radius)
        reader = (f"{data.what} ({len(data.points)} {'segments' if data.what == 'streamlines' else 'points'}, "
                  f"unit {data.unit}), orientation tensors within {radius * 1e3:.3g} mm of the nodes, weight "
                  "1 - d/radius")
        params = {"radius_m": radius}
    coverage = float(has.mean())
    if coverage < MIN_COVERAGE:
        raise InputError(f"{source.path}: only {100 * coverage:.1f} % of the mesh's nodes have data (at least "
                         f"{100 * MIN_COVERAGE:g} % needed): does the data lie on the mesh (its frame and unit)?")
    a = oriented(principal(fill(tensor, has, edges)), edges, nodes.axis)
    report = {"coverage": coverage, "nodes": len(a), **params,
              "pennation": distribution(angles(a, nodes.axis)), "line_of_action": LINE_OF_ACTION}
    return Field(a, has, nodes.axis, reader + "; filled by a harmonic extension on the edge graph; signs along a "
                 "minimum spanning tree", report)


# -------------------------------------------------------------------- mesh (DOLFINx)


def node_coordinates(space: fem.FunctionSpace) -> np.ndarray:
    """The coordinates of each local node of a P1 space: the mesh's own, not
    ``tabulate_dof_coordinates``' push-forward, whose last bit depends on the partition."""
    mesh = space.mesh
    index_map = space.dofmap.index_map
    node = np.full(index_map.size_local + index_map.num_ghosts, -1, dtype=np.int64)
    node[space.dofmap.list.ravel()] = mesh.geometry.dofmaps[0].ravel()
    return mesh.geometry.x[node]


def gather_nodes(geometry: geo.Geometry, space: fem.FunctionSpace, root: int = 0) -> Nodes | None:
    """The loaded mesh's nodes and cells on rank ``root`` (None elsewhere). Collective."""
    mesh = geometry.mesh
    comm = mesh.comm
    n = space.dofmap.index_map.size_local
    keys = fibers.node_index(space)
    cells = mesh.topology.index_map(mesh.topology.dim).size_local
    ends = [geo.facet_centroid(geometry, tag) for tag in geometry.ends]
    parts = comm.gather((keys[:n], node_coordinates(space)[:n], keys[space.dofmap.list[:cells]]), root=root)
    if comm.rank != root:
        return None
    keys, x, tets = (np.concatenate(p) for p in zip(*parts))
    order = np.argsort(keys)
    keys, x = keys[order], x[order]
    tets = np.searchsorted(keys, tets)
    # every vertex once: the P1 nodes of an affine mesh
    axis = np.linalg.svd(x - x.mean(axis=0), full_matrices=False)[2][0]
    axis = axis if np.dot(ends[1] - ends[0], axis) >= 0 else -axis
    return Nodes(keys, x, tets, axis)


def nodal_values(geometry: geo.Geometry, a0: fem.Function, root: int = 0) -> np.ndarray | None:
    """The values of a vector P1 function at the nodes, sorted by file node index, on ``root``."""
    space = a0.function_space
    n = space.dofmap.index_map.size_local
    parts = space.mesh.comm.gather((fibers.node_index(space)[:n], a0.x.array.reshape(-1, 3)[:n]), root=root)
    if space.mesh.comm.rank != root:
        return None
    keys, values = (np.concatenate(p) for p in zip(*parts))
    return values[np.argsort(keys)]


def function(space: fem.FunctionSpace, node: np.ndarray, values: np.ndarray) -> fem.Function:
    """A vector P1 function with ``values`` (sorted by the file node indices ``node``) at its nodes."""
    a0 = fem.Function(space, name="a0")
    a0.x.array[:] = values[np.searchsorted(node, fibers.node_index(space))].ravel()
    return a0


def read(source: fr.Source):
    """The data of ``source`` (not a fibre file), as `hyper.fem.fiberread` reads it."""
    return fr.read_image(source) if source.format in (".nii", ".nii.gz") else fr.read_samples(source)


def make(geometry: geo.Geometry, source: fr.Source, stokes: fem.Function | None = None,
         stokes_note: str = "") -> tuple[fem.Function, Field]:
    """The fibres of ``source`` on the loaded ``geometry`` (not a refinement: see
    `hyper.fem.fibers.carried`) and their `Field` (on every rank). ``stokes``: the
    Stokes fibres to compare with; without them ``stokes_note`` says why there are none.
    Collective; bad data is an InputError on every rank.
    """
    if geometry.parent is not None:
        raise ValueError("fibres from data are made on the loaded mesh and carried onto its refinements")
    comm = geometry.comm
    space = fem.functionspace(geometry.mesh, ("Lagrange", 1, (3,)))
    if source.format == ".h5":
        a0 = fibers.load(geometry, source.path)
        values = nodal_values(geometry, a0)
    nodes = gather_nodes(geometry, space)
    reference = nodal_values(geometry, stokes) if stokes is not None else None
    result: Field | str | None = None
    if comm.rank == 0:
        try:
            if source.format == ".h5":
                field = Field(values, np.ones(len(values), dtype=bool), nodes.axis, f"hyper fibre file {source.path}",
                              {"coverage": 1.0, "nodes": len(values), "line_of_action": LINE_OF_ACTION,
                               "pennation": distribution(angles(values, nodes.axis))})
            else:
                field = from_data(nodes, source, read(source))
            if reference is not None:
                field.report["against_stokes"] = distribution(angles(field.a0, reference / np.linalg.norm(
                    reference, axis=1)[:, None]))
            else:
                field.report["against_stokes"] = stokes_note or "no Stokes fibres to compare with"
            result = field
        except InputError as err:
            result = str(err)
    result = comm.bcast(result, root=0)
    if isinstance(result, str):
        raise InputError(result)
    if source.format == ".h5":
        return a0, result
    node = comm.bcast(nodes.node if nodes is not None else None, root=0)
    return function(space, node, result.a0), result


def summary(field: Field) -> str:
    """One line: coverage, pennation angle, and the angle against the Stokes fibres."""
    p = field.report["pennation"]
    text = (f"coverage {100 * field.coverage:.1f} % of {field.report['nodes']} nodes; pennation angle (to "
            f"{field.report['line_of_action']}) mean {p['mean_deg']:.1f}°, median {p['p50_deg']:.1f}°, "
            f"5-95 % {p['p5_deg']:.1f}-{p['p95_deg']:.1f}°")
    s = field.report["against_stokes"]
    if isinstance(s, dict):
        return text + f"; against the Stokes fibres mean {s['mean_deg']:.1f}°, 95th percentile {s['p95_deg']:.1f}°"
    return text + f"; {s}"


def method(source: fr.Source, field: Field) -> str:
    """How fibres from data were made, as a result records it (``fibers_method``)."""
    params = ", ".join(f"{k} {v}" for k, v in source.attributes().items())
    return f"from data: {field.reader} ({params}); {summary(field)}"


def stokes_beside(geometry: geo.Geometry, path: Path | None) -> tuple[fem.Function | None, str]:
    """The Stokes fibres in ``path`` to compare with, or None and why not. Collective."""
    if path is None:
        return None, "no Stokes fibres to compare with (none for this geometry)"
    path = Path(path)
    if not on_rank0(geometry.comm, lambda: is_complete(path) and fr.stored_fibres(path)[0] == "stokes"):
        return None, f"no Stokes fibres to compare with ({path}: none there)"
    return fibers.load(geometry, path), ""


def store(path: str | Path, geometry: geo.Geometry, a0: fem.Function, field: Field, source: fr.Source,
          sha256: str, **attrs) -> None:
    """Write fibres from data as a fibre file (`hyper.fem.fibers`'s format, which
    `hyper.fem.fibers.load` reads: node, a0, x, and has_data instead of speed),
    atomically on rank 0. Collective."""
    space = a0.function_space
    n = space.dofmap.index_map.size_local
    comm = geometry.comm
    parts = comm.gather((fibers.node_index(space)[:n], space.tabulate_dof_coordinates()[:n]), root=0)
    if comm.rank == 0:
        keys, x = (np.concatenate(p) for p in zip(*parts))
        order = np.argsort(keys)
        flat = {f"{group}_{k}": v for group in ("pennation", "against_stokes")
                if isinstance(field.report.get(group), dict) for k, v in field.report[group].items()}
        write_series(path, {"node": keys[order], "a0": field.a0, "x": x[order], "has_data": field.has.astype(np.int8)},
                     attrs={"geometry": geometry.name, "kind": "data", "method": method(source, field),
                            "element": ELEMENT, "coordinates": "m", "source": str(source.path),
                            "source_sha256": sha256, "coverage": field.coverage,
                            "line_of_action": LINE_OF_ACTION, "ranks": comm.size, **flat, **attrs},
                     groups={"parameters": source.attributes()})
    comm.barrier()
