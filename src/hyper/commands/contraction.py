"""hyper contraction: ramp the activation α from 0 to 1 on one geometry.

Writes <output>.h5 (series alpha, end_force, spring_force, reaction_force_original,
reaction_force_current, newton_iterations, krylov_iterations, volume_ratio, stretch_min,
stretch_max; the groups material and settings; the attributes linear_solver and peak_rss_mb),
<output>_fields.xdmf (displacement u and pressure p on P1, fibre stretch λ per cell, one
time step per activation level) and <output>.png (force against activation).
The forces on the end Γ1 (N, positive in tension), along its mean outward normal d:
end_force, the resultant d·∫ P N dA (the headline: converged to about 3 % on the
idealized mesh, python -m hyper.bench refinement), equal by equilibrium to
spring_force, the tendon spring's resultant; reaction_force_original, the original
code's ∫ (σN)·N dA, Cauchy stress over reference area, which converges slowly and
depends on the fibres in the end cells (MODEL.md §9); reaction_force_current, ∫ (PN)·n dA.
The original code's idealized shape: --ends tags --fibers original (P2 fibres as they
are, surface integrals at UFL's estimated degree) gives its reaction_force_original at
α = 1, 0.9291244 N.
A step whose Newton solve fails is retried as two half steps, down to --max-halvings.
Options after the known ones go to PETSc under the prefix mechanics_ (for example
-mechanics_snes_monitor).
"""

from __future__ import annotations

import sys
from pathlib import Path

import dolfinx_solver  # noqa: F401  (before petsc4py)
from mpi4py import MPI
from petsc4py import PETSc

from hyper.commands import cli
from hyper.core import io, log
from hyper.core.log import info
from hyper.core.params import InputError
from hyper.fem import fibers
from hyper.fem import geometry as geo
from hyper.fem.mechanics import LINEAR_SOLVERS, SolverError
from hyper.model import material as mat
from hyper.runs import locks, presets
from hyper.runs.contraction import contract, peak_rss_mb


class _Parser(cli.Parser):
    """Single-dash words after the known options are PETSc's: kept in ``args.petsc``."""

    def parse_args(self, args=None, namespace=None):
        args, rest = self.parse_known_args(args, namespace)
        stray = [a for a in rest if a.startswith("--")]
        if stray:
            raise InputError(f"unknown option(s) {' '.join(stray)}; PETSc options take one dash")
        args.petsc = rest
        return args


def parser() -> cli.Parser:
    p = _Parser("contraction", description=__doc__)
    p.add_argument("--geometry", default="idealized", help="geometry identifier")
    p.add_argument("--ends", choices=geo.IDEALIZED_ENDS, default="disks",
                   help="the idealized shape's spring ends: the flat end disks, or the XDMF's end tags with "
                        "their lateral band (the original code)")
    p.add_argument("--steps", type=cli.integer(1, 10**4), default=10, help="equal activation steps from 0 to 1")
    p.add_argument("--output", type=cli.output(folder=False, suffixes=(".h5",)),
                   help="HDF5 series file; results/contraction/GEOMETRY.h5 by default")
    p.add_argument("--fibers", default="auto", metavar="KIND|FILE",
                   help=f"fibre field kind: {', '.join(fibers.FIBER_KINDS)} (see hyper.fem.fibers.fiber_field); "
                        f"original: the original code's idealized fibres, with its surface quadrature; "
                        f"{presets.DATA_HELP}")
    cli.fibre_data_options(p)
    p.add_argument("--material", type=Path, metavar="F.toml", reads=True,
                   help="TOML file overriding the muscle law's parameters (hyper.model.material.MaterialParams)")
    p.add_argument("--quadrature-degree", type=cli.integer(1, 12), default=4, help="quadrature degree of the forms")
    cli.refine_option(p)
    p.add_argument("--linear-solver", choices=LINEAR_SOLVERS, default="lu",
                   help="MUMPS LU; GMRES with MUMPS's block low-rank LU; or pmg, GMRES with a Schur fieldsplit "
                        "and a P2 -> P1 multigrid on the displacements (memory linear in the mesh: for meshes "
                        "LU cannot hold); all three give the answer to the Newton tolerance")
    p.add_argument("--max-halvings", type=cli.integer(0, 12), default=6, help="step cuts allowed per step")
    return p


def run(comm, args) -> int:
    args.fiber_data = presets.data_source(args, fibers.FIBER_KINDS)
    if args.fiber_data is not None and args.ends != "disks":
        raise InputError("--ends applies to the idealized shape with its own fibres, not with --fibers FILE")
    args.material = mat.load(args.material) if args.material is not None else mat.MaterialParams()
    if args.output is None:
        args.output = Path("results/contraction") / f"{Path(args.geometry).name}.h5"
        problem = io.unwritable(args.output, folder=False)
        if problem is not None:
            raise InputError(f"--output: {problem}")
    if args.petsc:
        PETSc.Options().insertString(" ".join(args.petsc))
    try:
        with locks.hold(comm, [args.output]):
            series = contract(comm, args)
    except SolverError as err:
        log.error(comm, f"{err} (after {args.max_halvings} step halvings)")
        return cli.EXIT_SOME_FAILED
    info(comm, f"end force at α = 1: {series['end_force'][-1]:.6f} N (spring {series['spring_force'][-1]:.6f} N; "
               f"the original's ∫(σN)·N dA {series['reaction_force_original'][-1]:.7f} N); "
               f"fibre stretch range at α = 1: [{series['stretch_min'][-1]:.4f}, {series['stretch_max'][-1]:.4f}]; "
               f"{sum(series['krylov_iterations'])} {args.linear_solver} Krylov its, peak memory "
               f"{comm.allreduce(peak_rss_mb(), op=MPI.MAX):.0f} MB a rank; "
               f"wrote {args.output}")
    return cli.EXIT_OK


main = cli.entry(parser, run)

if __name__ == "__main__":
    sys.exit(main())
