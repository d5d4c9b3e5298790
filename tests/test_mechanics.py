"""MechanicsProblem: exact solutions, invariants, parallel = serial.

Box with springs. A box [-a, a]² × [0, L] with fibres along z and tendon springs on
both ends contracts homogeneously: F = diag(λ^-1/2, λ^-1/2, λ), J = 1. Each end moves
by (1 - λ) L / 2, so the spring's Cauchy traction is σzz = k (1 - λ) L / 2, and
equilibrium with the uniaxial law (see test_material.py) reads

    λ P11(λ) = k (1 - λ) L / 2,   P11(λ) = c1 (λ - λ⁻²) + c2 (1 - λ⁻³) + α σact fact(λ/λ0) / λ.

The reaction forces on Γ1 are then σzz A0 (reference normal) and P11 A0 (current).
"""

import gc
import weakref

import dolfinx_solver  # noqa: F401
import numpy as np
import pytest
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh
from mpi4py import MPI
from petsc4py import PETSc
from scipy.optimize import brentq

from hyper.core.params import InputError
from hyper.fem import fibers
from hyper.fem import geometry as geo
from hyper.fem.mechanics import MechanicsProblem, SolverError, rigid_modes
from hyper.model import growth
from hyper.model import material as mat
from test_material import nominal_stress

PARAMS = mat.MaterialParams()
TIGHT = {"snes_rtol": 1e-11, "snes_atol": 1e-11}


def box_geometry(comm, a=0.01, L=0.1, n=(2, 2, 6)) -> geo.Geometry:
    mesh = dmesh.create_box(comm, [[-a, -a, 0.0], [a, a, L]], list(n), dmesh.CellType.tetrahedron,
                            ghost_mode=dmesh.GhostMode.shared_facet)
    mesh.topology.create_connectivity(2, 3)
    exterior = dmesh.exterior_facet_indices(mesh.topology)
    mid = dmesh.compute_midpoints(mesh, 2, exterior)
    values = np.where(np.isclose(mid[:, 2], 0.0), 1, np.where(np.isclose(mid[:, 2], L), 2, 4)).astype(np.int32)
    tags = dmesh.meshtags(mesh, 2, exterior.astype(np.int32), values)
    return geo.Geometry("box", mesh, tags, ends=(1, 2), lateral=4)


def _sum(comm, expr, measure):
    return comm.allreduce(fem.assemble_scalar(fem.form(expr * measure)), op=MPI.SUM)


def _box_spring_contraction(comm):
    L, a = 0.1, 0.01
    geometry = box_geometry(comm, a=a, L=L)
    problem = MechanicsProblem(geometry, fibers.uniform_fiber_field(geometry.mesh, (0, 0, 1)),
                               petsc_options=TIGHT)
    for alpha in np.linspace(0, 1, 6)[1:]:
        problem.alpha.value = alpha
        problem.solve()
    k = PARAMS.k_tendon
    lam = brentq(lambda l: l * nominal_stress(l, 1.0) - k * (1 - l) * L / 2, 0.5, 1.0, xtol=1e-15)
    area = (2 * a) ** 2

    u = ufl.split(problem.w)[0]
    X = ufl.SpatialCoordinate(geometry.mesh)
    exact = ufl.as_vector([(lam**-0.5 - 1) * X[0], (lam**-0.5 - 1) * X[1], (lam - 1) * (X[2] - L / 2)])
    err = np.sqrt(_sum(comm, ufl.dot(u - exact, u - exact), geometry.dx) / (area * L))
    sigma = k * (1 - lam) * L / 2
    return problem, lam, err, sigma * area, nominal_stress(lam, 1.0) * area, area * L


def _check_box(comm):
    problem, lam, err, force, force_current, volume = _box_spring_contraction(comm)
    assert 0.6 < lam < 0.8
    assert err < 1e-10 * 0.1
    assert problem.reaction_force_original() == pytest.approx(force, rel=1e-8)
    assert problem.reaction_force_current() == pytest.approx(force_current, rel=1e-8)
    assert problem.volume() == pytest.approx(volume, rel=1e-10)
    assert np.abs(problem.multipliers).max() < 1e-8  # the symmetric solution needs no constraint force


