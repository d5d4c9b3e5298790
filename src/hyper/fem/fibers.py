"""Fibre fields (MODEL.md §5): `fiber_field` gives the reference fibre direction a0 of any
geometry, analytic (the idealized shape), uniform (the cylinder, a principal axis), or the
Stokes-flow fibres of the anatomical meshes (after Varvik et al. 2021), computed here.

A slow viscous flow enters the muscle through one end (tag ``ends[0]``), leaves it
through the other (``ends[1]``) and slides along the lateral surface; its normalized
velocity is the fibre direction a0. ``python -m hyper.fibers`` computes it once per
mesh and stores it next to the mesh (``meshes/<folder>/fibers_stokes.h5`` for the shipped
meshes, whose own fibres, ``fibers.h5``, are the Laplace fibres of `hyper.fem.laplace`,
which converge with the mesh where these do not: docs/convergence.md); ``load`` reads it
back on any number of ranks. They are the paper's fibres: ``--settings original`` (and
``--fibers stokes``) runs them.

Method (μ = 1 and unit inflow speed: both scale out of the normalized velocity)

    -div(2μ ε(u)) + ∇p = 0,  div u = 0                        in Ω
    u·N = -1,  tangential traction 0                           on Γin  (ends[0])
    u·N =  0,  tangential traction 0   (free slip)             on Γlat (lateral)
    σ(u, p) n = 0                      (natural outflow)       on Γout (ends[1])

- Taylor–Hood P2–P1: inf-sup stable on tetrahedra, and P2 velocity resolves the
  bending of the flow around the curved lateral surface on these coarse meshes
  (~2500 vertices, ~50 000 unknowns: one MUMPS LU factorization).
- Inflow as a prescribed normal velocity with free tangential traction, i.e. the same
  slip condition as the lateral surface with flux -1 instead of 0. A full velocity
  (u = -N, no tangential motion) would contradict u·N = 0 along the rim where the
  end meets the lateral surface wherever the two are not at right angles; prescribing
  only the normal component is compatible with the slip condition next to it, so no
  singular corner layer forms and the speed stays bounded away from 0 (min 0.055 to
  0.32 of the inflow speed on the 12 anatomical meshes), which keeps the normalization
  defined.
  A uniform normal speed means a uniform attachment of fibres over the end surface.
- Both slip conditions weakly by Nitsche's method (symmetric variant, e.g. Urquiza,
  Garon & Farinas 2014): consistency terms -(N·σ(u,p)n)(v·N) and their transposes,
  penalty 2μ γ/h (u·N - g)(v·N) with h the cell diameter and γ = 100 (``penalty``).
  The share of BFLH_VHF_Left within 30° of its axis stays within 99.84–99.95 % for
  γ = 10, 100, 1000. Strong conditions would need a rotated basis at curved boundary
  nodes.
- N is the *vertex* normal, not the facet normal: the area-weighted average of the
  facet normals of each end or lateral surface at its vertices, interpolated linearly
  and normalized. On a faceted curved surface, slip along the facet normals lets the
  flow follow the facets' zigzag (on the straight cylinder mesh only 67 % of the
  volume is within 2° of the axis, the speed varies 0.57–1.26); with vertex normals
  100 % is within 2° and the speed varies by ±2 %. The traction in the consistency
  terms is σ n with the facet normal n (what the weak form leaves on each facet); N
  only picks its normal part.
- Outflow natural (zero traction): it fixes the pressure, and the flow leaves in
  whatever direction the geometry gives it.

Fibre field. The P2 velocity at the vertices (its P1 interpolant), divided by its
length there: a vector P1 field, unit at the nodes, which the mechanics uses as a UFL
vector and the growth field evaluates and renormalizes at its quadrature points. A
node where the speed falls below ``min_speed`` (a stagnation point: no direction) is
an error.

Stored form (``fibers.h5``): datasets ``node`` (the mesh file's node indices,
``mesh.geometry.input_global_indices``), ``a0`` (unit fibres at those nodes, (n, 3)),
``x`` (their coordinates in metres, to check that the file belongs to the mesh) and
``speed`` (|u| at the nodes / inflow speed); the method, parameters, tags, statistics
and versions as attributes, and ``complete`` last (written atomically). Keyed by the
file's node index, the field maps back exactly onto any partition of the mesh.

Resolution (docs/convergence.md, `python -m hyper.bench convergence`). On one mesh the P2
field is within 3° (95th percentile) of P3's on 7 of 10 muscles measured, not on the
pennate or wide ones (``StokesParams.degree`` 3 computes P3). Between meshes of one
surface the field changes far more, with the surface's facets and end patches;
`compute_transferred` solves the flow on a finer mesh of the surface and carries it onto
the mechanics mesh's nodes (`hyper mesh --flow-cells`).

The job that computes and stores them for the anatomical meshes is `hyper.commands.fibers`.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from pathlib import Path

import basix.ufl
import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
import numpy as np
import ufl
from dolfinx import fem, la
from dolfinx.fem.petsc import LinearProblem
from mpi4py import MPI

from hyper.core.io import is_complete, reading_h5, write_series
from hyper.core.params import InputError, as_attributes, check_positive
from hyper.fem import geometry as geo

FILE_NAME = "fibers.h5"
# the paper's Stokes fibres beside a mesh whose own fibres (FILE_NAME) are of another kind:
# the shipped anatomical meshes carry Laplace fibres (hyper.fem.laplace) and these
STOKES_FILE_NAME = "fibers_stokes.h5"
METHOD = ("Stokes flow, Taylor-Hood P2-P1; inflow u.N = -1 on ends[0] and free slip u.N = 0 "
          "on the lateral surface, both with zero tangential traction by symmetric Nitsche "
          "(N the area-weighted vertex normal); zero traction on ends[1]; MUMPS LU; "
          "a0 = u/|u| at the vertices (P1)")
ELEMENT = "Lagrange P1 vector, unit length at the nodes"


SMOOTHED_METHOD = ("; the velocity smoothed over {mm:g} mm before its direction is taken (w - l^2 lap w = u, "
                   "zero normal gradient, P1, l = {mm:g} mm)")


def stokes_method(params: StokesParams) -> str:
    """METHOD with the Taylor–Hood degrees and the smoothing of ``params``."""
    method = METHOD.replace("P2-P1", f"P{params.degree}-P{params.degree - 1}")
    return method + (SMOOTHED_METHOD.format(mm=params.smoothing_m * 1e3) if params.smoothing_m > 0 else "")
ALIGNMENT_DEG = 30.0  # the angle the alignment statistic counts up to

_prefixes = itertools.count()


@dataclasses.dataclass(frozen=True)
class StokesParams:
    penalty: float = 100.0  # Nitsche penalty γ (1): weight 2μγ/h on the normal-velocity misfit
    # (1) for all forms; degree 6 moves the fibres of BFLH_VHF_Left by 0.007° on average
    # (at most 0.3°) and leaves the 30° share unchanged
    quadrature_degree: int = 4
    min_speed: float = 1.0e-6  # (1, of the inflow speed) below it a node has no fibre direction
    degree: int = 2  # of the velocity (Taylor–Hood: the pressure one less)
    # (m) length l of the filter w - l² Δw = u applied to the velocity before its direction
    # is taken (`smoothed`); 0: none (the paper's fibres and the shipped fibre files)
    smoothing_m: float = 0.0

    def __post_init__(self):
        check_positive(self, "penalty", "min_speed")
        if not (isinstance(self.smoothing_m, (int, float)) and math.isfinite(self.smoothing_m)
                and 0.0 <= self.smoothing_m <= 0.05):
            raise InputError(f"smoothing_m must be a length in [0, 0.05] m, got {self.smoothing_m!r}")
        if self.degree not in (2, 3):
            raise InputError(f"degree must be 2 or 3, got {self.degree!r}")
        q = self.quadrature_degree
        if isinstance(q, bool) or not float(q).is_integer() or not 2 <= q <= 12:
            raise InputError(f"quadrature_degree must be an integer in 2..12, got {q!r}")
        object.__setattr__(self, "quadrature_degree", int(q))


# ------------------------------------------------------------------------------ solver


def vertex_normal(space: fem.FunctionSpace, ds: ufl.Measure) -> fem.Function:
    """Area-weighted average of the facet normals over ``ds`` at each vertex, unit length.

    ``space`` is a vector P1 space; vertices off the surface get 0. The assembled
    integral ∫ n·φ_i ds is the area-weighted sum over the facets around vertex i
    (a third of each area), summed over ranks before normalizing.
    """
    n = ufl.FacetNormal(space.mesh)
    vector = fem.assemble_vector(fem.form(ufl.dot(n, ufl.TestFunction(space)) * ds))
    vector.scatter_reverse(la.InsertMode.add)
    normal = fem.Function(space, name="N")
    values = normal.x.array.reshape(-1, 3)
    values[:] = vector.array.reshape(-1, 3)
    length = np.linalg.norm(values, axis=1)
    on = length > 0
    values[on] /= length[on, None]
    normal.x.scatter_forward()
    return normal


class StokesFibers:
    """The Stokes problem of the module docstring on one geometry, built once.

    ``solve()`` returns the P2 velocity; ``fibers()`` the unit P1 fibre field and the
    nodal speed. Collective over the geometry's communicator.
    """

    def __init__(self, geometry: geo.Geometry, params: StokesParams = StokesParams(), inflow_speed=None):
        """``inflow_speed``: the normal inflow speed as a function of x (shape (3, n)), for flows
        whose exact field is known (tests); uniform 1 by default, as the method says."""
        self.geometry = geometry
        self.params = params
        mesh = geometry.mesh
        cell = mesh.topology.cell_name()
        velocity = basix.ufl.element("Lagrange", cell, params.degree, shape=(3,))
        pressure = basix.ufl.element("Lagrange", cell, params.degree - 1)
        self.W = fem.functionspace(mesh, basix.ufl.mixed_element([velocity, pressure]))
        self.V1 = fem.functionspace(mesh, ("Lagrange", 1, (3,)))

        metadata = {"quadrature_degree": params.quadrature_degree}
        dx = ufl.Measure("dx", domain=mesh, metadata=metadata)
        ds = ufl.Measure("ds", domain=mesh, subdomain_data=geometry.facet_tags, metadata=metadata)
        inflow, _ = geometry.ends
        lateral = geometry.lateral

        u, p = ufl.TrialFunctions(self.W)
        v, q = ufl.TestFunctions(self.W)
        n = ufl.FacetNormal(mesh)
        h = ufl.CellDiameter(mesh)
        gamma = fem.Constant(mesh, float(params.penalty))
        self.normals = {tag: vertex_normal(self.V1, ds(tag)) for tag in (inflow, lateral)}

        def eps(w):
            return ufl.sym(ufl.grad(w))

        def sigma(w, r):
            return 2.0 * eps(w) - r * ufl.Identity(3)

        def unit(w):
            return w / ufl.sqrt(ufl.dot(w, w))

        a = (ufl.inner(2.0 * eps(u), eps(v)) - p * ufl.div(v) - q * ufl.div(u)) * dx
        L = fem.Constant(mesh, 0.0) * q * dx
        speed = 1.0
        if inflow_speed is not None:
            speed = fem.Function(fem.functionspace(mesh, ("Lagrange", params.degree)))
            speed.interpolate(inflow_speed)
        for tag, flux in ((inflow, -speed), (lateral, 0.0)):
            N = unit(self.normals[tag])
            a += (-ufl.dot(N, sigma(u, p) * n) * ufl.dot(v, N)
                  - ufl.dot(N, sigma(v, q) * n) * ufl.dot(u, N)
                  + 2.0 * gamma / h * ufl.dot(u, N) * ufl.dot(v, N)) * ds(tag)
            if tag == inflow:
                L += flux * (-ufl.dot(N, sigma(v, q) * n) + 2.0 * gamma / h * ufl.dot(v, N)) * ds(tag)
        self.problem = LinearProblem(
            a, L,
            petsc_options_prefix=f"hyper_fibers_{next(_prefixes)}_",
            petsc_options={"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"},
        )

    def solve(self) -> fem.Function:
        """The velocity (P2); raises RuntimeError (on all ranks) if the solve failed."""
        w = self.problem.solve()
        reason = self.problem.solver.getConvergedReason()
        if reason < 0:
            raise RuntimeError(f"{self.geometry.name}: Stokes solve failed (KSP reason {reason})")
        return w.sub(0).collapse()

    def fibers(self) -> tuple[fem.Function, fem.Function]:
        """(a0, speed): the unit fibre field (vector P1) and |u| at the nodes (scalar P1)."""
        if self.params.smoothing_m > 0:
            return normalized(smoothed(self.solve(), self.V1, self.params.smoothing_m), self.params.min_speed,
                              self.geometry.name)
        u1 = fem.Function(self.V1)
        u1.interpolate(self.solve())
        # Ghost copies take the owner's value: interpolating from a different cell can
        # differ in the last bit, and the stored field is the owners' values.
        u1.x.scatter_forward()
        return normalized(u1, self.params.min_speed, self.geometry.name)


def smoothed(u: fem.Function, space: fem.FunctionSpace, length: float) -> fem.Function:
    """The vector P1 field w with (w, v) + l² (∇w, ∇v) = (u, v) for all v in ``space``.

    Why (docs/convergence.md): on a Visible Human surface the flow's direction next to the
    lateral surface follows the surface's facets (the STLs' neighbouring triangles differ
    by 4° in the median, 23° at the 95th percentile), and every finer mesh resolves more of
    them, so the unsmoothed field does not converge with the mesh (on TA_VHF_Left the 8k,
    16k and 32k fields differ from the 64k one by 9.4°, 6.3°, 3.5° at the 95th percentile).
    The filter keeps what is longer than l and removes the facets' ripple; its natural
    boundary condition leaves the flux and the mean direction alone.
    """
    mesh = space.mesh
    w, v = ufl.TrialFunction(space), ufl.TestFunction(space)
    ell2 = fem.Constant(mesh, float(length) ** 2)
    problem = LinearProblem(
        (ufl.inner(w, v) + ell2 * ufl.inner(ufl.grad(w), ufl.grad(v))) * ufl.dx, ufl.inner(u, v) * ufl.dx,
        petsc_options_prefix=f"hyper_fibers_smooth_{next(_prefixes)}_",
        petsc_options={"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"},
    )
    out = problem.solve()
    out.x.scatter_forward()
    return out


def normalized(u: fem.Function, min_speed: float, name: str) -> tuple[fem.Function, fem.Function]:
    """u/|u| at the nodes of a vector P1 function, and |u| as a scalar P1 function.

    Raises RuntimeError on every rank if some node is slower than ``min_speed``.
    """
    values = u.x.array.reshape(-1, 3)
    length = np.linalg.norm(values, axis=1)
    slowest = u.function_space.mesh.comm.allreduce(float(length.min(initial=np.inf)), op=MPI.MIN)
    if not slowest >= min_speed:
        raise RuntimeError(f"{name}: the flow stagnates (speed {slowest:.3g} < {min_speed:g} at a "
                           "node), where it has no direction")
    a0 = fem.Function(u.function_space, name="a0")
    a0.x.array[:] = (values / length[:, None]).ravel()
    speed = fem.Function(fem.functionspace(u.function_space.mesh, ("Lagrange", 1)), name="speed")
    speed.x.array[:] = length
    return a0, speed


def compute(geometry: geo.Geometry, params: StokesParams = StokesParams()) -> tuple[fem.Function, fem.Function]:
    """The Stokes-flow fibres of ``geometry``: (a0, speed), see ``StokesFibers.fibers``."""
    return StokesFibers(geometry, params).fibers()


# -------------------------------------------------------------------------- statistics


def principal_axis(geometry: geo.Geometry) -> np.ndarray:
    """The first principal axis of the vertex coordinates (every vertex once)."""
    _, axes = geo.principal_axes(geometry.mesh)
    return axes[:, 0]


def aligned_share(geometry: geo.Geometry, a0: fem.Function, axis, angle_deg: float = ALIGNMENT_DEG) -> float:
    """Share of the volume where a0 is within ``angle_deg`` of ±``axis``.

    Integrated with the geometry's quadrature rule (a0 renormalized at each point), so
    it is the rule's approximation of the volume of the region, the same on any number
    of ranks.
    """
    mesh = geometry.mesh
    axis = np.asarray(axis, dtype=float)
    # Constants, not literals: one compiled form serves every mesh and angle.
    direction = fem.Constant(mesh, axis / np.linalg.norm(axis))
    threshold = fem.Constant(mesh, math.cos(math.radians(angle_deg)))
    cosine = abs(ufl.dot(a0, direction)) / ufl.sqrt(ufl.dot(a0, a0))
    inside = ufl.conditional(ufl.ge(cosine, threshold), 1.0, 0.0)
    comm = geometry.comm
    part = comm.allreduce(fem.assemble_scalar(fem.form(inside * geometry.dx)), op=MPI.SUM)
    return part / geometry.reference_volume()


def max_norm_error(a0: fem.Function) -> float:
    """max over the nodes of | |a0| - 1 | (owned nodes, reduced over ranks)."""
    n = a0.function_space.dofmap.index_map.size_local
    values = a0.x.array.reshape(-1, 3)[:n]
    local = float(np.abs(np.linalg.norm(values, axis=1) - 1.0).max(initial=0.0))
    return a0.function_space.mesh.comm.allreduce(local, op=MPI.MAX)


def statistics(geometry: geo.Geometry, a0: fem.Function, speed: fem.Function | None = None) -> dict:
    """The numbers reported per mesh (collective)."""
    mesh = geometry.mesh
    stats = {
        "cells": geometry.num_cells(),
        "vertices": mesh.topology.index_map(0).size_global,
        "share_within_30deg": aligned_share(geometry, a0, principal_axis(geometry)),
        "max_norm_error": max_norm_error(a0),
    }
    if speed is not None:
        n = speed.function_space.dofmap.index_map.size_local
        local = speed.x.array[:n]
        stats["min_speed"] = mesh.comm.allreduce(float(local.min(initial=np.inf)), op=MPI.MIN)
        stats["max_speed"] = mesh.comm.allreduce(float(local.max(initial=-np.inf)), op=MPI.MAX)
    return stats


# ------------------------------------------------------------------ nodes and storage


def node_index(space: fem.FunctionSpace) -> np.ndarray:
    """For each local (owned and ghost) node of a P1 space: the mesh file's node index.

    For P1 on an affine mesh the dofs and the geometry nodes of a cell are listed in
    the same reference order, which gives the dof -> geometry node map.
    """
    mesh = space.mesh
    if space.ufl_element().degree != 1 or mesh.geometry.cmaps[0].degree != 1:
        raise ValueError("node_index needs a P1 space on an affine mesh")
    index_map = space.dofmap.index_map
    node = np.full(index_map.size_local + index_map.num_ghosts, -1, dtype=np.int64)
    node[space.dofmap.list.ravel()] = mesh.geometry.dofmaps[0].ravel()
    return np.asarray(mesh.geometry.input_global_indices, dtype=np.int64)[node]


def gather_nodal(a0: fem.Function, speed: fem.Function, root: int = 0) -> dict[str, np.ndarray] | None:
    """The datasets of a fibre file, sorted by file node index, on rank ``root`` (else None)."""
    space = a0.function_space
    comm = space.mesh.comm
    n = space.dofmap.index_map.size_local
    keys = node_index(space)[:n]
    x = space.tabulate_dof_coordinates()[:n]
    parts = comm.gather((keys, a0.x.array.reshape(-1, 3)[:n], x, speed.x.array[:n]), root=root)
    if comm.rank != root:
        return None
    keys, values, x, s = (np.concatenate(p) for p in zip(*parts))
    order = np.argsort(keys)
    return {"node": keys[order], "a0": values[order], "x": x[order], "speed": s[order]}


def fiber_path(name: str, meshes_dir: str | Path | None = None, kind: str = "auto") -> Path:
    """Where the fibres of geometry ``name`` live: next to its mesh file, ``FILE_NAME`` its
    own (whatever kind it holds: `stored_kind`); with ``kind`` "stokes" its Stokes fibres,
    ``STOKES_FILE_NAME`` where its own are another kind (the shipped meshes: Laplace)."""
    if name not in geo.GEOMETRIES:
        raise InputError(f"unknown geometry {name!r}; known: {', '.join(geo.GEOMETRIES)}")
    root = Path(meshes_dir) if meshes_dir is not None else geo.MESHES_DIR
    folder = root / Path(geo.GEOMETRIES[name]).parent
    return stokes_path(folder) if kind == "stokes" else folder / FILE_NAME


def stokes_path(folder: Path) -> Path:
    """The Stokes fibres' file in a mesh's ``folder``: ``STOKES_FILE_NAME`` where it exists
    or the mesh's own fibres (``FILE_NAME``) are of another kind, else ``FILE_NAME``."""
    folder = Path(folder)
    if (folder / STOKES_FILE_NAME).exists() or stored_kind(folder / FILE_NAME) != "stokes":
        return folder / STOKES_FILE_NAME
    return folder / FILE_NAME


