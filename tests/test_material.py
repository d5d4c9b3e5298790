"""The muscle law against its 1-D incompressible uniaxial solution (MODEL.md §3).

Uniaxial stretch λ along the fibres a0 = e1, free lateral faces, J = 1:
F = diag(λ, λ^-1/2, λ^-1/2), C = diag(λ², 1/λ, 1/λ), I1 = λ² + 2/λ, I4 = λ².
S22 = 0 fixes the pressure, p = (c1 + c2 (λ² + 1/λ)) / λ, and the nominal stress
P11 = λ S11 is

    P11(λ) = c1 (λ - λ⁻²) + c2 (1 - λ⁻³) + (σpass fpass(λ/λ0) + α σact fact(λ/λ0)) / λ.
"""

import basix.ufl
import dolfinx_solver  # noqa: F401
import numpy as np
import pytest
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh
from dolfinx.fem.petsc import NonlinearProblem
from mpi4py import MPI

from hyper.core.params import InputError
from hyper.model import material as mat

PARAMS = mat.MaterialParams()


def fact_np(l):
    l = np.asarray(l, dtype=float)
    return np.select(
        [l <= 0.4, l <= 0.6, l <= 1.4, l <= 1.6],
        [0.0 * l, 9 * (l - 0.4) ** 2, 1 - 4 * (1 - l) ** 2, 9 * (l - 1.6) ** 2],
        0.0,
    )


def fpass_np(l, g1=PARAMS.g1, g2=PARAMS.g2):
    l = np.asarray(l, dtype=float)
    e = np.exp(0.4 * g2)
    return np.select(
        [l <= 1.0, l <= 1.4],
        [0.0 * l, g1 * (np.exp(g2 * (l - 1)) - 1)],
        g1 * g2 * e * l + g1 * ((1 - 1.4 * g2) * e - 1),
    )


def nominal_stress(lam, alpha, p=PARAMS):
    fibre = p.sigma_pass * fpass_np(lam / p.lambda0) + alpha * p.sigma_act * fact_np(lam / p.lambda0)
    return p.c1 * (lam - lam**-2) + p.c2 * (1 - lam**-3) + fibre / lam


def uniaxial_pressure(lam, p=PARAMS):
    return (p.c1 + p.c2 * (lam**2 + 1 / lam)) / lam


def _one_cell():
    return dmesh.create_box(MPI.COMM_SELF, [[0, 0, 0], [1, 1, 1]], [1, 1, 1], dmesh.CellType.tetrahedron)


def _evaluate(mesh, expr) -> float:
    return fem.assemble_scalar(fem.form(expr * ufl.dx(domain=mesh, metadata={"quadrature_degree": 0})))


# ℓ = λ/1.4 covers every branch: fact 0 / rising / plateau / falling / 0, fpass 0 / exp / linear.
ELLS = [0.3, 0.5, 0.59, 0.61, 0.9, 1.0, 1.1, 1.39, 1.41, 1.5, 1.7]


@pytest.mark.parametrize("ell", ELLS)
def test_force_length_relations_match_model(ell):
    mesh = _one_cell()
    l = fem.Constant(mesh, ell)
    assert _evaluate(mesh, mat.f_act(l)) == pytest.approx(float(fact_np(ell)), rel=1e-14, abs=1e-15)
    assert _evaluate(mesh, mat.f_pass(l, PARAMS.g1, PARAMS.g2)) == pytest.approx(
        float(fpass_np(ell)), rel=1e-14, abs=1e-15
    )


def test_force_length_relations_are_continuous_and_fpass_is_c1():
    for b in (0.4, 0.6, 1.4, 1.6):
        assert fact_np(b - 1e-12) == pytest.approx(float(fact_np(b + 1e-12)), abs=1e-10)
    for b in (1.0, 1.4):
        assert fpass_np(b - 1e-12) == pytest.approx(float(fpass_np(b + 1e-12)), abs=1e-10)
    h = 1e-6
    left = (fpass_np(1.4) - fpass_np(1.4 - h)) / h
    right = (fpass_np(1.4 + h) - fpass_np(1.4)) / h
    assert left == pytest.approx(right, rel=1e-4)  # the linear branch is the tangent at 1.4
    assert fact_np(1.0) == 1.0


@pytest.mark.parametrize("alpha", [0.0, 0.4, 1.0])
@pytest.mark.parametrize("lam", [0.5, 0.7, 0.84, 1.0, 1.3, 1.6, 2.0, 2.1, 2.4])
def test_first_piola_uniaxial_matches_analytic(lam, alpha):
    """P of MODEL.md §3 on the exact uniaxial F, with the pressure that frees the sides."""
    mesh = _one_cell()
    F = ufl.as_matrix(np.diag([lam, lam**-0.5, lam**-0.5]).tolist())
    a0 = ufl.as_vector([1.0, 0.0, 0.0])
    P = mat.first_piola(F, uniaxial_pressure(lam), a0, fem.Constant(mesh, alpha), PARAMS)
    scale = PARAMS.sigma_act
    assert _evaluate(mesh, P[0, 0]) == pytest.approx(nominal_stress(lam, alpha), rel=1e-12, abs=1e-12 * scale)
    for i, j in [(1, 1), (2, 2), (0, 1), (1, 2)]:
        assert abs(_evaluate(mesh, P[i, j])) < 1e-10 * scale


