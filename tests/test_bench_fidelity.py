"""The fidelity benchmark's plan and comparison (the runs themselves are the benchmark)."""

import pytest

from hyper.commands.bench import fidelity as bench


def test_cases_run_the_choice_the_paper_and_a_converged_reference():
    plan = bench.cases("TA_VHF_Right", 1e-3)
    assert plan["choice"]["settings"] == {"growth_dt": 168.0, "signaling_dt": 0.125}
    assert plan["paper"]["settings"] == {"growth_dt": 1.0, "grow_during_sessions": False}
    assert plan["paper"]["signaling"] == "rk45"
    assert plan["reference"]["settings"] == {"growth_dt": 6.0, "signaling_dt": 0.05}


def test_compare_measures_errors_against_the_reference_and_the_speedup():
    rows = {"reference": {"csa_ratio": 1.08, "volume_ratio": 1.09},
            "choice": {"csa_ratio": 1.08004, "volume_ratio": 1.09, "wall_s": 10.0, "cpu_s": 9.0},
            "paper": {"csa_ratio": 1.0788, "volume_ratio": 1.0888, "wall_s": 200.0, "cpu_s": 180.0}}
    out = bench.compare(rows, 1e-3)
    assert out["choice"]["errors"]["csa"] == pytest.approx(5e-4)
    assert out["choice"]["within_accuracy"]
    assert out["paper"]["errors"]["csa"] == pytest.approx(0.015) and not out["paper"]["within_accuracy"]
    assert out["speedup_wall"] == pytest.approx(20.0) and out["speedup_cpu"] == pytest.approx(20.0)
