# ruff: noqa
"""Scratch experiment (issue 33): algebraic augmented Lagrangian (AL) for the P2-P1 Newton systems.

    PYTHONPATH=src OMP_NUM_THREADS=1 python jobs/solver_al.py GEOMETRY LEVEL BLOCK GAMMAS SCHURS [max_it=N]

The growth solve of jobs/solver_pmg.py (ϑ = 1.05 at once), with the Newton loop done here
(atol = rtol = 1e-8 on the residual, as the SNES of MechanicsProblem). Each Newton system
K δ = F is replaced by the equivalent K_γ δ = F_γ,

    K_γ = K + γ G W⁻¹ K[p, :],   F_γ = F + γ G W⁻¹ F[p],   G = K[p, u]ᵀ (on the u rows),

W = diag(M_p) on the P1 pressure rows (multiplier rows are not augmented): the u rows get
γ Bᵀ W⁻¹ (B δu - f_p), so the displacement block becomes A + γ Bᵀ W⁻¹ B (PSD added), the
solution is unchanged. Solved by GMRES (right, restart 200, rtol 1e-10) with the upper Schur
fieldsplit of MechanicsProblem's "amg"/"pmg" (multipliers' Schur -bᵢᵀ Â⁻¹ bᵢ with the same Â⁻¹),
the pressure part Ŝ⁻¹ = -a M_p⁻¹ - b W⁻¹:
    SCHUR "lump": a = 0, b = μ + γ        (γ = 0: the amg/pmg solvers before 3058d11, -(1/μ) M_p with Jacobi)
    SCHUR "mass": a = μ, b = γ            (the exact-AL identity S_γ⁻¹ = S⁻¹ - γ W⁻¹ with S ≈ -M_p/μ)
    SCHUR "lump+", "mass+": the same with the opposite sign, Ŝ⁻¹ = +a M_p⁻¹ + b W⁻¹: K's coupling
    blocks are K[u, p] ≈ -K[p, u]ᵀ (printed: coupling_antisym), so S = -B A⁻¹ K[u, p] ≈ +M_p/μ and
    S_γ⁻¹ = S⁻¹ + γ W⁻¹ for this augmentation.
BLOCK: lu (MUMPS on the whole K_γ, preonly: the reference), exact (MUMPS on the u block),
pmg (PMG_SUBSOLVER_OPTIONS, GAMG coarse), gamg (AMG_SUBSOLVER_OPTIONS). GAMMAS: comma list
of γ/μ. SCHURS: comma list. One JSON line per (γ, schur); the block=lu γ=0 run saves the
reference solution /tmp/al_GEOMETRY_LEVEL_lu.npy that the others are compared with.

Run with (1 rank, 2-core machine, another job on the other core):
    python jobs/solver_al.py idealized 0 lu 0,1
    python jobs/solver_al.py idealized 0 exact 0,0.1,1,10,100 lump,mass
    python jobs/solver_al.py idealized 0 pmg 0,0.1,1,10,100 lump,mass
    python jobs/solver_al.py TA_VHF_Left 0 lu 0
    python jobs/solver_al.py TA_VHF_Left 0 exact 0,0.1,1,10,100 lump,mass
    python jobs/solver_al.py TA_VHF_Left 0 pmg 0,0.1,1,10,100 lump,mass
"""
import json
import resource
import sys
import time

import dolfinx_solver  # noqa
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla
import ufl
from dolfinx import fem
from dolfinx.fem import petsc as fp
from mpi4py import MPI
from petsc4py import PETSc

from hyper.fem import fibers
from hyper.fem import geometry as geo
from hyper.fem.mechanics import (AMG_SUBSOLVER_OPTIONS, PMG_SUBSOLVER_OPTIONS, MechanicsProblem)
from hyper.model import growth

comm = MPI.COMM_WORLD
assert comm.size == 1, "serial only (scipy)"
name, level, block = sys.argv[1], int(sys.argv[2]), sys.argv[3]
gammas = [float(v) for v in sys.argv[4].split(",")]
schurs = sys.argv[5].split(",") if len(sys.argv) > 5 and "=" not in sys.argv[5] else ["lump"]
extra = dict(a.split("=", 1) for a in sys.argv[5:] if "=" in a)
max_it = int(extra.get("max_it", 1000))

g = geo.load(name, comm)
for _ in range(level):
    g = geo.refine(g)
