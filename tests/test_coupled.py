"""The coupled model: exact growth of a cylinder, and the same answer on 1 and 2 ranks."""

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np
import pytest
import ufl
from dolfinx import fem
from mpi4py import MPI

from hyper import fibers, growth, material, signaling
from hyper import geometry as geo
from hyper.coupled import CoupledModel, GrowthSettings
from hyper.mechanics import MechanicsProblem
from hyper.params import InputError
from hyper.protocols import Protocol, Session


@pytest.mark.parametrize("fields", growth.GROWTH_FIELDS)
def test_uniform_growth_of_a_cylinder_is_stress_free_and_exact(fields):
    """Axial fibres and uniform ϑ: growth is compatible, so the body grows without stress.

    The displacement is then u = (√Θ - 1)(x, y, 0) about the axis, CSA and volume grow by
    Θ = ϑ1 ϑ2 exactly, and the pressure is the law's stress-free value c1 + 2 c2, whether
    the growth tensors live at the quadrature points or at the DG1 nodes.
    """
    g = geo.load("cylinder", MPI.COMM_SELF)
    a0 = fibers.fiber_field(g)
    field = growth.GrowthField(g.mesh, a0, g.quadrature_degree, fields)
    assert field.Gbar.shape[1] == (4 if fields == "dg1" else 14)  # vertices, or degree-4 points
    problem = MechanicsProblem(g, a0, growth=field.function)
    field.set_deformation(problem.F)
    section = growth.FacetSection(g, problem.F)
    v0 = problem.volume()

    thetas = (1.05, 1.03)
    for theta in thetas:
        field.grow(theta)
        problem.solve()
        field.accept()
    total = np.prod(thetas)

    assert section.area() / section.area0 == pytest.approx(total, rel=1e-10)
    assert problem.volume() / v0 == pytest.approx(total, rel=1e-10)

    # ∇u = Ḡ - I everywhere; the rigid-mode constraints (∫ u·r dX = 0) fix the centre of
    # the expansion at the volume centroid.
    mismatch = ufl.grad(problem.w.sub(0)) - (field.function - ufl.Identity(3))
    assert np.sqrt(fem.assemble_scalar(fem.form(ufl.inner(mismatch, mismatch) * g.dx))) < 1e-12
    X = ufl.SpatialCoordinate(g.mesh)
    centroid = np.array([fem.assemble_scalar(fem.form(X[i] * g.dx)) for i in range(2)]) / v0
    u = problem.w.sub(0).collapse()
    x = u.function_space.tabulate_dof_coordinates()
    exact = (np.sqrt(total) - 1.0) * np.column_stack([x[:, 0] - centroid[0], x[:, 1] - centroid[1], np.zeros(len(x))])
    scale = (np.sqrt(total) - 1.0) * 0.02
    np.testing.assert_allclose(u.x.array.reshape(-1, 3), exact, rtol=0, atol=1e-10 * scale)

    p = problem.w.sub(1).collapse().x.array
    p_ref = material.reference_pressure(material.MaterialParams())
    np.testing.assert_allclose(p, p_ref, rtol=1e-10)
    # A = F Ḡ⁻¹ is the identity: nothing elastic is left.
    np.testing.assert_allclose(field.A, np.broadcast_to(np.eye(3), field.A.shape), atol=1e-10)


def short_protocol() -> Protocol:
    return Protocol((Session(0.0, 1.0, 0.8), Session(48.0, 1.0, 0.8)), end=96.0, name="short")


# mTOR starts just above its threshold, so the muscle grows from the first hour.
GROWING = signaling.SignalingParams(thetaM=0.46)


def csa_series(comm) -> np.ndarray:
    g = geo.load("idealized", comm)
    a0 = fibers.fiber_field(g)
    model = CoupledModel(g, a0, short_protocol(), params=GROWING, settings=GrowthSettings(growth_dt=24.0))
    return np.array([[r.t, r.csa_ratio, r.volume_ratio, r.kM] for r in model.run()])


def test_dg1_growth_fields_give_the_quadrature_answer_for_uniform_growth():
    """The cylinder under a protocol: uniform ϑ, so both field choices are exact and agree."""
    g = geo.load("cylinder", MPI.COMM_SELF)
    a0 = fibers.fiber_field(g)
    series = {}
    for fields in growth.GROWTH_FIELDS:
        model = CoupledModel(g, a0, short_protocol(), params=GROWING,
                             settings=GrowthSettings(growth_dt=24.0, growth_fields=fields))
        series[fields] = np.array([[r.csa_ratio, r.volume_ratio, r.kM] for r in model.run()])
    assert series["quadrature"][-1, 0] > 1.0005  # it grew
    np.testing.assert_allclose(series["dg1"], series["quadrature"], rtol=1e-10)
    np.testing.assert_allclose(series["dg1"][:, 0], series["dg1"][:, 1], rtol=1e-8)  # CSA and V alike


def test_growth_fields_setting_is_checked_and_kept_out_of_default_digests():
    with pytest.raises(InputError, match="growth_fields: must be one of quadrature, dg1"):
        GrowthSettings(growth_fields="p1")
    assert "growth_fields" not in GrowthSettings().model_attributes()
    assert GrowthSettings(growth_fields="dg1").model_attributes()["growth_fields"] == "dg1"


def test_growth_lowers_synthesis_and_volume_follows_the_population():
    s = csa_series(MPI.COMM_SELF)
    t, csa, vol, kM = s.T
    assert np.all(np.diff(csa) > 0) and np.all(np.diff(vol) > 0)
    assert csa[-1] > 1.005
    np.testing.assert_allclose(kM[1:], GROWING.kM * growth.feedback(csa[1:]), rtol=1e-14)
    assert np.all(kM[1:] < GROWING.kM)


@pytest.mark.mpi
def test_two_ranks_reproduce_the_serial_csa_series():
    comm = MPI.COMM_WORLD
    assert comm.size == 2
    parallel = csa_series(comm)
    serial = csa_series(MPI.COMM_SELF)
    np.testing.assert_allclose(parallel[:, 1:3], serial[:, 1:3], rtol=1e-8)


def test_a_monitor_times_the_phases_and_an_integrator_replaces_the_signaling():
    """What a benchmark plugs in (a recording monitor, another ODE integrator) sees every
    phase and every period, and changes nothing in the answer."""
    from hyper.bench.common import Timings
    from hyper.coupled import PHASES

    g = geo.load("cylinder", MPI.COMM_SELF)
    a0 = fibers.fiber_field(g)
    settings = GrowthSettings(growth_dt=24.0)
    plain = [r.csa_ratio for r in CoupledModel(g, a0, short_protocol(), params=GROWING, settings=settings).run()]

    periods = []

    def integrator(*args, **kwargs):
        periods.append(args[3:5])
        return signaling.integrate(*args, **kwargs)

    clock = Timings()
    model = CoupledModel(g, a0, short_protocol(), params=GROWING, settings=settings, integrator=integrator,
                         monitor=clock)
    reports = list(model.run())
    assert [r.csa_ratio for r in reports] == plain
    assert periods == [(t0, t1) for t0, t1, _ in short_protocol().periods()]
    assert set(clock.calls) == set(PHASES)
    assert clock.calls["signaling"] == len(periods)
    assert clock.calls["mechanics"] >= sum(1 for r in reports[1:] if r.newton_iterations)
    assert clock.calls["jacobian assembly"] == model.jacobian.assemblies
    assert clock.calls["measures"] == clock.calls["growth update"] / 2  # grow and accept per solved step
    assert clock.seconds["jacobian assembly"] <= clock.seconds["mechanics"]
