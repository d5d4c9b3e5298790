"""Meshes, facet tags, principal axes and centroids: everything that knows a shape (MODEL.md §5).

The fibre fields on these shapes live in `hyper.fibers`.

Every geometry is a tetrahedral mesh in metres with facet tags for the two muscle ends
(where the tendon springs act), the lateral surface and, where the mesh has one, an
internal mid cross-section. `load` knows the project's meshes by clean identifiers:

    idealized   fusiform muscle, length 0.2 m along z (Gmsh .msh: tags 1, 2 the flat
                end disks, 3 the internal mid cross-section at z = 0.1)
    cylinder    radius 0.02 m, length 0.1 m along z (Gmsh .msh: tags 1, 2 the end
                disks, 3 the internal cross-section at z = 0.05)
    <M>_<S>_<side>  the 12 anatomical meshes, M in BFLH, ST, TA, S in VHF, VHM,
                side in Left, Right (XDMF in millimetres, tags `ft_small`: 1, 2 ends,
                3 lateral surface)
    NAME        a folder meshes/NAME/ that `hyper mesh` wrote (`MESHED`), loaded as
                the anatomical ones are

The two Gmsh meshes carry no lateral tag; the exterior facets that are neither end get
`LATERAL_TAG` (4) on load. The idealized shape is read from its .msh, not from the XDMF
next to it: the XDMF's tags 1 and 2 also cover a 2 cm band of the lateral surface at
each end (57 of their 64 facets), whereas MODEL.md §5 and the .msh make them the flat
end disks. ``ends="tags"`` takes the XDMF's end tags instead, band included, on the same
mesh (the original code's choice, MODEL.md §9).
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import xml.etree.ElementTree as ET
from collections import OrderedDict
from pathlib import Path

import basix.ufl
import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
import numpy as np
import ufl
from dolfinx import fem, la
from dolfinx import mesh as dmesh
from dolfinx.graph import adjacencylist
from dolfinx.io import XDMFFile
from dolfinx.io.utils import distribute_entity_data
from mpi4py import MPI

from hyper.core import resources
from hyper.core.io import HDF5_ERRORS
from hyper.core.params import InputError, read_text

MESHES_DIR = resources.folder("meshes")
LATERAL_TAG = 4
MM = 1.0e-3  # m per mm: the anatomical meshes are stored in millimetres

MUSCLES = {"BFLH": "biceps femoris long head", "ST": "semitendinosus", "TA": "tibialis anterior"}
# The muscles `hyper mesh` made from the other Visible Human surfaces (meshes/M_S_side/, README
# "A mesh from a surface"); the 19 folders are the set NEW.
NEW_MUSCLES = {"RF": "rectus femoris", "VL": "vastus lateralis", "VM": "vastus medialis",
               "VI": "vastus intermedius", "GM": "gastrocnemius medialis"}

# Clean id -> mesh file relative to MESHES_DIR; folder names keep the dataset's spellings.
GEOMETRIES: OrderedDict[str, str] = OrderedDict(
    [
        ("idealized", "muscle-idealized/muscle-idealized.msh"),
        ("cylinder", "muscle-cylinder/muscle-cylinder.msh"),
    ]
    + [
        (ident, f"{folder}/{folder}.xdmf")
        for ident, folder in [
            ("BFLH_VHF_Left", "VHF_Left_Muscle_BicepsFemorisLong_smooth"),
            ("BFLH_VHF_Right", "VHF_Right_Muscle_BicepsFemorisLongHead_smooth"),
            ("BFLH_VHM_Left", "VHM_Left_Muscle_BicepsFemorisLongus_smooth"),
            ("BFLH_VHM_Right", "VHM_Right_Muscle_BicepsFemorisLong_smooth"),
            ("ST_VHF_Left", "VHF_Left_Muscle_Semitendinosus_smooth"),
            ("ST_VHF_Right", "VHF_Right_Muscle_Semitendonosus_smooth"),
            ("ST_VHM_Left", "VHM_Left_Muscle_Semitendonosus_smooth"),
            ("ST_VHM_Right", "VHM_Right_Muscle_Semitendinosus_smooth"),
            ("TA_VHF_Left", "VHF_Left_Muscle_TibialisAnterior_smooth"),
            ("TA_VHF_Right", "VHF_Right_Muscle_TibialisAnterior_smooth"),
            ("TA_VHM_Left", "VHM_Left_Muscle_TibialisAnterior_smooth"),
            ("TA_VHM_Right", "VHM_Right_Muscle_TibialisAnterior_smooth"),
        ]
    ]
)
ANATOMICAL: tuple[str, ...] = tuple(name for name in GEOMETRIES if name not in ("idealized", "cylinder"))


def meshed_folders(root: Path) -> list[str]:
    """Folders ``root/NAME/`` holding ``NAME.xdmf``: meshes made by `hyper mesh`, whose
    folder name is their identifier (millimetres, tags `ft_small`, as the shipped ones)."""
    if not root.is_dir():
        return []
    shipped = {Path(file).parent.name for file in GEOMETRIES.values()}
    return sorted(d.name for d in root.iterdir()
                  if d.name not in shipped and d.name not in GEOMETRIES and (d / f"{d.name}.xdmf").is_file())


# Found when the module loads: `hyper mesh … --output meshes/NAME/` makes `--geometry NAME` known.
MESHED: tuple[str, ...] = tuple(meshed_folders(MESHES_DIR))
GEOMETRIES.update((name, f"{name}/{name}.xdmf") for name in MESHED)
NEW: tuple[str, ...] = tuple(name for name in MESHED if name.split("_")[0] in NEW_MUSCLES)
# Names that stand for several geometries where a job takes a list (cohort --geometries).
SETS: dict[str, tuple[str, ...]] = {"paper": ANATOMICAL, "new": NEW}


def split_id(name: str) -> tuple[str, str, str]:
    """'BFLH_VHF_Left' -> ('BFLH', 'VHF', 'Left'): muscle, subject, side."""
    if name not in ANATOMICAL and not (name in MESHED and name.count("_") == 2):
        raise InputError(f"{name!r} is not an anatomical geometry; known: {', '.join(ANATOMICAL)}")
    muscle, subject, side = name.split("_")
    return muscle, subject, side


@dataclasses.dataclass
class Geometry:
    """A mesh with its facet tags; it owns the integration measures and their quadrature.

    ends: the tags of the two ends Γ1, Γ2 (Γ1 = ends[0] is where reaction forces are
    measured); lateral: the traction-free side; midsection: the tag of an internal
    facet set for the mid cross-section, or None where the mesh has none.
    """

    name: str
    mesh: dmesh.Mesh
    facet_tags: dmesh.MeshTags
    ends: tuple[int, int]
    lateral: int
    midsection: int | None = None
    quadrature_degree: int = 4
    # Surface integrals (ds, dS) at the degree UFL estimates for each integrand instead
    # of quadrature_degree: the original code's choice (MODEL.md §9), slow to compile.
    estimated_surface_degree: bool = False
    # the geometry this one is a uniform refinement of (`refine`), None for a loaded one:
    # fibres that belong to the loaded mesh (a fibre file, its principal axis) are made
    # there and carried onto the refined mesh (hyper.fem.fibers.carried)
    parent: Geometry | None = dataclasses.field(default=None, repr=False, compare=False)

    @property
    def base(self) -> Geometry:
        """The loaded geometry this one refines (itself if it is not refined)."""
        return self if self.parent is None else self.parent.base

    @property
    def refinements(self) -> int:
        return 0 if self.parent is None else 1 + self.parent.refinements

    @property
    def comm(self):
        return self.mesh.comm

    @property
    def metadata(self) -> dict:
        return {"quadrature_degree": self.quadrature_degree}

    @property
    def surface_metadata(self) -> dict:
        return {} if self.estimated_surface_degree else self.metadata

    @property
    def dx(self) -> ufl.Measure:
        return ufl.Measure("dx", domain=self.mesh, metadata=self.metadata)

    @property
    def ds(self) -> ufl.Measure:
        return ufl.Measure("ds", domain=self.mesh, subdomain_data=self.facet_tags, metadata=self.surface_metadata)

    @property
    def dS(self) -> ufl.Measure:
        return ufl.Measure("dS", domain=self.mesh, subdomain_data=self.facet_tags, metadata=self.surface_metadata)

    def num_cells(self) -> int:
        return self.mesh.topology.index_map(self.mesh.topology.dim).size_global

    def reference_volume(self) -> float:
        return _sum(self.comm, fem.assemble_scalar(fem.form(1.0 * self.dx)))

    def area(self, tag: int) -> float:
        """Reference area of an exterior (end, lateral) or interior (midsection) facet set."""
        measure = self.dS if tag == self.midsection else self.ds
        return _sum(self.comm, fem.assemble_scalar(fem.form(1.0 * measure(tag))))


def _sum(comm, value):
    return comm.allreduce(value, op=MPI.SUM)


# ---------------------------------------------------------------------------- loading


# The idealized shape's ends: the flat end disks of the .msh (MODEL.md §5), or the end
# tags of the XDMF next to it, which add a lateral band at each end (MODEL.md §9).
IDEALIZED_ENDS = ("disks", "tags")


def load(name: str, comm, *, meshes_dir: str | Path | None = None, quadrature_degree: int = 4,
         ends: str = "disks", estimated_surface_degree: bool = False) -> Geometry:
    """The geometry with clean identifier ``name``, distributed over ``comm``, in metres.

    ``ends`` (`IDEALIZED_ENDS`) and ``estimated_surface_degree`` (`Geometry`) are the
    original code's choices for the idealized shape; the other geometries take the defaults.
    """
    if name not in GEOMETRIES:
        raise InputError(f"unknown geometry {name!r}; known: {', '.join(GEOMETRIES)}")
    if ends not in IDEALIZED_ENDS:
        raise InputError(f"ends must be one of {', '.join(IDEALIZED_ENDS)}, got {ends!r}")
    if name != "idealized" and (ends != "disks" or estimated_surface_degree):
        raise InputError(f"the original's end tags and surface quadrature apply to the idealized shape only, "
                         f"not {name!r}")
    path = Path(meshes_dir if meshes_dir is not None else MESHES_DIR) / GEOMETRIES[name]
    if name in ("idealized", "cylinder"):
        mesh, tags = _read_msh(path, comm)
        if ends == "tags":
            tags = _xdmf_end_tags(mesh, tags, path.with_suffix(".h5"), ends=(1, 2))
        tags = _with_lateral(mesh, tags, ends=(1, 2), lateral=LATERAL_TAG)
        geometry = Geometry(name, mesh, tags, ends=(1, 2), lateral=LATERAL_TAG, midsection=3,
                            quadrature_degree=quadrature_degree, estimated_surface_degree=estimated_surface_degree)
        _check_tags(geometry, path)
        _check_cells(geometry, path)
        return geometry
    return load_file(path, comm, name=name, tags="ft_small", ends=(1, 2), lateral=3, scale=MM,
                     quadrature_degree=quadrature_degree)


def load_file(
    path: str | Path,
    comm,
    *,
    name: str | None = None,
    tags: str = "ft_small",
    ends: tuple[int, int] = (1, 2),
    lateral: int = 3,
    midsection: int | None = None,
    scale: float = 1.0,
    mesh_name: str = "Grid",
    quadrature_degree: int = 4,
) -> Geometry:
    """A user-provided tetrahedral XDMF mesh with facet tags named ``tags``.

    ``scale`` converts the file's length unit to metres (1e-3 for millimetres).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such mesh file")
    problem = comm.bcast(_unreadable(path) if comm.rank == 0 else None, root=0)
    if problem is not None:
        raise InputError(f"{path}: {problem}")
    try:
        with XDMFFile(comm, str(path), "r") as xdmf:
            mesh = xdmf.read_mesh(name=mesh_name)
            mesh.topology.create_connectivity(mesh.topology.dim - 1, mesh.topology.dim)
            facet_tags = xdmf.read_meshtags(mesh, name=tags)
    except RuntimeError as err:
        raise InputError(
            f"{path}: cannot read a mesh {mesh_name!r} with facet tags {tags!r} "
            f"(expected XDMF with HDF5 data): {err}"
        ) from None
    if mesh.topology.cell_name() != "tetrahedron":
        raise InputError(f"{path}: expected a tetrahedral mesh, got {mesh.topology.cell_name()}")
    if facet_tags.dim != mesh.topology.dim - 1:
        raise InputError(f"{path}: tags {tags!r} are not facet tags (dimension {facet_tags.dim})")
    mesh.geometry.x[:] *= scale
    geometry = Geometry(name or path.stem, mesh, facet_tags, ends=tuple(ends), lateral=lateral,
                        midsection=midsection, quadrature_degree=quadrature_degree)
    _check_tags(geometry, path)
    _check_cells(geometry, path)
    return geometry