def stored_kind(path: Path) -> str:
    """The kind of the fibres a complete fibre file holds (a file without a ``kind``, the
    Stokes fibres' `store`, holds Stokes fibres); "stokes" where there is no complete file
    (they are computed or `load` says how)."""
    if not is_complete(path):
        return "stokes"
    with reading_h5(path, "fibre file") as f:
        return str(f.attrs.get("kind", "stokes"))


def load(geometry: geo.Geometry, path: str | Path | None = None) -> fem.Function:
    """The stored Stokes fibres of ``geometry`` as a unit vector P1 function ("a0").

    ``path`` defaults to ``fiber_path(geometry.name)``. Works on any number of ranks:
    each local node takes the value stored under its file node index. The file must
    be complete and belong to this very mesh (same nodes, same coordinates), else
    InputError. Collective over the geometry's communicator.
    """
    path = Path(path) if path is not None else fiber_path(geometry.name, kind="stokes")
    comm = geometry.comm
    data: dict | str | None = None
    if comm.rank == 0:
        if not is_complete(path):
            data = (f"{path}: no complete fibre file; compute it with "
                    f"`python -m hyper.fibers --geometries {geometry.name}`")
        else:
            try:  # rank 0 alone reads: a damaged file is a message for every rank, not a raise here
                with reading_h5(path, "fibre file") as f:
                    data = {k: f[k][()] for k in ("node", "a0", "x")}
            except InputError as err:
                data = str(err)
    data = comm.bcast(data, root=0)
    if isinstance(data, str):
        raise InputError(data)

    space = fem.functionspace(geometry.mesh, ("Lagrange", 1, (3,)))
    keys = node_index(space)
    stored = data["node"]
    n_nodes = geometry.mesh.topology.index_map(0).size_global
    where = np.minimum(np.searchsorted(stored, keys), len(stored) - 1)
    x = space.tabulate_dof_coordinates()
    same = (len(stored) == n_nodes and np.array_equal(stored[where], keys)
            and bool(np.all(np.abs(data["x"][where] - x) <= 1e-12 * np.abs(data["x"]).max())))
    if not comm.allreduce(same, op=MPI.LAND):
        raise InputError(f"{path}: the fibres were computed on another mesh than {geometry.name!r} "
                         f"({len(stored)} stored nodes, the mesh has {n_nodes}, or the nodes or "
                         "their coordinates differ); recompute them with --force")
    a0 = fem.Function(space, name="a0")
    a0.x.array[:] = data["a0"][where].ravel()
    return a0


