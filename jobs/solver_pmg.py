"""Scratch prototype (issue 33) of the p-multigrid that became linear_solver="pmg"; not part of hyper.

    PYTHONPATH=src python jobs/solver_pmg.py GEOMETRY LEVEL VARIANT [KEY=VALUE ...]

The bench's growth solve (ϑ = 1.05 at once) with VARIANT lu, exact (the amg fieldsplit with
an LU displacement solve), gamg (amg as it is), pmg-lu or pmg-gamg (P2 -> P1 two-level
multigrid on the displacement block, LU or GAMG on the Galerkin P1 operator). KEY=VALUE:
smooth=KSP/PC and its=N (the P2 smoother), cycles_u=N, pits=N (N Chebyshev/Jacobi
iterations on the Schur complement, each with a displacement solve), pm=N (N Chebyshev/Jacobi
iterations on the Schur preconditioner's mass matrix instead of one Jacobi), fact=full, defl=sym (a rigid-motion
correction before and after the multigrid) or defl=eig (the same with the block's neig=8
softest eigenvectors, by scipy, serial), k=K_TENDON, blocktest=1 (after the solve, GMRES
to 1e-10 on the displacement block alone with the multigrid, GAMG and LU, from a random right
side). Prints one JSON line; with a saved lu run of the same mesh, the difference from it.
Set the outer GMRES restart with PETSC_OPTIONS="-mechanics_ksp_gmres_restart 200".
"""
import json
import resource
import sys
import time

import dolfinx_solver  # noqa
import numpy as np
import ufl
from dolfinx import fem
from dolfinx.fem import petsc as fp
from mpi4py import MPI
from petsc4py import PETSc

from hyper.fem import fibers
from hyper.fem import geometry as geo
from hyper.fem.mechanics import MechanicsProblem, SolverError, _rigid_body_space
from hyper.model import growth

comm = MPI.COMM_WORLD
name, level, variant = sys.argv[1], int(sys.argv[2]), sys.argv[3]
extra = dict(a.split("=", 1) for a in sys.argv[4:])
g = geo.load(name, comm)
for _ in range(level):
    g = geo.refine(g)
a0 = fibers.fiber_field(g)
unit = a0 / ufl.sqrt(ufl.dot(a0, a0))
theta = fem.Constant(g.mesh, 1.0)
Fg = growth.transverse_growth_ufl(theta**2, unit)

t0 = time.perf_counter()
if variant == "lu":
    problem = MechanicsProblem(g, a0, growth=Fg)
elif variant == "exact":
    problem = MechanicsProblem(g, a0, growth=Fg, linear_solver="amg",
                               petsc_options={"fieldsplit_u_pc_type": "lu",
                                              "fieldsplit_u_pc_factor_mat_solver_type": "mumps"})
elif variant == "gamg":
    problem = MechanicsProblem(g, a0, growth=Fg, linear_solver="amg")