a0 = fibers.fiber_field(g)
unit = a0 / ufl.sqrt(ufl.dot(a0, a0))
theta = fem.Constant(g.mesh, 1.0)
Fg = growth.transverse_growth_ufl(theta**2, unit)
problem = MechanicsProblem(g, a0, growth=Fg, linear_solver="pmg")  # for its splits, prolongation, shift
mu = 2.0 * (problem.material.c1 + problem.material.c2)
is_u, is_p = problem._splits
udofs = problem._split_udofs
Q, qdofs = problem.W.sub(1).collapse()
qdofs = np.asarray(qdofs, dtype=np.int64).ravel()[: Q.dofmap.index_map.size_local]
nq = len(qdofs)
nm = problem._nmult
N = problem.num_dofs
p_, q_ = ufl.TrialFunction(Q), ufl.TestFunction(Q)
Mp = fp.assemble_matrix(fem.form(p_ * q_ * g.dx))
Mp.assemble()
ai, aj, av = Mp.getValuesCSR()
Mp_sp = sp.csr_matrix((av, aj, ai), shape=(nq, nq))
Wd = Mp_sp.diagonal()  # W = diag(M_p), in the collapsed-Q order = K's qdofs order
Mp_lu = sla.splu(Mp_sp.tocsc())
shift_sp = None
if nm:
    # the problem's shift ε diag(M_u), on the u dofs of K's numbering (serial: first row 0)
    shift_sp = sp.csr_matrix((problem._shift.getArray(), (udofs, udofs)), shape=(N, N))


def to_scipy(M):
    i, j, v = M.getValuesCSR()
    return sp.csr_matrix((v, j, i), shape=M.getSize())


def to_petsc(S):
    S = S.tocsr()
    S.sort_indices()
    M = PETSc.Mat().createAIJ(S.shape, csr=(S.indptr.astype(PETSc.IntType), S.indices.astype(PETSc.IntType), S.data),
                              comm=comm)
    M.assemble()
    return M


class SchurPC:
    """Ŝ⁻¹ on the p split (P1 pressures in Q order, then multipliers): -a M_p⁻¹ - b W⁻¹ ⊕ 1/s_m."""

    def __init__(self, a, b):
        self.a, self.b = a, b
        self.s = np.ones(nm)

    def apply(self, pc, x, y):
        xa = x.getArray(readonly=True)
        ya = y.getArray()
        xp = xa[:nq]
        out = -self.b * xp / Wd
        if self.a:
            out = out - self.a * Mp_lu.solve(xp)
        ya[:nq] = out
        ya[nq:] = xa[nq:] / self.s


def make_ksp(Kmat, Pmat, schur_pc):
    ksp = PETSc.KSP().create(comm)
    prefix = "al_"
    ksp.setOptionsPrefix(prefix)
    ksp.setOperators(Kmat, Pmat)
    db = PETSc.Options()
    added = []

    def put(k, v):
        db.setValue(prefix + k, v)
        added.append(prefix + k)

    if block == "lu":
        ksp.setType("preonly")
        ksp.getPC().setType("lu")
        ksp.getPC().setFactorSolverType("mumps")
        ksp.setUp()
        return ksp
    ksp.setType("gmres")
    ksp.setGMRESRestart(200)
    ksp.setPCSide(PETSc.PC.Side.RIGHT)
    ksp.setTolerances(rtol=1e-10, atol=0.0, max_it=max_it)
    pc = ksp.getPC()
    pc.setType("fieldsplit")
    pc.setFieldSplitType(PETSc.PC.CompositeType.SCHUR)
    pc.setFieldSplitSchurFactType(PETSc.PC.FieldSplitSchurFactType.UPPER)
    pc.setFieldSplitIS(("u", is_u), ("p", is_p))
    pc.setFieldSplitSchurPreType(PETSc.PC.FieldSplitSchurPreType.USER, problem._schur)
    sub = {"exact": {"fieldsplit_u_ksp_type": "preonly", "fieldsplit_u_pc_type": "lu",
                     "fieldsplit_u_pc_factor_mat_solver_type": "mumps",
                     "fieldsplit_p_ksp_type": "preonly", "fieldsplit_p_pc_type": "jacobi"},
           "pmg": PMG_SUBSOLVER_OPTIONS, "gamg": AMG_SUBSOLVER_OPTIONS}[block]
    for k, v in sub.items():
        put(k, v)
    try:
        ksp.setFromOptions()
        ksp.setUp()
        subu, subp = pc.getFieldSplitSubKSP()
        if block == "pmg":
            upc = subu.getPC()
            upc.setMGInterpolation(1, problem._prolongation)
            coarse = upc.getMGCoarseSolve()
            coarse.getPC().setType("jacobi")
            upc.setUp()
            coarse.getOperators()[1].setNearNullSpace(problem._coarse_modes)
            coarse.getPC().setType("gamg")
            coarse.setFromOptions()
            coarse.setUp()
        subu.setUp()
        ppc = subp.getPC()
        ppc.setType("python")
        ppc.setPythonContext(schur_pc)
        subp.setUp()
    finally:
        for k in added:
            db.delValue(k)
    if nm:  # the multipliers' Schur -bᵢᵀ Â⁻¹ bᵢ with the u split's preconditioner
        upc = subu.getPC()
        bvec = upc.getOperators()[1].createVecRight()
        z = bvec.duplicate()
        c = []
        for row in problem._B:
            bvec.getArray()[:] = row[udofs]
            upc.apply(bvec, z)
            c.append(bvec.dot(z))
        schur_pc.s = -np.array(c)
    return ksp