# ------------------------------------------------------------------------- fibre fields


def idealized_fiber(x: np.ndarray) -> np.ndarray:
    """MODEL.md §5: a0 ∝ (x/r y'(z), y/r y'(z), 0.2), a0 = e_z on the axis; x has shape (3, n)."""
    z = x[2]
    slope = np.where(z <= 0.1, 0.06 - 6.0 * z**2, 6.0 * z**2 - 2.4 * z + 0.18)
    r = np.hypot(x[0], x[1])
    on_axis = r < 1e-12
    r = np.where(on_axis, 1.0, r)
    a = np.vstack([np.where(on_axis, 0.0, x[0] / r * slope), np.where(on_axis, 0.0, x[1] / r * slope),
                   np.full_like(z, 0.2)])
    return a / np.linalg.norm(a, axis=0)


# Inside this radius (m) the original code set a0 = e_z (MODEL.md §9).
ORIGINAL_AXIS_RADIUS = 1e-4


def original_idealized_fiber(x: np.ndarray) -> np.ndarray:
    """The idealized fibres as the original code wrote them: `idealized_fiber`, but e_z
    wherever r < `ORIGINAL_AXIS_RADIUS`; x has shape (3, n)."""
    a = idealized_fiber(x)
    a[:, np.hypot(x[0], x[1]) < ORIGINAL_AXIS_RADIUS] = np.array([[0.0], [0.0], [1.0]])
    return a


