"""Laplace fibres: the potential flow through a muscle from one end to the other.

The paper's fibres (`hyper.fem.fibers`) are the velocity of a Stokes flow entering at one
end, leaving at the other and sliding along the lateral surface. This is the same flow
without viscosity: the gradient of a potential φ,

    -Δφ = 0                      in Ω
    ∇φ·n = -1                    on Γin  (ends[0]: unit inflow speed, as the Stokes flow's)
    ∇φ·n = |Γin| / |Γout|        on Γout (ends[1]: the same flux out, uniform)
    ∇φ·n = 0                     on the lateral surface

and a0 = ∇φ/|∇φ| at the nodes. This is Choi & Blemker's Laplacian flow (PLoS ONE 8:e77576,
2013; `hyper.fem.pennate` makes it between aponeuroses one names) with the two ends as the
attachments.

Why (docs/convergence.md, "Laplace fibres converge"): on the wide muscles the Stokes field
does not settle as the mesh of the surface is refined (VL_VHM_Left: 46°, 29°, 18° at the
95th percentile between its 8k, 16k, 32k fields and the 64k one; the share of the volume
within 30° of the axis 67, 73, 78, 83 %). A free-slip wall makes vorticity where it curves,
and every finer mesh of a Visible Human surface resolves more of its creases, which turns
the slow flow in the wide belly. A potential flow has no vorticity; its gradient depends on
the shape only through a harmonic function, which moves little when the boundary moves a
little. On the same meshes the Laplace fibres are 2.4°, 1.7°, 1.3° from the 64k field.

Discretisation: φ in P2 on the mechanics mesh (in P1 its gradient is constant per cell:
6.6°, 4.8°, 3.4° on the same meshes, L2-projected), pinned at one dof (its data sum to
zero, so the other equations hold exactly), one MUMPS LU; ∇φ projected onto vector P1 with
the Stokes fibres' 2 mm smoothing, (w, z) + l²(∇w, ∇z) = (∇φ, z) (``smoothing_m``; 0 is the
L2 projection: 4.4°, 2.8°, 2.0°), by conjugate gradients, and normalised at the nodes. A
node where |∇φ| falls below ``min_speed`` of the inflow speed has no direction: an error.

The fibre file is `hyper.fem.fibers`'s (datasets node, a0, x, speed) with ``kind =
"laplace"``; `hyper mesh` writes it by default and `hyper fibers --mesh F --method laplace`
beside any mesh file, and a run on that mesh records ``fibers = laplace``.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
import numpy as np
import ufl
from dolfinx import fem
from dolfinx.fem.petsc import LinearProblem
from mpi4py import MPI

from hyper.core.io import write_series
from hyper.core.params import InputError, as_attributes, check_positive
from hyper.fem import fibers
from hyper.fem import geometry as geo

KIND = "laplace"
REFERENCE = "Choi & Blemker 2013 (PLoS ONE 8:e77576), the ends as attachments; docs/convergence.md"

_prefixes = itertools.count()


@dataclasses.dataclass(frozen=True)
class LaplaceParams:
    degree: int = 2  # of φ (the fibres are its gradient, projected onto P1)
    min_speed: float = 1.0e-6  # (1, of the inflow speed) below it a node has no fibre direction
    # (m) length l of the projection (w, z) + l² (∇w, ∇z) = (∇φ, z) of the gradient onto P1
    # (0: the L2 projection); 2 mm as the Stokes fibres' of `hyper mesh`: the facets' ripple
    # goes, the 8k-cell fibres come within 2.4° (p95) of the 64k ones on VL_VHM_Left
    smoothing_m: float = 0.002

    def __post_init__(self):
        check_positive(self, "min_speed")
        if not (isinstance(self.smoothing_m, (int, float)) and math.isfinite(self.smoothing_m)
                and 0.0 <= self.smoothing_m <= 0.05):
            raise InputError(f"smoothing_m must be a length in [0, 0.05] m, got {self.smoothing_m!r}")
        if self.degree not in (1, 2):
            raise InputError(f"degree must be 1 or 2, got {self.degree!r}")


def method(params: LaplaceParams = LaplaceParams()) -> str:
    projection = ("the L2 projection of grad phi onto P1" if params.smoothing_m == 0 else
                  f"grad phi projected onto P1 and smoothed over {params.smoothing_m * 1e3:g} mm "
                  f"((w, z) + l^2 (grad w, grad z) = (grad phi, z), l = {params.smoothing_m * 1e3:g} mm)")
    return (f"potential flow from ends[0] to ends[1] (Laplace, P{params.degree}): uniform inflow speed 1 "
            f"through ends[0], the same flux out of ends[1] uniformly, none through the lateral surface; "
            f"a0 = {projection}, unit at the nodes")


def compute(geometry: geo.Geometry, params: LaplaceParams = LaplaceParams(), inflow_speed=None
            ) -> tuple[fem.Function, fem.Function]:
    """(a0, speed) of ``geometry``: the unit fibres and |∇φ| (of the inflow speed) at the
    nodes, vector and scalar P1. ``inflow_speed``: the flux density g as a function of x
    (shape (3, n)) on both ends (-g in, +g scaled to the same total out), for flows whose
    exact field is known (tests); 1 by default, as the method says. Collective;
    RuntimeError on every rank if a solve fails or the flow stagnates at a node."""
    mesh = geometry.mesh
    comm = geometry.comm
    inflow, outflow = geometry.ends
    ds = ufl.Measure("ds", domain=mesh, subdomain_data=geometry.facet_tags)
    V = fem.functionspace(mesh, ("Lagrange", params.degree))
    g = fem.Constant(mesh, 1.0)
    if inflow_speed is not None:
        g = fem.Function(V)
        g.interpolate(inflow_speed)
    total = [comm.allreduce(fem.assemble_scalar(fem.form(g * ds(tag))), op=MPI.SUM) for tag in (inflow, outflow)]
    if not min(total) > 0.0:
        raise InputError(f"{geometry.name}: an end (facet tag {inflow} or {outflow}) has no facets")

    phi, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    index_map = V.dofmap.index_map
    local = np.arange(index_map.size_local + index_map.num_ghosts, dtype=np.int32)
    # the dof of global index 0, on its owner and wherever it is a ghost: every rank that
    # assembles its row or column must know the condition
    pinned = local[index_map.local_to_global(local) == 0]
    ratio = fem.Constant(mesh, total[0] / total[1])  # a Constant: one compiled form for every mesh
    potential = _solved(LinearProblem(
        ufl.inner(ufl.grad(phi), ufl.grad(v)) * ufl.dx, -g * v * ds(inflow) + ratio * g * v * ds(outflow),
        bcs=[fem.dirichletbc(np.float64(0.0), pinned, V)],
        petsc_options_prefix=f"hyper_laplace_{next(_prefixes)}_",
        petsc_options={"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"}),
        geometry.name, "Laplace")

    V1 = fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    w, z = ufl.TrialFunction(V1), ufl.TestFunction(V1)
    ell2 = fem.Constant(mesh, float(params.smoothing_m) ** 2)
    # the P1 mass matrix is well conditioned, and l² (∇w, ∇z) adds at most (l/h)² times it,
    # so CG with Jacobi reaches round-off in tens of iterations on any number of ranks
    gradient = _solved(LinearProblem(
        (ufl.inner(w, z) + ell2 * ufl.inner(ufl.grad(w), ufl.grad(z))) * ufl.dx,
        ufl.inner(ufl.grad(potential), z) * ufl.dx,
        petsc_options_prefix=f"hyper_laplace_grad_{next(_prefixes)}_",
        petsc_options={"ksp_type": "cg", "pc_type": "jacobi", "ksp_rtol": 1.0e-12, "ksp_atol": 0.0,
                       "ksp_max_it": 1000}),
        geometry.name, "gradient projection")
    return fibers.normalized(gradient, params.min_speed, geometry.name)


def _solved(problem: LinearProblem, name: str, what: str) -> fem.Function:
    out = problem.solve()
    reason = problem.solver.getConvergedReason()
    if reason < 0:
        raise RuntimeError(f"{name}: the {what} solve failed (KSP reason {reason})")
    out.x.scatter_forward()
    return out


def store(path: str | Path, geometry: geo.Geometry, a0: fem.Function, speed: fem.Function,
          params: LaplaceParams = LaplaceParams(), described: str | None = None, **attrs) -> None:
    """Write the fibres as a fibre file (`hyper.fem.fibers`'s format) with ``kind =
    "laplace"``, the method (``described``, where the flow was solved on another mesh), the
    statistics and ``attrs``; atomic, on rank 0. Collective."""
    stats = fibers.statistics(geometry, a0, speed)
    data = fibers.gather_nodal(a0, speed)
    if geometry.comm.rank == 0:
        write_series(path, data,
                     attrs={"geometry": geometry.name, "kind": KIND, "method": described or method(params),
                            "element": fibers.ELEMENT, "reference": REFERENCE, "inflow_tag": geometry.ends[0],
                            "outflow_tag": geometry.ends[1], "lateral_tag": geometry.lateral, "coordinates": "m",
                            "ranks": geometry.comm.size, **stats, **attrs},
                     groups={"parameters": as_attributes(params)})
    geometry.comm.barrier()