else:
    smooth = extra.get("smooth", "chebyshev/jacobi")
    ksp_s, pc_s = smooth.split("/")
    opts = {"fieldsplit_u_ksp_type": "preonly", "fieldsplit_p_ksp_type": "preonly", "fieldsplit_p_pc_type": "jacobi",
            "fieldsplit_u_pc_type": "mg", "fieldsplit_u_pc_mg_levels": 2,
            "fieldsplit_u_pc_mg_galerkin": "both",
            "fieldsplit_u_mg_levels_ksp_type": ksp_s, "fieldsplit_u_mg_levels_pc_type": pc_s,
            "fieldsplit_u_mg_levels_ksp_max_it": int(extra.get("its", 2))}
    if "cycles_u" in extra:
        opts.update({"fieldsplit_u_ksp_type": "richardson", "fieldsplit_u_ksp_max_it": int(extra["cycles_u"]),
                     "fieldsplit_u_ksp_norm_type": "none"})
    if "pits" in extra:  # Chebyshev/Jacobi on the Schur complement itself (each iteration a u solve)
        opts.update({"fieldsplit_p_ksp_type": "chebyshev", "fieldsplit_p_ksp_max_it": int(extra["pits"])})
    if "pm" in extra:  # the Schur preconditioner's mass matrix solved by pm Chebyshev/Jacobi steps, not one Jacobi
        opts.update({"fieldsplit_p_pc_type": "ksp", "fieldsplit_p_ksp_ksp_type": "chebyshev",
                     "fieldsplit_p_ksp_pc_type": "jacobi", "fieldsplit_p_ksp_ksp_max_it": int(extra["pm"]),
                     "fieldsplit_p_ksp_ksp_convergence_test": "skip"})
    if "fact" in extra:
        opts["pc_fieldsplit_schur_fact_type"] = extra["fact"]
    if pc_s == "sor":
        opts["fieldsplit_u_mg_levels_pc_sor_symmetric"] = 1
    if pc_s == "sor" and "omega" in extra:
        opts["fieldsplit_u_mg_levels_pc_sor_omega"] = float(extra["omega"])
    if ksp_s == "chebyshev" and "esteig" in extra:
        opts["fieldsplit_u_mg_levels_ksp_chebyshev_esteig"] = extra["esteig"]
    if variant == "pmg-lu":
        opts.update({"fieldsplit_u_mg_coarse_ksp_type": "preonly", "fieldsplit_u_mg_coarse_pc_type": "lu",
                     "fieldsplit_u_mg_coarse_pc_factor_mat_solver_type": "mumps"})
    else:
        opts.update({"fieldsplit_u_mg_coarse_ksp_type": "preonly",
                     "fieldsplit_u_mg_coarse_pc_gamg_threshold": float(extra.get("thr", 0.02)),
                     "fieldsplit_u_mg_coarse_pc_gamg_aggressive_coarsening": 0,
                     "fieldsplit_u_mg_coarse_mg_levels_ksp_type": "chebyshev",
                     "fieldsplit_u_mg_coarse_mg_levels_pc_type": extra.get("cpc", "jacobi"),
                     "fieldsplit_u_mg_coarse_mg_levels_ksp_max_it": int(extra.get("cits", 2))})
        if "cycles" in extra:
            opts.update({"fieldsplit_u_mg_coarse_ksp_type": "richardson",
                         "fieldsplit_u_mg_coarse_ksp_max_it": int(extra["cycles"])})
    db = PETSc.Options()
    for k, v in opts.items():
        db.setValue("mechanics_" + k, v)  # in the database for the whole process
    from hyper.model.material import MaterialParams
    problem = MechanicsProblem(g, a0, growth=Fg, linear_solver="amg",
                               material=MaterialParams(k_tendon=float(extra.get("k", 1e5))),
                               petsc_options={"fieldsplit_u_pc_type": "mg"})
    V2 = problem.W.sub(0).collapse()[0]
    V1 = fem.functionspace(g.mesh, ("Lagrange", 1, (3,)))
    Pm = fp.interpolation_matrix(V1, V2)
    Pm.assemble()
    problem.load_state(problem._x)
    problem.assemble_jacobian(problem._x)
    ksp = problem.snes.getKSP()
    ksp.setOperators(problem._K, problem._K)
    ksp.setUp()
    subu, subp = ksp.getPC().getFieldSplitSubKSP()
    pc = subu.getPC()
    if "defl" in extra:
        # u-block PC: Z-correction, p-multigrid, Z-correction (Z: the six rigid motions)
        nu2 = V2.dofmap.index_map.size_local
        Z = [v for v in _rigid_body_space(V2.tabulate_dof_coordinates()[:nu2], comm).getVecs()]

        class RigidCorrection:
            def setUp(self, pc):
                A = pc.getOperators()[1]
                if extra["defl"] == "eig":
                    # the block's own softest modes (serial: scipy, shift-invert), not the rigid motions
                    import scipy.sparse as sp
                    import scipy.sparse.linalg as sla
                    ai, aj, av = A.getValuesCSR()
                    S = sp.csr_matrix((av, aj, ai), shape=A.getSize())
                    _, vecs = sla.eigsh((0.5 * (S + S.T)).tocsc(), k=int(extra.get("neig", 8)), sigma=0.0)
                    Z[:] = []
                    for col in vecs.T:
                        z = A.createVecLeft()
                        z.getArray()[:] = col
                        Z.append(z)
                AZ = [A.createVecLeft() for _ in Z]
                for z, az in zip(Z, AZ):
                    A.mult(z, az)
                self.E = np.array([[zi.dot(azj) for azj in AZ] for zi in Z])
                if comm.rank == 0 and "verbose" in extra:
                    print("E eig", np.linalg.eigvals(self.E), flush=True)

            def apply(self, pc, x, y):
                c = np.linalg.solve(self.E, np.array([z.dot(x) for z in Z]))
                y.set(0.0)
                for ci, z in zip(c, Z):
                    y.axpy(ci, z)

        pc.setType("composite")
        pc.setCompositeType(PETSc.PC.CompositeType.SYMMETRIC_MULTIPLICATIVE if extra["defl"] in ("sym", "eig")
                            else PETSc.PC.CompositeType.MULTIPLICATIVE)
        pc.addCompositePCType("python")
        pc.addCompositePCType("mg")
        shell = pc.getCompositePC(0)
        shell.setPythonContext(RigidCorrection())
        outer_pc = pc
        pc = pc.getCompositePC(1)
        pc.setOptionsPrefix("mechanics_fieldsplit_u_")
        pc.setFromOptions()
    pc.setMGInterpolation(1, Pm)
    n1 = V1.dofmap.index_map.size_local
    coords = V1.tabulate_dof_coordinates()[:n1]
    if variant != "pmg-lu":
        pc.getMGCoarseSolve().getPC().setType("jacobi")  # until the Galerkin coarse matrix exists
    subu.setUp()
    if variant != "pmg-lu":
        cksp = pc.getMGCoarseSolve()
        Ac = cksp.getOperators()[1]
        print("coarse bs", Ac.getBlockSize(), Ac.getSize())
        Ac.setNearNullSpace(_rigid_body_space(coords, comm))
        cksp.getPC().setType("gamg")
        cksp.setFromOptions()
        cksp.setUp()
    if "defl" in extra:
        outer_pc.setUp()
    subp.setUp()
    problem._subsolvers_read = True
    problem._multiplier_schur()