def uniform_fiber_field(mesh, direction) -> fem.Function:
    """A constant unit fibre direction as a P1 vector function."""
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    a0 = fem.Function(fem.functionspace(mesh, ("Lagrange", 1, (3,))), name="a0")
    a0.interpolate(lambda x: np.tile(d[:, None], (1, x.shape[1])))
    return a0


# laplace: made by `hyper.fem.laplace` (which builds on this module); here read from a fibre file
FIBER_KINDS = ("auto", "idealized", "axial", "principal", "stokes", "original", "laplace")
# The kinds whose field the mechanics and the growth field must use as it is, not
# normalised at their points.
UNNORMALISED_KINDS = ("original",)
# How each kind is made, as a result records it (`method`)
METHODS = {
    "idealized": "analytic (MODEL.md §5), interpolated at the nodes of the mesh run (P1)",
    "axial": "uniform e_z (P1)",
    "principal": "uniform along the first principal axis of the loaded mesh's vertices, from ends[0] "
                 "to ends[1] (P1)",
    "stokes": METHOD,
    "original": "the original code's analytic field interpolated into P2, used as it is (MODEL.md §9)",
    "laplace": "the potential flow between the ends (hyper.fem.laplace), as the fibre file records it",
}
# what a refined mesh takes from the mesh it refines, by kind (the others are evaluated on it)
CARRIED = ("principal", "stokes", "laplace")
CARRIED_METHOD = "; made on the loaded mesh and interpolated onto its {n} uniform refinement(s), unit at the nodes"