# A cell this much thinner than the mean is degenerate: the shipped meshes' thinnest is
# 3.5e-3 of their mean, a cell flattened onto a plane or a line 1e-16.
DEGENERATE_VOLUME = 1e-6


def _check_cells(geometry: Geometry, path) -> None:
    """Refuse a tangled mesh (cells of both orientations: a vertex moved through a face)
    and degenerate cells, which would give a wrong CSA0 and volume or a singular solve."""
    mesh = geometry.mesh
    p = mesh.geometry.x[mesh.geometry.dofmaps[0][: mesh.topology.index_map(3).size_local]]
    volume = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0
    comm = geometry.comm
    positive = _sum(comm, int(np.count_nonzero(volume > 0)))
    negative = _sum(comm, int(np.count_nonzero(volume < 0)))
    cells = _sum(comm, len(volume))
    mean = _sum(comm, float(np.abs(volume).sum())) / max(cells, 1)
    thinnest = comm.allreduce(float(np.abs(volume).min()) if len(volume) else np.inf, op=MPI.MIN)
    if positive and negative:
        raise InputError(f"{path}: the mesh is tangled: {min(positive, negative)} of its {cells} cells are "
                         "inverted against the others")
    if not mean > 0 or thinnest < DEGENERATE_VOLUME * mean:
        raise InputError(f"{path}: degenerate cells: the smallest has {thinnest / max(mean, 1e-300):.3g} of the "
                         "mean cell volume (flat or collapsed cells)")


