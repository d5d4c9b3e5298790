"""Growth steps solved with kept factors (hyper.fem.newton) land on the lagged SNES Newton's
answers: the CSA and volume series agree within 1e-6 of the growth, with fewer
factorisations."""

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np
import pytest
from mpi4py import MPI

from hyper.fem import fibers
from hyper.fem import geometry as geo
from hyper.fem.coupled import GrowthSettings, build_model
from hyper.model import signaling
from hyper.model.protocols import Protocol, Session

# Three sessions in a week; mTOR starts just above its threshold, so every step grows.
PROTOCOL = Protocol(tuple(Session(48.0 * k, 1.0, 0.8) for k in range(3)), end=144.0, name="three")
GROWING = signaling.SignalingParams(thetaM=0.46)


def series(name: str, newton: str, growth_dt: float):
    g = geo.load(name, MPI.COMM_SELF)
    model = build_model(g, fibers.fiber_field(g), PROTOCOL, params=GROWING,
                         settings=GrowthSettings(growth_dt=growth_dt, newton=newton))
    rows = np.array([[r.t, r.csa_ratio, r.volume_ratio] for r in model.run()])
    return rows, model.jacobian.assemblies


@pytest.mark.parametrize("name, growth_dt", [("idealized", 12.0), ("BFLH_VHF_Left", 47.0)])
def test_kept_factors_reproduce_the_lagged_newton_series(name, growth_dt):
    old, old_matrices = series(name, "lagged", growth_dt)
    new, new_matrices = series(name, "kept", growth_dt)
    np.testing.assert_array_equal(new[:, 0], old[:, 0])
    for column in (1, 2):
        growth = old[-1, column] - 1.0
        assert growth > 1e-3  # the comparison means something
        assert np.max(np.abs(new[:, column] - old[:, column])) <= 1e-6 * growth
    assert new_matrices < old_matrices


def test_an_unknown_newton_method_is_refused():
    from hyper.core.params import InputError

    with pytest.raises(InputError, match="newton"):
        GrowthSettings(newton="broyden")