def resolved(geometry: geo.Geometry, kind: str) -> str:
    """The kind "auto" stands for on ``geometry`` (the kind itself otherwise)."""
    if kind not in FIBER_KINDS:
        raise InputError(f"unknown fibre kind {kind!r}; expected one of {', '.join(FIBER_KINDS)}")
    if kind == "auto":
        if geometry.name in ("idealized", "cylinder"):
            return {"idealized": "idealized", "cylinder": "axial"}[geometry.name]
        if geometry.name in geo.GEOMETRIES:  # the kind its fibre file holds (rank 0 reads it)
            return geometry.comm.bcast(stored_kind(fiber_path(geometry.name)) if geometry.comm.rank == 0 else None,
                                       root=0)
        return "stokes"
    if kind == "original" and geometry.name not in ("idealized", "cylinder"):
        return "stokes"  # the paper's fibres of an anatomical mesh
    return kind


def method(geometry: geo.Geometry, kind: str) -> str:
    """How the fibres of ``kind`` on ``geometry`` are made, refinements included."""
    kind = resolved(geometry, kind)
    carried_over = CARRIED_METHOD.format(n=geometry.refinements) if kind in CARRIED and geometry.refinements else ""
    return METHODS[kind] + carried_over


def carried(a0: fem.Function, geometry: geo.Geometry) -> fem.Function:
    """A vector P1 field ``a0`` of an unrefined ancestor of ``geometry`` (`geo.refine`) on
    ``geometry``'s mesh, unit at its nodes.

    Level by level: each refinement's P1 space contains the coarser one, so the
    interpolant is the same function; the nodes it shares with the coarser mesh keep
    their values (to round-off), the new ones (edge midpoints) take the mean of the
    edge's two, normalised.
    """
    chain = []
    level = geometry
    while level.mesh is not a0.function_space.mesh:
        if level.parent is None:
            raise ValueError(f"{geometry.name}: the fibre field is not on a mesh this one refines")
        chain.append(level)
        level = level.parent
    for level in reversed(chain):
        mesh = level.mesh
        space = fem.functionspace(mesh, ("Lagrange", 1, (3,)))
        fine = fem.Function(space, name="a0")
        cell_map = mesh.topology.index_map(mesh.topology.dim)
        cells = np.arange(cell_map.size_local + cell_map.num_ghosts, dtype=np.int32)
        fine.interpolate_nonmatching(a0, cells, fem.create_interpolation_data(space, a0.function_space, cells))
        fine.x.scatter_forward()
        a0 = fine
    values = a0.x.array.reshape(-1, 3)
    values /= np.linalg.norm(values, axis=1)[:, None]
    return a0