def test_box_with_springs_contracts_as_analytic():
    _check_box(MPI.COMM_WORLD)


@pytest.mark.mpi
def test_box_with_springs_contracts_as_analytic_in_parallel():
    _check_box(MPI.COMM_WORLD)


def test_no_activation_no_load_gives_zero_displacement():
    comm = MPI.COMM_WORLD
    geometry = geo.load("idealized", comm)
    problem = MechanicsProblem(geometry, fibers.fiber_field(geometry), petsc_options=TIGHT)
    assert problem.solve() == 0  # the reference state is the solution, no work to do
    rng = np.random.default_rng(comm.rank)
    problem.w.x.array[:] += 1e-4 * rng.standard_normal(problem.w.x.array.shape)
    problem.w.x.scatter_forward()
    assert problem.solve() > 0
    u, p = ufl.split(problem.w)
    volume = geometry.reference_volume()
    u_rms = np.sqrt(_sum(comm, ufl.dot(u, u), geometry.dx) / volume)
    p_rms = np.sqrt(_sum(comm, (p - mat.reference_pressure(PARAMS)) ** 2, geometry.dx) / volume)
    assert u_rms < 1e-12
    assert p_rms < 1e-6  # Pa, against 3e4
    assert abs(problem.reaction_force_original()) < 1e-10
    assert problem.volume() == pytest.approx(volume, rel=1e-12)


@pytest.mark.parametrize("consistent", [True, False])
def test_uniform_transverse_growth_of_cylinder_is_stress_free(consistent):
    """Fg = diag(√ϑ, √ϑ, 1): u = (Fg - I)(X - X̄) exactly, p = c1 + 2c2, V = ϑ V0."""
    _check_growth(MPI.COMM_WORLD, consistent)


@pytest.mark.mpi
def test_uniform_transverse_growth_of_cylinder_in_parallel():
    _check_growth(MPI.COMM_WORLD, True)


def _check_growth(comm, consistent):
    geometry = geo.load("cylinder", comm)
    theta = 1.21
    s = np.sqrt(theta)
    Fg = fem.Constant(geometry.mesh, np.diag([s, s, 1.0]))
    problem = MechanicsProblem(geometry, fibers.fiber_field(geometry), growth=Fg,
                               consistent_stress=consistent, petsc_options=TIGHT)
    problem.solve()
    V0 = geometry.reference_volume()
    X = ufl.SpatialCoordinate(geometry.mesh)
    centroid = [_sum(comm, X[i], geometry.dx) / V0 for i in range(2)]
    u, p = ufl.split(problem.w)
    grad_err = ufl.grad(u) - ufl.as_matrix(np.diag([s - 1, s - 1, 0.0]).tolist())
    exact = ufl.as_vector([(s - 1) * (X[0] - centroid[0]), (s - 1) * (X[1] - centroid[1]), 0.0])
    assert np.sqrt(_sum(comm, ufl.inner(grad_err, grad_err), geometry.dx) / V0) < 1e-10
    assert np.sqrt(_sum(comm, ufl.dot(u - exact, u - exact), geometry.dx) / V0) < 1e-12
    assert np.sqrt(_sum(comm, (p - mat.reference_pressure(PARAMS)) ** 2, geometry.dx) / V0) < 1e-5
    assert problem.volume() == pytest.approx(theta * V0, rel=1e-10)
    assert abs(problem.reaction_force_original()) < 1e-8


def test_rigid_modes_found_where_the_ends_leave_them_free():
    comm = MPI.COMM_WORLD
    for name in ("idealized", "cylinder"):
        modes = rigid_modes(geo.load(name, comm))
        assert len(modes.modes) == 3
        assert modes.stiffness_ratio < 1e-14
    curved = rigid_modes(geo.load("TA_VHF_Left", comm))
    assert curved.modes == ()
    assert curved.stiffness_ratio > 1e-4  # the curved ends resist every rigid motion