def _unreadable(xdmf: Path) -> str | None:
    """Why the XDMF mesh file is not UTF-8 text (`read_text`) or the HDF5 data it points to
    cannot be read (None where it can, or where the file is no XML: XDMFFile says so),
    found by h5py, which reports it in one line where the HDF5 library under XDMFFile
    prints pages."""

    import h5py

    try:
        items = [item.text.strip() for item in ET.fromstring(read_text(xdmf, "XDMF file")).iter("DataItem")
                 if item.text and ":" in item.text]
    except InputError as err:  # binary, UTF-16: rank 0 alone reads here, so a reason, not a raise
        return err.reason.removeprefix(f"{xdmf}: ")
    except ET.ParseError:
        return None
    for text in items:
        name, _, dataset = text.partition(":")
        data = xdmf.parent / name
        if not data.is_file():
            return f"its data file {name} is missing"
        try:
            with h5py.File(data, "r") as f:
                f[dataset][()]
        except HDF5_ERRORS as err:
            return f"cannot read its data file {name} (truncated or damaged?): {err}"
    return None


def _check_tags(geometry: Geometry, path) -> None:
    required = {"end": list(geometry.ends), "lateral": [geometry.lateral]}
    if geometry.midsection is not None:
        required["midsection"] = [geometry.midsection]
    present = geometry.facet_tags.values
    for role, tags in required.items():
        for tag in tags:
            count = _sum(geometry.comm, int(np.count_nonzero(present == tag)))
            if count == 0:
                raise InputError(f"{path}: facet tag {tag} ({role}) is missing; "
                                 f"the file has tags {_all_tags(geometry)}")


