"""Scratch check (issue 33): DOLFINx assembles a MATIS equal to the AIJ matrix.

    PYTHONPATH=src mpirun -n 2 python jobs/solver_matis_check.py

A P2 vector Laplacian on the cylinder, assembled as MATIS (kind="is") and as AIJ; prints
the type and the norm of the difference on each rank.
"""

import dolfinx_solver  # noqa: F401
import ufl
from dolfinx import fem
from dolfinx.fem import petsc as fp
from mpi4py import MPI
from petsc4py import PETSc

from hyper.fem import geometry as geo

g = geo.load("cylinder", MPI.COMM_WORLD)
V = fem.functionspace(g.mesh, ("Lagrange", 2, (3,)))
u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
a = fem.form(ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx)
A = fp.create_matrix(a, kind="is")
fp.assemble_matrix(A, a)
A.assemble()
B = fp.assemble_matrix(a)
B.assemble()
C = A.convert("aij", PETSc.Mat())
C.axpy(-1.0, B)
print(MPI.COMM_WORLD.rank, A.getType(), A.getSize(), "|A_is - A_aij| =", C.norm(), "|A_aij| =", B.norm())
