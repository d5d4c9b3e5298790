"""The coupled model: exact growth of a cylinder, and the same answer on 1 and 2 ranks."""

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np
import pytest
import ufl
from dolfinx import fem
from mpi4py import MPI

from hyper.core.params import InputError
from hyper.fem import fibers, growthfield
from hyper.fem import geometry as geo
from hyper.fem.coupled import GrowthSettings, build_model
from hyper.fem.mechanics import MechanicsProblem
from hyper.model import growth, signaling
from hyper.model import material as mat
from hyper.model.protocols import Protocol, Session


@pytest.mark.parametrize("fields", growthfield.GROWTH_FIELDS)
def test_uniform_growth_of_a_cylinder_is_stress_free_and_exact(fields):
    """Axial fibres and uniform ϑ: growth is compatible, so the body grows without stress.

    The displacement is then u = (√Θ - 1)(x, y, 0) about the axis, CSA and volume grow by
    Θ = ϑ1 ϑ2 exactly, and the pressure is the law's stress-free value c1 + 2 c2, whether
    the growth tensors live at the quadrature points or at the DG1 nodes.
    """
    g = geo.load("cylinder", MPI.COMM_SELF)
    a0 = fibers.fiber_field(g)
    field = growthfield.GrowthField(g.mesh, a0, g.quadrature_degree, fields)
    assert field.Gbar.shape[1] == (4 if fields == "dg1" else 14)  # vertices, or degree-4 points
    problem = MechanicsProblem(g, a0, growth=field.function)
    field.set_deformation(problem.F)
    section = growthfield.FacetSection(g, problem.F)
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
    p_ref = mat.reference_pressure(mat.MaterialParams())
    np.testing.assert_allclose(p, p_ref, rtol=1e-10)
    # A = F Ḡ⁻¹ is the identity: nothing elastic is left.
    A = field.elastic_tensor()
    np.testing.assert_allclose(A, np.broadcast_to(np.eye(3), A.shape), atol=1e-10)


def test_the_compiled_fibre_directions_are_those_of_the_deformation_gradient():
    """What a growth step reads of the last equilibrium, F⁻¹a0 and Fᵀa0 with unit a0,
    comes from one compiled expression: the same as from F at the quadrature points."""
    g = geo.load("cylinder", MPI.COMM_SELF)
    a0 = 1.7 * fibers.fiber_field(g)  # not unit: the directions are of the unit fibre
    field = growthfield.GrowthField(g.mesh, a0, g.quadrature_degree)
    problem = MechanicsProblem(g, a0, growth=field.function)
    field.set_deformation(problem.F)
    u = np.asarray(problem.w.function_space.sub(0).collapse()[1]).ravel()
    problem.w.x.array[u] = 5e-5 * np.random.default_rng(1).standard_normal(len(u))
    problem.w.x.scatter_forward()
    field.accept()
    F = field.elastic_tensor() @ field.Gbar  # Ḡ = I: F itself
    assert np.abs(F - np.eye(3)).max() > 0.1  # a real deformation
    pulled, pushed = growth.fibre_directions(F, field.a0)
    np.testing.assert_allclose(field.directions[0], pulled, rtol=0, atol=1e-12 * np.abs(pulled).max())
    np.testing.assert_allclose(field.directions[1], pushed, rtol=0, atol=1e-12 * np.abs(pushed).max())


def short_protocol() -> Protocol:
    return Protocol((Session(0.0, 1.0, 0.8), Session(48.0, 1.0, 0.8)), end=96.0, name="short")


# mTOR starts just above its threshold, so the muscle grows from the first hour.
GROWING = signaling.SignalingParams(thetaM=0.46)


def csa_series(comm) -> np.ndarray:
    g = geo.load("idealized", comm)
    a0 = fibers.fiber_field(g)
    model = build_model(g, a0, short_protocol(), params=GROWING, settings=GrowthSettings(growth_dt=24.0))
    return np.array([[r.t, r.csa_ratio, r.volume_ratio, r.kM] for r in model.run()])


