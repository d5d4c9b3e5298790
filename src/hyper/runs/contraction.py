"""The contraction run: ramp the activation α from 0 to 1 on one geometry (``hyper
contraction``, `hyper.commands.contraction`; `hyper.analysis.reproduce` and the
mechanics benchmark run it too).

`contract` writes <output>.h5 (the series `SERIES` in `UNITS`, the groups material and
settings), <output>_fields.xdmf (`Fields`: displacement u and pressure p on P1, fibre
stretch λ per cell, one time step per activation level) and <output>.png (`plot`: force
against activation). `advance` moves α to a target, retrying a step whose Newton solve
fails as two half steps.
"""

from __future__ import annotations

import resource
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
import numpy as np
from dolfinx import fem
from mpi4py import MPI

from hyper.core import io
from hyper.core.collective import on_rank0
from hyper.core.log import Progress, info
from hyper.core.params import as_attributes
from hyper.fem import fibers
from hyper.fem import geometry as geo
from hyper.fem.mechanics import MechanicsProblem, SolverError
from hyper.runs import checkpoint as ckpt
from hyper.runs import driver, plot, runspec

SERIES = ("alpha", "end_force", "spring_force", "reaction_force_original", "reaction_force_current",
          "newton_iterations", "krylov_iterations", "volume_ratio", "stretch_min", "stretch_max", "wall_s")
UNITS = {"alpha": "1", "end_force": "N", "spring_force": "N", "reaction_force_original": "N",
         "reaction_force_current": "N", "newton_iterations": "count", "krylov_iterations": "count",
         "volume_ratio": "1", "stretch_min": "1", "stretch_max": "1", "wall_s": "s"}


class Fields:
    """Output fields on spaces XDMF stores: P1 displacement and pressure, DG0 fibre stretch."""

    def __init__(self, problem):
        mesh = problem.geometry.mesh
        self.problem = problem
        self.u = fem.Function(fem.functionspace(mesh, ("Lagrange", 1, (3,))), name="u")
        self.p = fem.Function(fem.functionspace(mesh, ("Lagrange", 1)), name="p")
        dg0 = fem.functionspace(mesh, ("DG", 0))
        self.stretch = fem.Function(dg0, name="fibre_stretch")
        self._stretch_expr = fem.Expression(problem.fibre_stretch, dg0.element.interpolation_points)
        self._ncells = mesh.topology.index_map(3).size_local

    def update(self):
        self.u.interpolate(self.problem.u)
        self.p.interpolate(self.problem.p)
        self.stretch.interpolate(self._stretch_expr)
        return self.u, self.p, self.stretch

    def stretch_range(self) -> tuple[float, float]:
        values = self.stretch.x.array[: self._ncells]
        comm = self.problem.comm
        return comm.allreduce(values.min(), op=MPI.MIN), comm.allreduce(values.max(), op=MPI.MAX)


