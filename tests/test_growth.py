"""Growth kinematics: exact identities of the tensors, the cumulative rule and feedback laws."""

import numpy as np
import pytest

from hyper.model import growth, tensors

rng = np.random.default_rng(7)


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@pytest.mark.parametrize("law", growth.FEEDBACK_LAWS)
def test_feedback_is_one_at_the_reference_area(law):
    assert growth.feedback(1.0, law) == pytest.approx(1.0, abs=0, rel=1e-15)


def test_hill_feedback_lowers_synthesis_when_grown_and_raises_it_when_atrophied():
    assert growth.feedback(1.05, "hill") < 1.0 < growth.feedback(0.95, "hill")
    # h(x) = 2/(1 + x^4): h(2) = 2/17 exactly
    assert growth.feedback(2.0, "hill") == pytest.approx(2.0 / 17.0, rel=1e-15)
    assert growth.feedback(1.1, "linear") == pytest.approx(0.8, rel=1e-14)


def test_unknown_feedback_law_is_rejected():
    with pytest.raises(ValueError, match="unknown feedback law 'cubic'"):
        growth.feedback(1.0, "cubic")


def test_transverse_growth_keeps_fibres_and_scales_the_cross_section():
    a0 = unit(rng.normal(size=(50, 3)))
    theta = 1.0 + 0.1 * rng.random(50)
    G = growth.transverse_growth(theta, a0)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", G, a0), a0, atol=1e-15)
    np.testing.assert_allclose(np.linalg.det(G), theta, rtol=1e-14)
    b = unit(np.cross(a0, rng.normal(size=(50, 3))))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", G, b), np.sqrt(theta)[:, None] * b, atol=1e-15)


def test_two_increments_compose_to_one_of_the_product_when_unloaded():
    a0 = unit(rng.normal(size=(20, 3)))
    eye = np.broadcast_to(np.eye(3), (20, 3, 3))
    t1, t2 = 1.03, 1.07
    G1 = growth.transverse_growth(t1, a0)
    G2 = growth.transverse_growth(t2, a0)
    Gbar = growth.cumulative_update(growth.cumulative_update(eye, eye, G1), eye, G2)
    np.testing.assert_allclose(Gbar, growth.transverse_growth(t1 * t2, a0), rtol=0, atol=1e-14)


def test_cumulative_update_conjugates_the_increment_by_the_elastic_tensor():
    Gbar = np.eye(3) + 0.05 * rng.normal(size=(10, 3, 3))
    A = np.eye(3) + 0.05 * rng.normal(size=(10, 3, 3))
    G = growth.transverse_growth(1.05, unit(rng.normal(size=(10, 3))))
    new = growth.cumulative_update(Gbar, A, G)
    np.testing.assert_allclose(A @ new, G @ A @ Gbar, atol=1e-14)


def test_elastic_part_times_growth_is_the_deformation():
    F = np.eye(3) + 0.1 * rng.normal(size=(10, 3, 3))
    Gbar = np.eye(3) + 0.1 * rng.normal(size=(10, 3, 3))
    np.testing.assert_allclose(growth.elastic_part(F, Gbar) @ Gbar, F, atol=1e-14)


def test_area_multiplier_scales_by_the_current_area():
    assert growth.area_multiplier(0.02, 1.0) == pytest.approx(1.02, rel=1e-15)
    assert growth.area_multiplier(0.02, 2.0) == pytest.approx(1.01, rel=1e-15)


def test_the_structured_update_and_the_adjugate_inverse_agree_with_the_general_ones():
    """The fast paths of a growth step: Ḡ by the structure of G from the fibre directions
    of F, M⁻¹ by the adjugate."""
    rng = np.random.default_rng(3)
    F = np.eye(3) + 0.1 * rng.normal(size=(6, 4, 3, 3))
    Gbar = np.eye(3) + 0.1 * rng.normal(size=(6, 4, 3, 3))
    a0 = unit(rng.normal(size=(6, 4, 3)))
    np.testing.assert_allclose(tensors.inverse(F) @ F, np.broadcast_to(np.eye(3), F.shape), atol=1e-14)
    np.testing.assert_allclose(growth.solve(F, a0), np.linalg.solve(F, a0[..., None])[..., 0], rtol=0, atol=1e-14)
    A = growth.elastic_part(F, Gbar)
    for theta in (1.07, np.linspace(1.0, 1.1, 6)[:, None]):
        G = growth.transverse_growth(theta, a0)
        new = growth.transverse_update(Gbar, *growth.fibre_directions(F, a0), theta)
        np.testing.assert_allclose(new, growth.cumulative_update(Gbar, A, G), rtol=0, atol=1e-14)
        assert np.abs(new - Gbar).max() > 1e-3  # the increment is there to be compared
