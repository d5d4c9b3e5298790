"""Issue 35 item 3: along-fibre growth (--fiber-growth stretch) during sessions that carry a
stretch; off (or on without a stretched session) it leaves today's series as they were."""

import math

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np
import pytest
from mpi4py import MPI

from hyper.core.params import InputError
from hyper.fem import fibers
from hyper.fem import geometry as geo
from hyper.fem.coupled import GrowthSettings, build_model
from hyper.model import growth, protocols, signaling
from hyper.model.protocols import Protocol, Session

GROWING = signaling.SignalingParams(thetaM=0.46)  # mTOR above its threshold from the first hour


def elapsed(theta_f, stretch, tau, crit, theta0=1.0):
    """The time (h) dϑ_f/dt = (λ/ϑ_f − λ_crit)/τ takes from theta0 to theta_f, by hand:
    ∫ ϑ dϑ/(λ − λ_crit ϑ) = (τ/λ_crit²) [λ ln(s₀/s) − (s₀ − s)], s = λ − λ_crit ϑ."""
    s0, s = stretch - crit * theta0, stretch - crit * theta_f
    return tau / crit**2 * (stretch * math.log(s0 / s) - (s0 - s))


@pytest.mark.parametrize("stretch, tau, crit", [(1.1, 168.0, 1.0), (1.25, 50.0, 1.05), (1.02, 1000.0, 1.0)])
def test_the_step_follows_the_law_in_closed_form(stretch, tau, crit):
    theta, t = 1.0, 0.0
    for dt in (0.5, 1.0, 24.0, 168.0, 3.0):
        new = growth.fibre_stretch_step(theta, stretch, dt, tau, crit)
        t += dt
        assert elapsed(new, stretch, tau, crit) == pytest.approx(t, rel=1e-10)
        # the rate at the step's end is the law's (λ/ϑ_f − λ_crit)/τ
        h = 1e-4
        rate = (growth.fibre_stretch_step(new, stretch, h, tau, crit) - new) / h
        assert rate == pytest.approx((stretch / new - crit) / tau, rel=1e-3)
        theta = new
    assert 1.0 < theta < stretch / crit  # bounded by the homeostatic ϑ_f = λ/λ_crit
    # no stretch beyond the homeostatic one: nothing grows
    assert growth.fibre_stretch_step(1.0, crit, 24.0, tau, crit) == 1.0
    assert growth.fibre_stretch_step(stretch / crit, stretch, 24.0, tau, crit) == stretch / crit


def test_the_fibre_growth_tensor():
    a0 = np.array([[0.0, 0.6, 0.8]])
    G = growth.fibre_growth(1.21, 1.05, a0)[0]
    np.testing.assert_allclose(G @ a0[0], 1.05 * a0[0], rtol=1e-15)  # along the fibre ϑ_f
    across = np.array([0.0, 0.8, -0.6])
    np.testing.assert_allclose(G @ across, 1.1 * across, rtol=1e-15)  # across √ϑ
    np.testing.assert_allclose(growth.fibre_growth(1.21, 1.0, a0), growth.transverse_growth(1.21, a0), atol=1e-16)
    # the cumulative update with ϑ_f: A⁻¹ G A Ḡ, for a random F = A Ḡ
    rng = np.random.default_rng(1)
    Gbar = np.eye(3) + 0.1 * rng.standard_normal((3, 3))
    F = np.eye(3) + 0.1 * rng.standard_normal((3, 3))
    A = growth.elastic_part(F[None], Gbar[None])
    pulled, pushed = growth.fibre_directions(F[None], a0)
    np.testing.assert_allclose(growth.transverse_update(Gbar[None], pulled, pushed, 1.21, 1.05),
                               growth.cumulative_update(Gbar[None], A, G[None]), rtol=1e-12, atol=1e-14)


def stretched(stretch=1.1) -> Protocol:
    return Protocol((Session(0.0, 1.0, 0.8, stretch), Session(48.0, 1.0, 0.8)), end=96.0, name="stretched")


def plain() -> Protocol:
    return Protocol((Session(0.0, 1.0, 0.8), Session(48.0, 1.0, 0.8)), end=96.0, name="short")


def run(settings, protocol):
    g = geo.load("cylinder", MPI.COMM_SELF)
    model = build_model(g, fibers.fiber_field(g), protocol, params=GROWING, settings=settings)
    return model, list(model.run())