def peak_rss_mb() -> float:
    """This process's peak resident memory so far (MB; Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def advance(problem, target: float, max_halvings: int) -> tuple[int, int]:
    """Move α from its current value to ``target``, halving the step on failure.

    Returns (Newton iterations, deepest halving).
    """
    start = float(problem.alpha.value)
    try:
        problem.alpha.value = target
        return problem.solve(), 0
    except SolverError:
        problem.alpha.value = start
        if max_halvings == 0:
            raise
    middle = 0.5 * (start + target)
    its1, h1 = advance(problem, middle, max_halvings - 1)
    its2, h2 = advance(problem, target, max_halvings - 1)
    return its1 + its2, 1 + max(h1, h2)


def figure(path: Path, series: dict, title: str) -> None:
    fig, (ax, ax2) = plot.pyplot().subplots(1, 2, figsize=(10, 4))
    ax.plot(series["alpha"], series["end_force"], "o-", label=r"$d\cdot\int_{\Gamma_1} P N\,dA$ (resultant)")
    ax.plot(series["alpha"], series["reaction_force_original"], "^--",
            label=r"$\int_{\Gamma_1} (\sigma N)\cdot N\,dA$ (original)")
    ax.plot(series["alpha"], series["reaction_force_current"], "s:",
            label=r"$\int_{\Gamma_1} (PN)\cdot n\,dA$ (current)")
    ax.set_xlabel("activation α")
    ax.set_ylabel("force on Γ1 (N)")
    ax.legend()
    ax.grid(alpha=0.3)
    ax2.fill_between(series["alpha"], series["stretch_min"], series["stretch_max"], alpha=0.3, label="cell range")
    ax2.set_xlabel("activation α")
    ax2.set_ylabel("fibre stretch λ")
    ax2.legend()
    ax2.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    plot.save(fig, path, dpi=120)


def contract(comm, args) -> dict:
    """The activation ramp of the job's ``args`` on ``comm``: the series (and the files)."""
    source = getattr(args, "fiber_data", None)  # fibres from data (--fibers FILE)
    original = source is None and args.fibers in fibers.UNNORMALISED_KINDS
    geometry = geo.load(args.geometry, comm, quadrature_degree=args.quadrature_degree, ends=args.ends,
                        estimated_surface_degree=original)
    for _ in range(args.refine):
        geometry = geo.refine(geometry)
    if source is not None:
        a0, record = driver.data_fibres(geometry, source, driver.stokes_file(args.geometry),
                                        f"contraction {args.geometry}")
    elif args.fibers == "laplace" and not driver.stored_laplace(geometry):
        a0, record = driver.laplace_fibres(geometry)
    else:
        a0, record = driver.built_in_fibres(geometry, args.geometry, fibers.resolved(geometry, args.fibers))
    material = args.material
    solver = getattr(args, "linear_solver", "lu")
    problem = MechanicsProblem(geometry, a0, material, normalize_fibres=not original, linear_solver=solver)
    info(comm, f"{args.geometry}: {geometry.num_cells()} cells, {problem.num_dofs} unknowns, "
               f"{comm.size} rank(s); rigid motions: {problem.rigid.description}")
    fields = Fields(problem)
    volume0 = problem.volume()
    series = {name: [] for name in SERIES}
    output = args.output
    xdmf_path = output.with_name(output.stem + "_fields.xdmf")
    progress = Progress(comm, args.steps, f"contraction {args.geometry}", every=0.0)
    start = time.perf_counter()
    with io.atomic_xdmf(comm, xdmf_path) as xdmf:
        xdmf.write_mesh(geometry.mesh)
        for k, alpha in enumerate(np.linspace(0.0, 1.0, args.steps + 1)):
            krylov = problem.krylov_iterations
            iterations, halvings = advance(problem, float(alpha), args.max_halvings)
            for f in fields.update():
                xdmf.write_function(f, float(alpha))
            lo, hi = fields.stretch_range()
            values = (float(alpha), problem.end_force(), problem.spring_force(), problem.reaction_force_original(),
                      problem.reaction_force_current(), iterations, problem.krylov_iterations - krylov,
                      problem.volume() / volume0, lo, hi,
                      time.perf_counter() - start)
            for name, value in zip(SERIES, values):
                series[name].append(value)
            progress.update(k, f"α = {alpha:.3f}: end force {values[1]:.4e} N, original R {values[3]:.4e} N, "
                               f"λ in [{lo:.4f}, {hi:.4f}], {iterations} Newton its"
                               + (f" ({values[6]} {solver} Krylov its)" if solver != "lu" else "")
                               + (f" ({halvings} halvings)" if halvings else ""), force=True)
    attrs = {
        "geometry": args.geometry,
        "steps": args.steps,
        **record,
        "fibres_normalised": not original,
        "refine": args.refine,
        "ends": args.ends,
        "end_areas_m2": [geometry.area(tag) for tag in geometry.ends],
        "end_axis": problem.end_axis,
        "surface_quadrature_degree": "estimated" if geometry.estimated_surface_degree else geometry.quadrature_degree,
        "mesh_sha256": on_rank0(comm, lambda: ckpt.file_digest(
            *runspec.mesh_files(geo.MESHES_DIR / geo.GEOMETRIES[args.geometry]))),
        "cells": geometry.num_cells(),
        "unknowns": problem.num_dofs,
        "ranks": comm.size,
        "quadrature_degree": geometry.quadrature_degree,
        "linear_solver": solver,
        # the largest resident set of any rank, and their sum: what a node must hold
        "peak_rss_mb": comm.allreduce(peak_rss_mb(), op=MPI.MAX),
        "peak_rss_mb_sum": comm.allreduce(peak_rss_mb(), op=MPI.SUM),
        "rigid_motions": problem.rigid.description,
        "fields_xdmf": xdmf_path.name,
    }
    settings = {"steps": args.steps, "fibers": args.fibers, "ends": args.ends, "refine": args.refine,
                "quadrature_degree": geometry.quadrature_degree,
                "max_halvings": args.max_halvings, "petsc_prefix": problem.snes.getOptionsPrefix(),
                "petsc_options": " ".join(args.petsc),
                "snes_rtol": problem.snes.getTolerances()[0], "snes_atol": problem.snes.getTolerances()[1]}
    if comm.rank == 0:
        io.write_series(output, series, attrs=attrs, units=UNITS,
                        groups={"material": as_attributes(material), "settings": settings})
        figure(output.with_suffix(".png"), series, f"{args.geometry}: {geometry.num_cells()} cells, "
                                                  f"{problem.num_dofs} unknowns")
    comm.barrier()
    return series