# How far outside the flow's mesh a node may lie (m): its nearest cell's value. Tried in
# turn: the search costs grow fast with the padding (32k cells onto 8k: 18 s at 1 mm, 94 s
# at 3 mm, over 10 min at 10 mm), and most meshes of one surface need the first.
TRANSFER_PADDINGS_M = (0.001, 0.01)
TRANSFERRED_METHOD = ("; solved on a mesh of the same surface at {cells} cells and interpolated onto this "
                      "mesh's nodes, unit there")


def transferred(field: fem.Function, geometry: geo.Geometry) -> fem.Function:
    """A P1 field (vector or scalar) on another mesh of the same shape, interpolated at
    ``geometry``'s nodes. Meshes of one surface at two resolutions have different facets:
    a node outside the other mesh (by up to a few mm between coarse meshes) takes the
    value of its nearest cell within the first of TRANSFER_PADDINGS_M that finds one for
    every node; one further out than the last is an error."""
    space = fem.functionspace(geometry.mesh, ("Lagrange", 1, field.function_space.value_shape))
    out = fem.Function(space, name=field.name)
    cmap = geometry.mesh.topology.index_map(geometry.mesh.topology.dim)
    cells = np.arange(cmap.size_local + cmap.num_ghosts, dtype=np.int32)
    for padding in TRANSFER_PADDINGS_M:
        out.x.array[:] = 0.0
        out.interpolate_nonmatching(field, cells, fem.create_interpolation_data(space, field.function_space, cells,
                                                                               padding=padding))
        out.x.scatter_forward()
        found = bool(np.all(np.abs(out.x.array.reshape(-1, space.dofmap.index_map_bs)).max(axis=1) > 0))
        if geometry.comm.allreduce(found, op=MPI.LAND):
            return out
    raise RuntimeError(f"{geometry.name}: some nodes lie further than {padding:g} m from the mesh "
                       "the field was computed on")