def _all_tags(geometry: Geometry) -> list[int]:
    tags = geometry.comm.allgather(np.unique(geometry.facet_tags.values).tolist())
    return sorted(set().union(*tags))


def _read_msh(path: Path, comm) -> tuple[dmesh.Mesh, dmesh.MeshTags]:
    """A Gmsh .msh (tetrahedra, physical groups on triangles), read by meshio on rank 0.

    (dolfinx.io.gmsh needs the gmsh module, which the project does not depend on.)
    Cells are ghosted across shared facets so that interior facet integrals (dS) work
    in parallel.
    """
    error = cells = x = facets = values = None
    if comm.rank == 0:
        try:
            cells, x, facets, values = _msh_arrays(path)
        except InputError as err:
            error = str(err)
    error = comm.bcast(error, root=0)
    if error is not None:
        raise InputError(error)
    if comm.rank != 0:
        cells = np.empty((0, 4), dtype=np.int64)
        x = np.empty((0, 3), dtype=np.float64)
        facets = np.empty((0, 3), dtype=np.int64)
        values = np.empty((0,), dtype=np.int32)
    domain = ufl.Mesh(basix.ufl.element("Lagrange", "tetrahedron", 1, shape=(3,)))
    partitioner = dmesh.create_cell_partitioner(dmesh.GhostMode.shared_facet, 2)
    mesh = dmesh.create_mesh(comm, cells, domain, x, partitioner)
    local_facets, local_values = distribute_entity_data(mesh, 2, facets, values)
    mesh.topology.create_connectivity(2, 3)
    tags = dmesh.meshtags_from_entities(
        mesh, 2, adjacencylist(local_facets), local_values.astype(np.int32)
    )
    return mesh, tags