def test_dg1_growth_fields_give_the_quadrature_answer_for_uniform_growth():
    """The cylinder under a protocol: uniform ϑ, so both field choices are exact and agree."""
    g = geo.load("cylinder", MPI.COMM_SELF)
    a0 = fibers.fiber_field(g)
    series = {}
    for fields in growthfield.GROWTH_FIELDS:
        model = build_model(g, a0, short_protocol(), params=GROWING,
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
    from hyper.commands.bench.common import Timings
    from hyper.fem.coupled import PHASES

    g = geo.load("cylinder", MPI.COMM_SELF)
    a0 = fibers.fiber_field(g)
    settings = GrowthSettings(growth_dt=24.0)
    plain = [r.csa_ratio for r in build_model(g, a0, short_protocol(), params=GROWING, settings=settings).run()]

    periods = []

    def integrator(*args, **kwargs):
        periods.append(args[3:5])
        return signaling.integrate(*args, **kwargs)

    clock = Timings()
    model = build_model(g, a0, short_protocol(), params=GROWING, settings=settings, integrator=integrator,
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


def test_left_point_grows_by_f_at_the_step_start_times_the_step():
    """On the cylinder growth is compatible, CSA_k = CSA_{k-1} ϑ_k = CSA_{k-1} + dN_k: the
    CSA ratio's increments are the dN of the steps. exact: N's change over the step;
    left-point: f at the step's start (with the kM its period was integrated with) × Δtg."""
    g = geo.load("cylinder", MPI.COMM_SELF)
    a0 = fibers.fiber_field(g)
    series = {}
    for rule in growth.INCREMENTS:
        model = build_model(g, a0, short_protocol(), params=GROWING,
                             settings=GrowthSettings(growth_dt=24.0, growth_increment=rule),
                             petsc_options={"snes_atol": 1e-11})
        series[rule] = list(model.run())
    # the period's kM: the one after the last step before the period (kM0 before any)
    starts = {t0 for t0, _, _ in short_protocol().periods()}
    for rule, reports in series.items():
        kM = GROWING.kM
        for before, after in zip(reports[:-1], reports[1:]):
            if before.t in starts:
                kM = before.kM
            dt = after.t - before.t
            f0 = signaling.net_balance(before.states[2], before.states[3], before.states[4], GROWING, kM)
            dN = after.states[4] - before.states[4] if rule == "exact" else f0 * dt
            # solved to a residual of 1e-11 (the default 1e-8 leaves CSA errors of about 1e-9)
            assert after.csa_ratio - before.csa_ratio == pytest.approx(dN, rel=0, abs=1e-11)
    exact, left = (np.array([r.csa_ratio for r in series[rule]]) for rule in growth.INCREMENTS)
    assert abs(left[2] - exact[2]) > 1e-4  # the rules differ: f changes within a step


def test_settings_presets_and_their_digests():
    from hyper.runs import presets

    default = GrowthSettings()
    assert set(default.model_attributes()) == {"growth_dt", "signaling_dt", "feedback", "grow_during_sessions",
                                               "consistent_stress"}  # as before the switches: digests stay
    original = presets.settings(GrowthSettings, "original", {"growth_dt": None, "feedback": "hill"})
    assert (original.growth_dt, original.signaling_method, original.growth_increment, original.grow_during_sessions,
            original.consistent_stress, original.csa_method, original.growth_fields, original.preset) == (
        1.0, "rk45-original", "left-point", False, False, "box", "dg1", "original")
    assert original.model_attributes()["signaling_method"] == "rk45-original"
    # an explicit option wins over the preset
    mixed = presets.settings(GrowthSettings, "original", {"growth_dt": 24.0, "grow_during_sessions": True})
    assert (mixed.growth_dt, mixed.grow_during_sessions, mixed.consistent_stress) == (24.0, True, False)
    assert presets.settings(GrowthSettings, "default", {}) == default
    with pytest.raises(InputError, match="--growth-increment: must be one of exact, left-point"):
        presets.settings(GrowthSettings, "default", {"growth_increment": "midpoint"})
    with pytest.raises(InputError, match="--settings: expected one of default, original"):
        presets.settings(GrowthSettings, "paper", {})


def test_grow_and_cohort_take_the_original_preset_and_explicit_switches(tmp_path):
    from hyper.commands import cohort as cohort_job
    from hyper.commands import grow

    out = ["--geometry", "cylinder", "--output", str(tmp_path / "run.h5")]
    original = grow.plan(MPI.COMM_SELF, [*out, "--settings", "original"]).settings
    assert (original.growth_dt, original.signaling_method, original.growth_increment, original.grow_during_sessions,
            original.consistent_stress, original.csa_method, original.growth_fields, original.preset) == (
        1.0, "rk45-original", "left-point", False, False, "box", "dg1", "original")
    idealized = grow.plan(MPI.COMM_SELF, ["--geometry", "idealized", "--output", str(tmp_path / "i.h5"),
                                          "--settings", "original"]).specs[0]
    assert (idealized.ends, idealized.fibers) == ("tags", "original")
    with pytest.raises(InputError, match="idealized shape only"):
        grow.plan(MPI.COMM_SELF, [*out, "--ends", "tags"])
    mixed = grow.plan(MPI.COMM_SELF, [*out, "--settings", "original", "--no-skip-sessions", "--growth-dt", "24"])
    assert (mixed.settings.grow_during_sessions, mixed.settings.growth_dt, mixed.settings.preset) == (True, 24.0,
                                                                                                    "original")
    one = grow.plan(MPI.COMM_SELF, [*out, "--growth-increment", "left-point", "--fe-stress"]).settings
    assert (one.growth_increment, one.consistent_stress, one.signaling_method, one.preset) == (
        "left-point", False, "rk4", "default")
    assert grow.plan(MPI.COMM_SELF, out).settings == GrowthSettings()
    with pytest.raises(InputError, match="--accuracy .* does not combine with --settings original"):
        grow.plan(MPI.COMM_SELF, [*out, "--settings", "original", "--accuracy"])
    args = cohort_job.parser().parse_args(["--geometries", "cylinder", "--settings", "original",
                                               "--signaling-method", "rk4"])
    _, settings, _ = cohort_job.check(args, MPI.COMM_SELF)
    assert args.shape == {"ends": "disks", "fibers": "auto"}
    assert (settings.growth_dt, settings.signaling_method, settings.growth_increment) == (1.0, "rk4", "left-point")
    assert not (tmp_path / "run.h5").exists()


def test_left_point_is_zero_where_N_is_held_at_a_bound():
    p = signaling.SignalingParams(thetaM=0.46, Nmax=1.001)
    y = np.array([0.045, 1.0, 0.43, 0.47, 1.0])  # mTOR above its threshold: f = 1e-2 × 0.01 = 1e-4 /h
    assert growth.population_change("left-point", y, y, 2.0, p, p.kM) == pytest.approx(2e-4, rel=1e-12)
    at_max = np.array([*y[:4], 1.001])
    assert growth.population_change("left-point", at_max, at_max, 2.0, p, p.kM) == 0.0
    cells = np.stack([y, at_max], axis=1)
    np.testing.assert_allclose(growth.population_change("left-point", cells, cells, 2.0, p, p.kM), [2e-4, 0.0],
                               rtol=1e-12)