def compute_transferred(geometry: geo.Geometry, flow: geo.Geometry, params: StokesParams = StokesParams()
                        ) -> tuple[fem.Function, fem.Function]:
    """The Stokes fibres of ``geometry`` solved on ``flow``, a finer mesh of the same
    surface, and carried onto ``geometry``'s nodes: (a0 unit at the nodes, speed)."""
    return carried_over(*StokesFibers(flow, params).fibers(), geometry, params.min_speed)


def carried_over(a0: fem.Function, speed: fem.Function, geometry: geo.Geometry, min_speed: float
                 ) -> tuple[fem.Function, fem.Function]:
    """Fibres (a0, speed) of another mesh of the same surface on ``geometry``'s nodes: the
    velocity a0·speed interpolated there (`transferred`), unit there, and its speed."""
    u = transferred(a0, geometry)
    u.x.array[:] *= np.repeat(transferred(speed, geometry).x.array, 3)
    return normalized(u, min_speed, geometry.name)


def store(path: str | Path, geometry: geo.Geometry, a0: fem.Function, speed: fem.Function,
          params: StokesParams = StokesParams(), **attrs) -> None:
    """Write the Stokes fibres of ``geometry`` to ``path`` as a fibre file (module
    docstring), atomically, on rank 0, with the method, the statistics and ``attrs``.
    Collective."""
    stats = statistics(geometry, a0, speed)
    data = gather_nodal(a0, speed)
    if geometry.comm.rank == 0:
        write_series(path, data,
                     attrs={"geometry": geometry.name, "method": stokes_method(params), "element": ELEMENT,
                            "reference": "Varvik et al. 2021; MODEL.md §5", "inflow_tag": geometry.ends[0],
                            "outflow_tag": geometry.ends[1], "lateral_tag": geometry.lateral, "coordinates": "m",
                            "ranks": geometry.comm.size, **stats, **attrs},
                     groups={"parameters": as_attributes(params)})
    geometry.comm.barrier()