def _msh_arrays(path: Path):
    import meshio

    if not path.is_file():
        raise InputError(f"{path}: no such mesh file")
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # meshio's Gmsh reader prints stray lines
            msh = meshio.read(path)
    except Exception as err:  # meshio raises many types for malformed files
        raise InputError(f"{path}: cannot read as a Gmsh mesh: {err}") from None
    phys = msh.cell_data.get("gmsh:physical")
    if phys is None:
        raise InputError(f"{path}: no physical groups (expected tagged triangles and tetrahedra)")
    tets = [b.data for b in msh.cells if b.type == "tetra"]
    tris = [(b.data, d) for b, d in zip(msh.cells, phys) if b.type == "triangle"]
    if not tets:
        raise InputError(f"{path}: no tetrahedra")
    cells = np.vstack(tets).astype(np.int64)
    facets = np.vstack([t for t, _ in tris]).astype(np.int64) if tris else np.empty((0, 3), np.int64)
    values = np.concatenate([d for _, d in tris]).astype(np.int32) if tris else np.empty(0, np.int32)
    return cells, np.ascontiguousarray(msh.points[:, :3], dtype=np.float64), facets, values


def _xdmf_end_tags(mesh: dmesh.Mesh, tags: dmesh.MeshTags, data: Path, ends) -> dmesh.MeshTags:
    """``tags`` with the end tags replaced by those stored in the XDMF's HDF5 ``data``
    (the same vertices as the .msh): its end facets are found by their centroids."""
    import h5py
    from scipy.spatial import cKDTree

    found = None
    if mesh.comm.rank == 0:
        with h5py.File(data, "r") as f:
            x = f["/Mesh/Grid/geometry"][()]
            triangles = f["/MeshTags/ft/topology"][()]
            values = f["/MeshTags/ft/Values"][()].ravel()
        keep = np.isin(values, ends)
        found = x[triangles[keep]].mean(axis=1), values[keep].astype(np.int32)
    centroids, values = mesh.comm.bcast(found, root=0)
    exterior = dmesh.exterior_facet_indices(mesh.topology)
    local = mesh.geometry.x[dmesh.entities_to_geometry(mesh, 2, exterior)].mean(axis=1)
    distance, index = cKDTree(centroids).query(local)
    # A centroid of the same facet agrees to round-off; the nearest other one is a
    # facet's size away (about 1e-3 m).
    match = distance < 1e-9
    others = ~np.isin(tags.values, ends)
    indices = np.concatenate([tags.indices[others], exterior[match]]).astype(np.int32)
    new_values = np.concatenate([tags.values[others], values[index[match]]]).astype(np.int32)
    order = np.argsort(indices)
    return dmesh.meshtags(mesh, 2, indices[order], new_values[order])