def test_reference_state_is_stress_free_at_reference_pressure():
    mesh = _one_cell()
    S = mat.second_piola(ufl.Identity(3), mat.reference_pressure(PARAMS), ufl.as_vector([0.0, 0.0, 1.0]), 0.0, PARAMS)
    assert mat.reference_pressure(PARAMS) == 3.0e4
    assert max(abs(_evaluate(mesh, S[i, j])) for i in range(3) for j in range(3)) < 1e-10


# Stretched passively, then activated at fixed stretch: the active law softens for
# 1.25 < λ < 1.85, where a homogeneous state under displacement control is unstable.
@pytest.mark.parametrize(("lam", "alpha"), [(0.62, 1.0), (0.8, 0.5), (1.1, 1.0), (1.5, 0.0), (2.1, 1.0), (2.2, 0.0)])
def test_box_uniaxial_stretch_matches_analytic(lam, alpha):
    """Finite elements: a box stretched along its fibres recovers P11(λ) and p to 1e-8."""
    comm = MPI.COMM_WORLD
    L = 1.0
    mesh = dmesh.create_box(comm, [[0, 0, 0], [L, 0.5, 0.5]], [2, 1, 1], dmesh.CellType.tetrahedron)
    el = basix.ufl.mixed_element(
        [basix.ufl.element("Lagrange", "tetrahedron", 2, shape=(3,)), basix.ufl.element("Lagrange", "tetrahedron", 1)]
    )
    W = fem.functionspace(mesh, el)
    w = fem.Function(W)
    u, p = ufl.split(w)
    v, q = ufl.TestFunctions(W)
    F = ufl.Identity(3) + ufl.grad(u)
    a0 = ufl.as_vector([1.0, 0.0, 0.0])
    activation = fem.Constant(mesh, 0.0)
    P = mat.first_piola(F, p, a0, activation, PARAMS)
    dx = ufl.dx(metadata={"quadrature_degree": 4})
    R = ufl.inner(P, ufl.grad(v)) * dx + q * (ufl.det(F) - 1) * dx

    mesh.topology.create_connectivity(2, 3)
    stretch = fem.Constant(mesh, 0.0)
    bcs = []
    for axis, where in [(0, 0.0), (1, 0.0), (2, 0.0), (0, L)]:
        facets = dmesh.locate_entities_boundary(mesh, 2, lambda x, a=axis, c=where: np.isclose(x[a], c))
        sub = W.sub(0).sub(axis)
        dofs = fem.locate_dofs_topological(sub, 2, facets)
        bcs.append(fem.dirichletbc(stretch if where == L else 0.0, dofs, sub))
    _, pdofs = W.sub(1).collapse()
    w.x.array[pdofs] = mat.reference_pressure(PARAMS)
    problem = NonlinearProblem(
        R, w, bcs=bcs, petsc_options_prefix="test_box_",
        petsc_options={"snes_linesearch_type": "basic", "snes_rtol": 1e-13, "snes_atol": 1e-9, "snes_stol": 0.0,
                       "snes_max_it": 30,
                       "ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"},
    )
    for s in np.linspace(0.0, lam - 1.0, 25)[1:]:
        stretch.value = s * L
        problem.solve()
        assert problem.solver.getConvergedReason() > 0
    for a in np.linspace(0.0, alpha, 5)[1:] if alpha > 0 else []:
        activation.value = a
        problem.solve()
        assert problem.solver.getConvergedReason() > 0

    facets = dmesh.locate_entities_boundary(mesh, 2, lambda x: np.isclose(x[0], L))
    tags = dmesh.meshtags(mesh, 2, np.sort(facets).astype(np.int32), np.ones(len(facets), dtype=np.int32))
    ds = ufl.Measure("ds", domain=mesh, subdomain_data=tags, metadata={"quadrature_degree": 4})
    area = comm.allreduce(fem.assemble_scalar(fem.form(1.0 * ds(1))), op=MPI.SUM)
    force = comm.allreduce(fem.assemble_scalar(fem.form(P[0, 0] * ds(1))), op=MPI.SUM)
    p_integral = comm.allreduce(fem.assemble_scalar(fem.form(p * dx)), op=MPI.SUM)
    assert force / area == pytest.approx(nominal_stress(lam, alpha), rel=1e-8)
    assert p_integral / (0.25 * L) == pytest.approx(uniaxial_pressure(lam), rel=1e-8)


def test_parameters_are_validated():
    with pytest.raises(InputError, match="c1: expected a number > 0"):
        mat.MaterialParams(c1=-1.0)
    with pytest.raises(InputError, match="sigma_act: expected a number >= 0"):
        mat.MaterialParams(sigma_act=-3.0)
    with pytest.raises(InputError, match="finite"):
        mat.MaterialParams(k_tendon=float("nan"))
    assert mat.MaterialParams(c2=0.0, sigma_pass=0.0).c2 == 0.0


def test_material_file(tmp_path):
    good = tmp_path / "m.toml"
    good.write_text("c1 = 2e4\nsigma_act = 1.5e5\n")
    m = mat.load(good)
    assert (m.c1, m.sigma_act, m.c2) == (2e4, 1.5e5, mat.MaterialParams().c2)
    for text, message in (("c3 = 1.0\n", "unknown parameter.*c3"), ("c1 = -1.0\n", "c1: expected a number > 0"),
                          ("g1 = 'x'\n", "g1: expected a number")):
        good.write_text(text)
        with pytest.raises(InputError, match=message):
            mat.load(good)