def test_divergence_raises_and_restores_the_state():
    comm = MPI.COMM_WORLD
    geometry = geo.load("cylinder", comm)
    problem = MechanicsProblem(geometry, fibers.fiber_field(geometry),
                               petsc_options={"snes_max_it": 1}, options_prefix="test_diverge_")
    before = problem.w.x.array.copy()
    problem.alpha.value = 1.0
    with pytest.raises(SolverError, match="did not converge at alpha = 1 after 1 iterations"):
        problem.solve()
    assert np.array_equal(problem.w.x.array, before)


def test_options_database_overrides_the_dict_which_overrides_defaults():
    comm = MPI.COMM_WORLD
    geometry = box_geometry(comm)
    a0 = fibers.uniform_fiber_field(geometry.mesh, (0, 0, 1))
    db = PETSc.Options()
    db["test_opts_snes_max_it"] = 7
    try:
        problem = MechanicsProblem(geometry, a0, petsc_options={"snes_max_it": 3, "snes_rtol": 1e-9},
                                   options_prefix="test_opts_")
    finally:
        db.delValue("test_opts_snes_max_it")
    rtol, atol, _, max_it = problem.snes.getTolerances()
    assert (max_it, rtol, atol) == (7, 1e-9, 1e-8)
    assert problem.snes.getKSP().getPC().getFactorSolverType() == "mumps"
    assert not db.hasName("test_opts_snes_rtol")  # defaults are not left behind in the database


def test_mumps_controls_of_the_options_reach_the_factorisation():
    """MUMPS reads -mat_mumps_ options when it factorises, after the options left the
    database: they must reach the factor all the same, and a solve must use them."""
    geometry = box_geometry(MPI.COMM_WORLD)
    a0 = fibers.uniform_fiber_field(geometry.mesh, (0, 0, 1))
    problem = MechanicsProblem(geometry, a0, petsc_options={"mat_mumps_icntl_7": 0, "mat_mumps_cntl_1": 0.25},
                               options_prefix="test_mumps_")
    problem.alpha.value = 0.5
    problem.solve()
    factor = problem.snes.getKSP().getPC().getFactorMatrix()
    assert factor.getMumpsIcntl(7) == 0 and factor.getMumpsCntl(1) == 0.25
    assert factor.getMumpsInfog(7) == 0  # the ordering MUMPS says it used: AMD
    assert not PETSc.Options().hasName("test_mumps_mat_mumps_icntl_7")
    with pytest.raises(InputError, match="mat_mumps_foo_3=1 is not a MUMPS control"):
        MechanicsProblem(geometry, a0, petsc_options={"mat_mumps_foo_3": 1}, options_prefix="test_mumps_bad_")


def _idealized_reaction(comm):
    geometry = geo.load("idealized", comm)
    problem = MechanicsProblem(geometry, fibers.fiber_field(geometry), petsc_options=TIGHT,
                               options_prefix=f"test_rank{comm.size}_")
    forces = []
    for alpha in (0.1, 0.2, 0.35, 0.55, 0.8, 1.0):
        problem.alpha.value = alpha
        problem.solve()
        forces.append((problem.reaction_force_original(), problem.reaction_force_current(), problem.volume()))
    return np.array(forces)


@pytest.mark.mpi
def test_two_ranks_give_the_serial_reaction_force():
    world = MPI.COMM_WORLD
    assert world.size == 2
    parallel = _idealized_reaction(world)
    serial = _idealized_reaction(MPI.COMM_SELF)
    assert np.allclose(parallel, serial, rtol=1e-8, atol=0)
    assert parallel[-1, 0] == pytest.approx(0.38785, rel=1e-4)  # N, full activation (see report)


def _lu_and_iterative(comm):
    """Both linear solvers on the idealized shape grown transversely by 10 % and then
    activated to α = 0.3 (free rigid modes, so multipliers in the system)."""
    geometry = geo.load("idealized", comm)
    a0 = fibers.fiber_field(geometry)
    Fg = growth.transverse_growth_ufl(1.1**2, a0 / ufl.sqrt(ufl.dot(a0, a0)))
    out = {}
    for solver in ("lu", "iterative"):
        problem = MechanicsProblem(geometry, a0, growth=Fg, petsc_options=TIGHT, linear_solver=solver)
        newton = problem.solve()
        problem.alpha.value = 0.3
        newton += problem.solve()
        factor = problem.snes.getKSP().getPC().getFactorMatrix()
        out[solver] = (problem.w.x.array.copy(), problem.volume(), newton, problem.linear_iterations(),
                       factor.getMumpsIcntl(35), factor.getMumpsCntl(7))
    return out