def test_the_stretched_cylinder_lengthens_as_the_law_says():
    """Axial fibres, a uniform stretch: ϑ_f(t) of the law's closed form in the growth tensor,
    a0·Ḡ a0 at every point; it grows only in the stretched session."""
    tau, crit = 2.0, 1.0
    settings = GrowthSettings(growth_dt=0.5, sections=0, fiber_growth="stretch", fiber_tau=tau, fiber_crit=crit)
    model, reports = run(settings, stretched(1.1))
    t = np.array([r.t for r in reports])
    fs = np.array([r.extra["fiber_stretch"] for r in reports])
    during = (t > 0.0) & (t <= 1.0)
    for ti, f in zip(t[during], fs[during], strict=True):
        assert elapsed(f, 1.1, tau, crit) == pytest.approx(ti, rel=1e-9)
    # no stretch after the first session: ϑ_f stays (the transverse steps conjugate by A = I to Newton's tolerance)
    np.testing.assert_allclose(fs[t >= 1.0], fs[t == 1.0][0], rtol=1e-9)
    assert fs[-1] > 1.02
    assert model.fiber_growth == pytest.approx(fs[-1], rel=1e-12)
    # the cylinder's ends sit on tendon springs: the lengthened fibres push on them, so the
    # body is compressed along its axis and bulges, its CSA above the transverse model's
    _, today = run(GrowthSettings(growth_dt=0.5, sections=0), stretched(1.1))
    assert reports[-1].csa_ratio > today[-1].csa_ratio
    assert reports[-1].volume_ratio > today[-1].volume_ratio * 1.02


@pytest.mark.parametrize("settings, protocol", [
    (GrowthSettings(growth_dt=24.0, sections=0), "stretched"),  # off
    (GrowthSettings(growth_dt=24.0, sections=0, fiber_growth="stretch"), "plain"),  # on, nothing stretched
])
def test_off_or_without_a_stretch_todays_series_bit_for_bit(settings, protocol):
    _, today = run(GrowthSettings(growth_dt=24.0, sections=0), plain())
    _, reports = run(settings, stretched() if protocol == "stretched" else plain())
    for a, b in zip(reports, today, strict=True):
        assert (a.t, a.csa_ratio, a.volume_ratio, a.kM) == (b.t, b.csa_ratio, b.volume_ratio, b.kM)
        assert np.array_equal(a.states, b.states)


def test_the_switch_enters_the_digest_only_when_set():
    default = GrowthSettings().model_attributes()
    assert not {"fiber_growth", "fiber_tau", "fiber_crit"} & set(default)
    assert GrowthSettings(fiber_growth="stretch").model_attributes()["fiber_growth"] == "stretch"
    assert "stretches" not in plain().to_attributes()
    np.testing.assert_array_equal(stretched().to_attributes()["stretches"], [1.1, 1.0])


@pytest.mark.parametrize("field, value", [("fiber_growth", "along"), ("fiber_tau", 0.0), ("fiber_tau", float("nan")),
                                          ("fiber_crit", 0.9), ("fiber_crit", float("inf"))])
def test_bad_settings_are_refused(field, value):
    with pytest.raises(InputError, match=field):
        GrowthSettings(**{field: value})


@pytest.mark.parametrize("bad", [0.9, float("nan"), float("inf"), True, "1.1"])
def test_bad_session_stretches_are_refused(bad):
    with pytest.raises(InputError, match="session 0: stretch must be a finite number >= 1"):
        Protocol((Session(0.0, 1.0, 0.8, bad),), end=2.0)


def test_a_toml_session_carries_a_stretch(tmp_path):
    path = tmp_path / "ecc.toml"
    path.write_text("end = 96.0\n[[session]]\nstart = 0.0\nduration = 1.0\nintensity = 0.8\nstretch = 1.1\n")
    p = protocols.load(path)
    assert p.sessions[0].stretch == 1.1 and p.stretch_at(0.0, 1.0) == 1.1 and p.stretch_at(1.0, 96.0) is None
    for bad, message in (("0.95", r"session 0: stretch: expected a number >= 1, got 0.95"),
                         ("nan", r"session 0: stretch: expected a finite number, got nan"),
                         ('"long"', r"session 0: stretch: expected a number, got 'long'")):
        path.write_text(f"end = 96.0\n[[session]]\nstart = 0.0\nduration = 1.0\nintensity = 0.8\nstretch = {bad}\n")
        with pytest.raises(InputError, match=message):
            protocols.load(path)
