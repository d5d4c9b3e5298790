"""hyper dose: the protocol grid, budgets and the frontier."""

import numpy as np

from hyper.analysis import dose
from hyper.model import protocols


def test_three_sessions_a_week_is_mwf():
    assert dose.schedule(3, 1.0, 0.8).sessions == protocols.named("mwf").sessions


def test_the_grid_has_at_least_a_thousand_protocols():
    assert dose.loads().size >= 1000


def test_the_best_protocol_keeps_to_its_budget_and_the_frontier_rises():
    gains = np.random.default_rng(1).random(dose.loads().shape)
    for budget in (0.5, 2.0, 9.0):
        index = dose.best_under(gains, budget)
        assert dose.loads()[index] <= budget
        assert gains[index] == gains[dose.loads() <= budget].max()
    assert dose.best_under(gains, 0.01) is None
    curve = dose.frontier(gains, np.linspace(0.1, 20, 50))
    assert np.all(np.diff(curve[np.isfinite(curve)]) >= 0)