def _with_lateral(mesh: dmesh.Mesh, tags: dmesh.MeshTags, ends, lateral: int) -> dmesh.MeshTags:
    """``tags`` plus ``lateral`` on every exterior facet that carries no end tag."""
    mesh.topology.create_connectivity(2, 3)
    exterior = dmesh.exterior_facet_indices(mesh.topology)
    side = np.setdiff1d(exterior, tags.indices[np.isin(tags.values, ends)])
    indices = np.concatenate([tags.indices, side]).astype(np.int32)
    values = np.concatenate([tags.values, np.full(len(side), lateral, dtype=np.int32)])
    order = np.argsort(indices, kind="stable")
    indices, values = indices[order], values[order]
    keep = np.ones(len(indices), dtype=bool)
    keep[1:] = indices[1:] != indices[:-1]  # a facet keeps its first (original) tag
    return dmesh.meshtags(mesh, 2, indices[keep], values[keep])


def refine(geometry: Geometry) -> Geometry:
    """Uniform refinement (every tetrahedron into eight), facet tags carried over.

    New vertices stay on the coarse facets: the domain is the coarse polyhedron, so a
    sequence of refinements converges to the solution on that polyhedron.
    dolfinx.mesh.transfer_meshtag refuses ghosted meshes, and interior facet integrals
    need the ghosts, so the tags are carried here: each rank tags the children of its
    own refined cells, and a scatter shares them with every rank that holds the facet.
    """
    mesh = geometry.mesh
    tdim = mesh.topology.dim
    mesh.topology.create_entities(1)
    mesh.topology.create_connectivity(tdim, tdim - 1)
    fine, parent_cell, parent_facet = dmesh.refine(mesh, option=dmesh.RefinementOption.parent_cell_and_facet)
    fine.topology.create_connectivity(tdim, tdim - 1)
    fine.topology.create_connectivity(tdim - 1, tdim)

    fmap = mesh.topology.index_map(tdim - 1)
    coarse_value = np.full(fmap.size_local + fmap.num_ghosts, -1, dtype=np.int32)
    coarse_value[geometry.facet_tags.indices] = geometry.facet_tags.values
    nf = tdim + 1
    parent_cell = np.asarray(parent_cell)
    local_parent = np.asarray(parent_facet, dtype=np.int64).reshape(-1, nf)
    # parent_cell/parent_facet follow the refined cells' creation order; the mesh
    # reorders cells, and original_cell_index maps back.
    offset = fine.topology.index_map(tdim).local_range[0]
    created = np.asarray(fine.topology.original_cell_index, dtype=np.int64) - offset
    child = np.full(len(parent_cell), -1, dtype=np.int64)
    mine = (created >= 0) & (created < len(parent_cell))
    child[created[mine]] = np.flatnonzero(mine)
    coarse_c2f = mesh.topology.connectivity(tdim, tdim - 1)
    fine_c2f = fine.topology.connectivity(tdim, tdim - 1)
    rows, cols = np.nonzero(local_parent >= 0)
    coarse_facets = np.array([coarse_c2f.links(parent_cell[r])[local_parent[r, c]] for r, c in zip(rows, cols)],
                             dtype=np.int64)
    fine_facets = np.array([fine_c2f.links(child[r])[c] for r, c in zip(rows, cols)], dtype=np.int64)
    values = coarse_value[coarse_facets] if len(coarse_facets) else np.empty(0, np.int32)
    keep = values >= 0

    # Share: owners collect (count, sum of tags) from every rank, then broadcast to ghosts.
    fine_map = fine.topology.index_map(tdim - 1)
    count = la.vector(fine_map, 1, dtype=np.float64)
    total = la.vector(fine_map, 1, dtype=np.float64)
    marked, first = np.unique(fine_facets[keep], return_index=True)
    count.array[marked] = 1.0
    total.array[marked] = values[keep][first]
    for vec in (count, total):
        vec.scatter_reverse(la.InsertMode.add)
        vec.scatter_forward()
    facets = np.flatnonzero(count.array > 0).astype(np.int32)
    tag_values = np.rint(total.array[facets] / count.array[facets]).astype(np.int32)
    tags = dmesh.meshtags(fine, tdim - 1, facets, tag_values)
    return dataclasses.replace(geometry, mesh=fine, facet_tags=tags, parent=geometry)