def fiber_field(geometry: geo.Geometry, kind: str = "auto", path: str | Path | None = None) -> fem.Function:
    """The reference fibre direction a0 as a vector P1 function, unit length at the nodes.

    kind: "idealized" the analytic spline fibres of MODEL.md §5; "axial" e_z (the axis of
    the cylinder and the idealized shape); "principal" the first principal axis of the
    vertex coordinates, oriented from end Γ1 to Γ2 (a stand-in for tests); "stokes" the
    Stokes-flow fibres stored next to an anatomical mesh (`load`, MODEL.md §5), or in
    ``path``; "laplace" the Laplace fibres stored there (`hyper.fem.laplace`); "auto" picks
    the first for `idealized`, the second for `cylinder` and for the others the kind their
    fibre file holds (the shipped meshes': Laplace). "original": the original code's fibres,
    on the idealized shape its field (`original_idealized_fiber`) interpolated into vector
    P2, which the original used as it is, unit at the nodes only (MODEL.md §9; see
    `UNNORMALISED_KINDS`), on an anatomical mesh the paper's Stokes fibres.

    Why P1: every fibre source (analytic, Stokes flow) can be written at vertices, XDMF
    stores and ParaView shows it as is, and any quadrature or DG space the forms or the
    growth tensors use interpolates it. Between the nodes |a0| dips below 1 where the
    fibres turn (by up to 4 % next to the idealized shape's axis, where the formula
    jumps); `MechanicsProblem` and the growth field normalise at their points.

    A refined geometry (`geo.refine`) evaluates the analytic kinds at its own nodes; the
    kinds of `CARRIED` belong to the loaded mesh (a fibre file's nodes, its vertices'
    axis) and are made there, then `carried` onto the refined mesh.
    """
    kind = resolved(geometry, kind)
    if kind in CARRIED and geometry.parent is not None:
        return carried(fiber_field(geometry.base, kind, path), geometry)
    if kind in ("stokes", "laplace"):
        path = Path(path) if path is not None else fiber_path(geometry.name, kind=kind)
        held = geometry.comm.bcast(stored_kind(path) if geometry.comm.rank == 0 else None, root=0)
        if held != kind:  # a Laplace field is made by hyper.fem.laplace (hyper.runs.driver.laplace_fibres)
            raise InputError(f"{path}: holds {held} fibres, not {kind}")
        return load(geometry, path)
    if kind == "original":
        if geometry.name != "idealized":
            raise InputError(f"the original fibres are those of the idealized shape, not of {geometry.name!r}")
        a0 = fem.Function(fem.functionspace(geometry.mesh, ("Lagrange", 2, (3,))), name="a0")
        a0.interpolate(original_idealized_fiber)
        return a0
    if kind == "axial":
        return uniform_fiber_field(geometry.mesh, (0.0, 0.0, 1.0))
    if kind == "principal":
        _, axes = geo.principal_axes(geometry.mesh)
        axis = axes[:, 0]
        if np.dot(geo.facet_centroid(geometry, geometry.ends[1]) - geo.facet_centroid(geometry, geometry.ends[0]),
                  axis) < 0:
            axis = -axis
        return uniform_fiber_field(geometry.mesh, axis)
    a0 = fem.Function(fem.functionspace(geometry.mesh, ("Lagrange", 1, (3,))), name="a0")
    a0.interpolate(idealized_fiber)
    return a0


# ---------------------------------------------------------------------- cells (pictures)


def cell_fibers(geometry: geo.Geometry, a0: fem.Function, root: int = 0):
    """(centroids (n, 3), unit fibres (n, 3), volumes (n,)) of all cells, in the mesh
    file's cell order, on rank ``root`` (None elsewhere). The fibre of a cell is the
    normalized mean of its nodal values."""
    mesh = geometry.mesh
    comm = mesh.comm
    n = mesh.topology.index_map(mesh.topology.dim).size_local
    corners = mesh.geometry.x[mesh.geometry.dofmaps[0][:n]]
    volume = np.abs(np.linalg.det(corners[:, 1:] - corners[:, :1])) / 6.0
    dofs = a0.function_space.dofmap.list[:n]
    mean = a0.x.array.reshape(-1, 3)[dofs].mean(axis=1)
    mean /= np.linalg.norm(mean, axis=1)[:, None]
    original = np.asarray(mesh.topology.original_cell_index[:n], dtype=np.int64)
    parts = comm.gather((original, corners.mean(axis=1), mean, volume), root=root)
    if comm.rank != root:
        return None
    original, centroid, fiber, volume = (np.concatenate(p) for p in zip(*parts))
    order = np.argsort(original)
    return centroid[order], fiber[order], volume[order]