setup = time.perf_counter() - t0
theta.value = 1.05
t0 = time.perf_counter()
row = {"geometry": name, "level": level, "variant": variant, **extra, "unknowns": problem.num_dofs}
try:
    row["newton"] = problem.solve()
except SolverError as e:
    row["failed"] = str(e)[:200]
row["solve_s"] = comm.allreduce(time.perf_counter() - t0, op=MPI.MAX)
row["setup_s"] = setup
row["krylov"] = problem.linear_iterations()
row["per_newton"] = row["krylov"] / max(row.get("newton", 1), 1)
row["volume"] = problem.volume()
row["rss_mb"] = comm.allreduce(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, op=MPI.SUM) / 1024
n = problem.owned_size
u = np.setdiff1d(np.arange(n), problem.pressure_dofs)
np.save(f"/tmp/pmg_{name}_{level}_{variant}_{comm.rank}.npy", problem.w.x.array[:n])
if variant != "lu":
    try:
        ref = np.load(f"/tmp/pmg_{name}_{level}_lu_{comm.rank}.npy")
        du = comm.allreduce(np.abs(ref[u] - problem.w.x.array[u]).max(), op=MPI.MAX)
        um = comm.allreduce(np.abs(ref[u]).max(), op=MPI.MAX)
        row["du_rel"] = du / um
    except FileNotFoundError:
        pass
if comm.rank == 0:
    print(json.dumps(row), flush=True)

if variant.startswith("pmg") and "blocktest" in extra:
    # the displacement block alone: GMRES with the u preconditioner, to 1e-10
    subu, subp = problem.snes.getKSP().getPC().getFieldSplitSubKSP()
    A, Ap = subu.getOperators()
    for what in ("mg",) if extra.get("blocktest") == "mg" else ("mg", "gamg", "lu"):
        k = PETSc.KSP().create(comm)
        k.setOperators(A, Ap)
        k.setType("gmres")
        k.setGMRESRestart(200)
        k.setTolerances(rtol=1e-10, max_it=500)
        k.setPCSide(PETSc.PC.Side.RIGHT)
        if what == "mg":
            k.setPC(subu.getPC())
        elif what == "gamg":
            k.getPC().setType("gamg")
            nodes = V2.tabulate_dof_coordinates()[: V2.dofmap.index_map.size_local]
            A.setNearNullSpace(_rigid_body_space(nodes, comm))
        else:
            k.getPC().setType("lu")
            k.getPC().setFactorSolverType("mumps")
        b = A.createVecLeft()
        b.setRandom()
        x = b.duplicate()
        t = time.perf_counter()
        k.solve(b, x)
        if comm.rank == 0:
            print("u-block", what, k.getIterationNumber(), k.getConvergedReason(),
                  f"{time.perf_counter() - t:.2f}s", flush=True)