# ----------------------------------------------------------------------------- shape


def owned_vertex_coordinates(mesh: dmesh.Mesh) -> np.ndarray:
    """Coordinates of the vertices this rank owns: over all ranks, each vertex once."""
    n = mesh.topology.index_map(0).size_local
    mesh.topology.create_connectivity(0, mesh.topology.dim)
    nodes = dmesh.entities_to_geometry(mesh, 0, np.arange(n, dtype=np.int32)).ravel()
    return mesh.geometry.x[nodes]


def principal_axes(mesh: dmesh.Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Mean of the vertices and the principal axes (columns, largest variance first).

    Every vertex counts once, whatever the number of ranks, so the result is a property
    of the reference mesh.
    """
    x = owned_vertex_coordinates(mesh)
    comm = mesh.comm
    count = _sum(comm, x.shape[0])
    mean = _sum(comm, x.sum(axis=0)) / count
    cov = _sum(comm, (x - mean).T @ (x - mean)) / count
    _, vectors = np.linalg.eigh(cov)
    return mean, vectors[:, ::-1].copy()


def facet_centroid(geometry: Geometry, tag: int) -> np.ndarray:
    """Area-weighted centroid of a tagged facet set (owned facets, reduced over ranks)."""
    mesh = geometry.mesh
    nowned = mesh.topology.index_map(2).size_local
    facets = geometry.facet_tags.find(tag)
    facets = facets[facets < nowned]
    pts = mesh.geometry.x[dmesh.entities_to_geometry(mesh, 2, facets)]
    area = 0.5 * np.linalg.norm(np.cross(pts[:, 1] - pts[:, 0], pts[:, 2] - pts[:, 0]), axis=1)
    total = _sum(geometry.comm, area.sum())
    return _sum(geometry.comm, (area[:, None] * pts.mean(axis=1)).sum(axis=0)) / total


__all__ = [
    "ANATOMICAL",
    "GEOMETRIES",
    "Geometry",
    "IDEALIZED_ENDS",
    "MESHED",
    "MUSCLES",
    "NEW",
    "NEW_MUSCLES",
    "SETS",
    "load",
    "load_file",
    "meshed_folders",
    "principal_axes",
    "refine",
    "split_id",
]