def _check_iterative(comm):
    from hyper.fem.mechanics import BLR_PRECISION

    out = _lu_and_iterative(comm)
    w_lu, v_lu, _, _, blr_lu, _ = out["lu"]
    w_it, v_it, _, _, blr_it, precision = out["iterative"]
    assert (blr_lu, blr_it, precision) == (0, 2, BLR_PRECISION)  # MUMPS got the BLR controls
    difference = comm.allreduce(np.abs(w_it - w_lu).max(), op=MPI.MAX)
    scale = comm.allreduce(np.abs(w_lu).max(), op=MPI.MAX)
    assert difference < 1e-9 * scale
    assert v_it == pytest.approx(v_lu, rel=1e-12)


def test_iterative_solver_gives_the_lu_answer():
    _check_iterative(MPI.COMM_WORLD)


@pytest.mark.mpi
def test_iterative_solver_gives_the_lu_answer_in_parallel():
    _check_iterative(MPI.COMM_WORLD)


def test_unknown_linear_solver_is_refused():
    geometry = geo.load("cylinder", MPI.COMM_SELF)
    with pytest.raises(ValueError, match="linear_solver"):
        MechanicsProblem(geometry, fibers.fiber_field(geometry), linear_solver="cg")
    with pytest.raises(ValueError, match="blr_precision"):
        MechanicsProblem(geometry, fibers.fiber_field(geometry), linear_solver="iterative", blr_precision=2.0)


def test_taylor_hood_unknowns_counts_the_space_without_building_it():
    from hyper.fem.mechanics import taylor_hood_unknowns

    geometry = geo.load("cylinder", MPI.COMM_WORLD)
    problem = MechanicsProblem(geometry, fibers.fiber_field(geometry))
    assert taylor_hood_unknowns(geometry.mesh) == problem.num_dofs - len(problem.rigid.modes)


def _taylor_remainders(comm) -> tuple[np.ndarray, np.ndarray]:
    """|R(x + εv) − R(x)| and |R(x + εv) − R(x) − ε K v| for ε = 1e-2 / 2^k, at a state
    x off equilibrium of a box under activation and non-uniform growth, along a smooth
    direction v in every block (displacement, pressure, multipliers)."""
    geometry = box_geometry(comm)
    mesh = geometry.mesh
    a0 = fibers.uniform_fiber_field(mesh, (0.3, 0.0, 1.0))
    theta = fem.Function(fem.functionspace(mesh, ("DG", 0)))
    theta.interpolate(lambda x: 1.0 + 0.05 * (1.0 + np.sin(40.0 * x[2])) * (1.0 + 50.0 * x[0]))
    unit = a0 / ufl.sqrt(ufl.dot(a0, a0))
    problem = MechanicsProblem(geometry, a0, growth=growth.transverse_growth_ufl(theta, unit), petsc_options=TIGHT)
    assert len(problem.multipliers) > 0  # the box leaves rigid motions to the multipliers
    for alpha in (0.0, 0.25, 0.5):  # growth alone, then activation in steps: at once they diverge
        problem.alpha.value = alpha
        problem.solve()

    def direction(scale_u, scale_p, phase):
        w = fem.Function(problem.W)
        w.sub(0).interpolate(lambda x: scale_u * np.vstack([np.sin(30 * x[2] + phase), x[0] * 50 * np.cos(phase),
                                                            np.cos(20 * x[2] + 100 * x[1])]))
        w.sub(1).interpolate(lambda x: scale_p * np.cos(25 * x[2] + 80 * x[0] + phase))
        out = problem.solution_vector.duplicate()
        out.getArray()[: problem.owned_size] = w.x.array[: problem.owned_size]
        out.getArray()[problem.owned_size:] = 1e-3 * (1.0 + phase)
        return out

    x = problem.solution_vector.duplicate()
    problem.load_state(x)
    x.axpy(1.0, direction(2e-4, 2e3, 0.3))  # off equilibrium: R(x) is not zero
    v = direction(1e-3, 1e4, 1.1)
    r0, r, Kv = x.duplicate(), x.duplicate(), x.duplicate()
    problem.assemble_residual(x, r0)
    problem.assemble_jacobian(x)
    problem.jacobian_matrix.mult(v, Kv)
    first, second = [], []
    for eps in 1e-2 / 2.0 ** np.arange(4):
        y = x.copy()
        y.axpy(eps, v)
        problem.assemble_residual(y, r)
        r.axpy(-1.0, r0)
        first.append(r.norm())
        r.axpy(-eps, Kv)
        second.append(r.norm())
    return np.array(first), np.array(second)


