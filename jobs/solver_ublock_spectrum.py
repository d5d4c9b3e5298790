"""Scratch diagnostic (issue 33): is the displacement block of the Newton matrix definite?

    PYTHONPATH=src python jobs/solver_ublock_spectrum.py GEOMETRY

The 12 generalized eigenvalues A x = λ M_u x nearest -1e-3 μ (shift-invert), divided by μ
(so in 1/m²), of the symmetric part of the Jacobian's displacement block at the first
Newton iterate of the bench's growth solve (the reference state, ϑ = 1.05), 1 rank.
"""
import sys

import dolfinx_solver  # noqa
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla
import ufl
from dolfinx import fem
from dolfinx.fem import petsc as fp
from mpi4py import MPI

from hyper.fem import fibers
from hyper.fem import geometry as geo
from hyper.fem.mechanics import MechanicsProblem
from hyper.model import growth

comm = MPI.COMM_SELF
g = geo.load(sys.argv[1], comm)
a0 = fibers.fiber_field(g)
theta = fem.Constant(g.mesh, 1.05)
Fg = growth.transverse_growth_ufl(theta**2, a0 / ufl.sqrt(ufl.dot(a0, a0)))
pr = MechanicsProblem(g, a0, growth=Fg)
pr.load_state(pr.solution_vector)
pr.assemble_jacobian(pr.solution_vector)
Vu, udofs = pr.W.sub(0).collapse()
udofs = np.asarray(udofs).ravel()
ai, aj, av = pr.jacobian_matrix.getValuesCSR()
K = sp.csr_matrix((av, aj, ai), shape=pr.jacobian_matrix.getSize())
A = K[udofs][:, udofs]
print("asymmetry", abs(A - A.T).max() / abs(A).max())
A = 0.5 * (A + A.T)
M = fp.assemble_matrix(fem.form(ufl.dot(ufl.TrialFunction(Vu), ufl.TestFunction(Vu)) * g.dx))
M.assemble()
mi, mj, mv = M.getValuesCSR()
M = sp.csr_matrix((mv, mj, mi), shape=M.getSize())
mu = 2 * (pr.material.c1 + pr.material.c2)
vals = sla.eigsh(A.tocsc(), k=12, M=M.tocsc(), sigma=-1e-3 * mu, which="LM", return_eigenvectors=False)
print("smallest generalized eigenvalues (x mu):", np.sort(vals) / mu)
