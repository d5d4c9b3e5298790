"""The pure helpers of the growth-step benchmark: errors, default choice, order, extrapolation."""

import math

import pytest

from hyper.commands.bench.growth import (
    cheapest_within,
    checked_dts,
    dt_label,
    extrapolate,
    growth_errors,
    observed_order,
    parser,
    relative_effect,
)
from hyper.core.params import InputError


def test_errors_are_relative_to_the_growth_not_to_the_ratio():
    e = growth_errors(1.0801, 1.0396, 1.08, 1.04)
    assert e["csa"] == pytest.approx(1e-4 / 0.08, rel=1e-9)
    assert e["volume"] == pytest.approx(4e-4 / 0.04, rel=1e-9)


def test_relative_effect_of_a_model_choice():
    assert relative_effect(1.09, 1.08) == pytest.approx(0.125, rel=1e-12)
    assert relative_effect(1.08, 1.08) == 0.0


def _row(label, cpu, e_csa, e_vol, reference=False):
    return {"label": label, "cpu_s": cpu, "reference": reference, "errors": {"csa": e_csa, "volume": e_vol}}


def test_default_is_the_cheapest_step_with_both_errors_within_tolerance():
    rows = [
        _row("0.5 h", 400.0, 0.0, 0.0, reference=True),
        _row("1 h", 200.0, 2e-4, 3e-4),
        _row("6 h", 40.0, 9e-4, 1e-3),  # on the line: accepted
        _row("24 h", 12.0, 4e-4, 2e-3),  # volume too far off
        {"label": "failed", "cpu_s": 1.0, "reference": False, "failed": "no result"},
    ]
    assert cheapest_within(rows, 1e-3)["label"] == "6 h"
    assert cheapest_within(rows, 1e-4) is None
    assert cheapest_within(rows, 1e-4, include_reference=True)["label"] == "0.5 h"


def test_observed_order_and_richardson_limit_recover_a_power_law():
    for p in (1.0, 2.0, 0.7):
        h = (0.5, 1.0, 2.0)
        x = [1.08 + 0.003 * hi**p for hi in h]
        q = observed_order(h, x[1] - x[0], x[2] - x[0])
        assert q == pytest.approx(p, abs=1e-9)
        assert extrapolate(h[0], h[1], x[0], x[1], q) == pytest.approx(1.08, abs=1e-12)
    # differences of opposite signs fit no power law
    assert math.isnan(observed_order((0.5, 1.0, 2.0), 1e-4, -1e-4))


def test_dts_checking_and_labels():
    assert checked_dts([24.0, 0.5, 1e9]) == (0.5, 24.0, 1e9)
    for bad in ([1.0], [1.0, 1.0], [1.0, -2.0], [1.0, math.inf]):
        with pytest.raises(InputError, match="--dts"):
            checked_dts(bad)
    assert parser().parse_args(["--dts", "24", "0.5", "1e9"]).dts == [24.0, 0.5, 1e9]
    with pytest.raises(InputError, match="--dts"):
        parser().parse_args(["--dts", "a", "b"])
    assert dt_label(0.5) == "0.5 h" and dt_label(1e9) == "1/period"