def _check_taylor(comm):
    first, second = _taylor_remainders(comm)
    rate_first = np.log2(first[:-1] / first[1:])
    rate_second = np.log2(second[:-1] / second[1:])
    assert np.all(np.abs(rate_first - 1.0) < 0.05), rate_first
    assert np.all(np.abs(rate_second - 2.0) < 0.05), rate_second
    assert second[0] < 0.1 * first[0]


def test_newton_matrix_is_the_derivative_of_the_residual():
    """Taylor test: the kept-factor iteration and SNES both rely on the assembled Newton
    matrix (growth, activation, the current-normal springs, the multiplier blocks) being
    the exact derivative of the residual: the remainder falls as ε², not ε."""
    _check_taylor(MPI.COMM_WORLD)


@pytest.mark.mpi
def test_newton_matrix_is_the_derivative_of_the_residual_in_parallel():
    _check_taylor(MPI.COMM_WORLD)


def _grown_cylinder(**kwargs):
    geometry = geo.load("cylinder", MPI.COMM_WORLD)
    a0 = fibers.fiber_field(geometry)
    theta = fem.Constant(geometry.mesh, 1.0)
    Fg = growth.transverse_growth_ufl(theta**2, a0 / ufl.sqrt(ufl.dot(a0, a0)))
    problem = MechanicsProblem(geometry, a0, growth=Fg, **kwargs)
    theta.value = 1.05
    return problem, problem.solve()


@pytest.mark.parametrize("linear_solver", ["lu", "amg", "pmg"])
def test_a_dropped_problem_is_freed_with_its_mesh_and_communicators(linear_solver):
    # PETSc holds its callbacks where Python's collector cannot see them: a bound method
    # kept the problem alive for ever, and a suite of them ran out of MPI communicators
    kwargs = {} if linear_solver == "lu" else {"linear_solver": linear_solver}
    problem, _ = _grown_cylinder(**kwargs)
    alive = weakref.ref(problem), weakref.ref(problem.geometry.mesh)
    del problem
    gc.collect()
    assert [ref() for ref in alive] == [None, None]


def test_the_experimental_amg_solver_equals_lu_on_a_body_with_free_rigid_motions():
    _check_amg()


@pytest.mark.mpi
def test_the_experimental_amg_solver_equals_lu_in_parallel():
    _check_amg()


def _check_amg():
    lu, _ = _grown_cylinder()
    amg, newton = _grown_cylinder(linear_solver="amg")
    assert len(amg.rigid.modes) == 3 and newton >= 2 and amg.linear_iterations() > 10 * newton
    n = lu.owned_size
    u = np.setdiff1d(np.arange(n), lu.pressure_dofs)
    du = np.abs(amg.w.x.array[u] - lu.w.x.array[u]).max() / np.abs(lu.w.x.array[u]).max()
    assert MPI.COMM_WORLD.allreduce(du, op=MPI.MAX) < 1e-8
    assert abs(amg.volume() - lu.volume()) < 1e-12 * lu.volume()


def test_the_amg_solver_refuses_a_fieldsplit_option_petsc_does_not_read():
    with pytest.raises(InputError, match="fieldsplit_u_pc_gamg_thresold"):
        _grown_cylinder(linear_solver="amg", petsc_options={"fieldsplit_u_pc_gamg_thresold": "0.1"})