def run(gamma_rel, schur):
    gamma = gamma_rel * mu
    problem.reset()
    theta.value = 1.05
    x = problem.solution_vector.duplicate()
    F = x.duplicate()
    problem.load_state(x)
    a, b = {"lump": (0.0, mu + gamma), "mass": (mu, gamma)}[schur.rstrip("+")]
    if schur.endswith("+"):  # the sign K's coupling gives: K[u, p] ≈ -K[p, u]ᵀ, so S = B A⁻¹ Bᵀ > 0
        a, b = -a, -b
    row = {"geometry": name, "level": level, "block": block, "gamma_mu": gamma_rel, "schur": schur,
           "unknowns": N}
    its, norms = [], []
    t0 = time.perf_counter()
    f0 = None
    nnz = None
    for k in range(26):
        problem.assemble_residual(x, F)
        fn = F.norm()
        norms.append(fn)
        f0 = fn if f0 is None else f0
        if fn <= max(1e-8, 1e-8 * f0):
            break
        if k == 25:
            row["failed"] = "newton max_it"
            break
        problem.assemble_jacobian(x)
        K = to_scipy(problem.jacobian_matrix)
        if k == 0:
            Kup = K[udofs][:, qdofs]
            Kpu = K[qdofs][:, udofs]
            row["coupling_sym"] = float(sp.linalg.norm(Kup - Kpu.T) / sp.linalg.norm(Kup))
            row["coupling_antisym"] = float(sp.linalg.norm(Kup + Kpu.T) / sp.linalg.norm(Kup))
        Kp = K[qdofs, :]  # pressure rows (N columns)
        G = sp.csr_matrix(Kp.T)
        mask = np.zeros(N)
        mask[udofs] = 1.0
        G = sp.diags(mask) @ G  # only the u rows (the pp block and multiplier columns of Kp are zero anyway)
        GW = G @ sp.diags(1.0 / Wd)
        Kaug = (K + gamma * (GW @ Kp)).tocsr() if gamma else K
        Fa = F.getArray(readonly=True)
        faug = Fa + gamma * (GW @ Fa[qdofs]) if gamma else Fa.copy()
        if nnz is None:
            Auu = K[udofs][:, udofs]
            Aaug = Kaug[udofs][:, udofs]
            Aaug.eliminate_zeros()
            Auu_e = Auu.copy(); Auu_e.eliminate_zeros()
            nnz = (Auu.nnz, Aaug.nnz, Auu_e.nnz)
            row["nnz_A"], row["nnz_Aaug"] = int(Auu.nnz), int(Aaug.nnz)
            row["nnz_ratio"] = Aaug.nnz / Auu.nnz
        Km = to_petsc(Kaug)
        Pm = to_petsc(Kaug + shift_sp) if nm else Km
        schur_pc = SchurPC(a, b)
        ksp = make_ksp(Km, Pm, schur_pc)
        rhs = Km.createVecLeft()
        rhs.getArray()[:] = faug
        d = rhs.duplicate()
        ksp.solve(rhs, d)
        reason = ksp.getConvergedReason()
        its.append(ksp.getIterationNumber())
        if reason <= 0:
            row["failed"] = f"ksp reason {reason} at newton {k}"
            ksp.destroy(); Km.destroy()
            break
        x.axpy(-1.0, d)
        ksp.destroy()
        if Pm is not Km:
            Pm.destroy()
        Km.destroy()
    row["wall_s"] = time.perf_counter() - t0
    row["newton"] = len(its) if "failed" not in row else None
    row["krylov_steps"] = its
    row["krylov"] = int(sum(its))
    row["per_newton"] = sum(its) / max(len(its), 1)
    row["res"] = [float(f"{v:.2e}") for v in norms]
    problem._set_state(x)
    n = problem.owned_size
    u = np.setdiff1d(np.arange(n), problem.pressure_dofs)
    w = problem.w.x.array[:n].copy()
    row["volume"] = problem.volume()
    fname = f"/tmp/al_{name}_{level}_lu.npy"
    np.save(f"/tmp/al_{name}_{level}_{block}_{gamma_rel:g}_{schur}.npy", w)
    if block == "lu" and gamma_rel == 0 and "failed" not in row:
        np.save(fname, w)
    try:
        ref = np.load(fname)
        row["du_rel"] = float(np.abs(ref[u] - w[u]).max() / np.abs(ref[u]).max())
        pp = problem.pressure_dofs[problem.pressure_dofs < n]
        row["dp_rel"] = float(np.abs(ref[pp] - w[pp]).max() / np.abs(ref[pp]).max())
    except FileNotFoundError:
        pass
    row["rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps(row), flush=True)


for gr in gammas:
    for sc in (schurs if block != "lu" else ["lump"]):
        run(gr, sc)