def _check_pmg(comm):
    lu, _ = _grown_cylinder()
    pmg, newton = _grown_cylinder(linear_solver="pmg")
    assert len(pmg.rigid.modes) == 3 and newton >= 2 and pmg.linear_iterations() > 10 * newton
    upc = pmg.snes.getKSP().getPC().getFieldSplitSubKSP()[0].getPC()
    coarse = upc.getMGCoarseSolve()
    # two levels, GAMG on the Galerkin P1 operator with the six rigid motions of its nodes
    assert (upc.getType(), upc.getMGLevels(), coarse.getPC().getType()) == ("mg", 2, "gamg")
    assert len(coarse.getOperators()[1].getNearNullSpace().getVecs()) == 6
    n = lu.owned_size
    u = np.setdiff1d(np.arange(n), lu.pressure_dofs)
    du = np.abs(pmg.w.x.array[u] - lu.w.x.array[u]).max() / np.abs(lu.w.x.array[u]).max()
    assert comm.allreduce(du, op=MPI.MAX) < 1e-8
    assert abs(pmg.volume() - lu.volume()) < 1e-12 * lu.volume()


def test_the_experimental_pmg_solver_equals_lu_on_a_body_with_free_rigid_motions():
    _check_pmg(MPI.COMM_WORLD)


@pytest.mark.mpi
def test_the_experimental_pmg_solver_equals_lu_in_parallel():
    _check_pmg(MPI.COMM_WORLD)


def _check_pmg_holds_one_newton_matrix(comm):
    # Memory: the preconditioner is built from K itself (no shifted copy), the displacement
    # block it extracts carries the shift ε diag(M_u) after every assembly, and the P1 -> P2
    # interpolation holds only its entries
    pmg, _ = _grown_cylinder(linear_solver="pmg")
    ksp = pmg.snes.getKSP()
    K = pmg.jacobian_matrix
    assert [op.handle for op in ksp.getOperators()] == [K.handle, K.handle]
    info = pmg._prolongation.getInfo()
    assert info["nz_allocated"] == info["nz_used"]
    is_u = pmg._splits[0]
    shift = pmg._shift.getArray()
    assert comm.allreduce(shift.min(), op=MPI.MIN) > 0
    for alpha in (0.0, 0.3):  # the block is extracted anew from each Newton matrix
        pmg.alpha.value = alpha
        pmg.assemble_jacobian(pmg.solution_vector)
        block = ksp.getPC().getFieldSplitSubKSP()[0].getOperators()[1]
        diagonal = K.getDiagonal().getSubVector(is_u).getArray()
        # to the round-off of the diagonal (about 1e2) against the shift (about 1e-5)
        assert np.allclose(block.getDiagonal().getArray() - diagonal, shift, rtol=1e-6, atol=0.0)


def test_the_pmg_solver_holds_one_newton_matrix_and_shifts_its_displacement_block():
    _check_pmg_holds_one_newton_matrix(MPI.COMM_WORLD)


@pytest.mark.mpi
def test_the_pmg_solver_holds_one_newton_matrix_in_parallel():
    _check_pmg_holds_one_newton_matrix(MPI.COMM_WORLD)


@pytest.mark.parametrize("option, said", [
    ("fieldsplit_u_mg_levels_ksp_max_iter=3", "does not read fieldsplit_u_mg_levels_ksp_max_iter"),
    ("fieldsplit_u_mg_levels_ksp_max_it=abc", "fieldsplit_u_mg_levels_ksp_max_it=abc: Input string abc"),
    ("fieldsplit_u_mg_coarse_pc_type=bogus", "fieldsplit_u_mg_coarse_pc_type=bogus: Unable to find"),
])
def test_the_pmg_solver_refuses_a_bad_multigrid_option_in_one_line(option, said):
    key, value = option.split("=")
    with pytest.raises(InputError, match=said) as err:
        _grown_cylinder(linear_solver="pmg", petsc_options={key: value})
    assert "\n" not in str(err.value)
