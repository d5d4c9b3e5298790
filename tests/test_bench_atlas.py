"""The atlas's own measurements: the growth-step failure map and the collected benchmarks."""

import json

import pytest

from hyper.commands.bench import atlas


def test_growth_step_volume_is_theta_squared_and_cutting_extends_the_range():
    """A transverse growth ϑ (det Fg = ϑ²) with det Fe = 1 enforced against the constant
    pressure test function gives V/V0 = ϑ² exactly; ϑ = 3 at once fails, and one
    halving of the step (two increments of log ϑ) reaches it."""
    rows = atlas.newton_growth_step((1.05, 3.0), halvings=2)
    small, large = rows
    assert small["no_cutting"]["converged"]
    assert small["no_cutting"]["volume_ratio"] == pytest.approx(1.05**2, rel=1e-10)
    assert not large["no_cutting"]["converged"]
    assert large["up_to_2_halvings"]["converged"] and large["up_to_2_halvings"]["halvings"] == 1
    assert large["up_to_2_halvings"]["volume_ratio"] == pytest.approx(9.0, rel=1e-8)


def test_collect_names_the_missing_benchmarks(tmp_path):
    assert atlas.collect(tmp_path)["missing"] == [
        "python -m hyper.bench signaling", "python -m hyper.bench growth", "python -m hyper.bench refinement",
        "python -m hyper.bench solvers"]
    (tmp_path / "refinement.json").write_text(json.dumps(
        {"levels": [{"unknowns": 10}], "forces": {}, "lu_memory": {"exponent": 1.3}}))
    collected = atlas.collect(tmp_path)
    assert "python -m hyper.bench refinement" not in collected["missing"]
    assert collected["refinement"]["lu_memory"]["exponent"] == 1.3


def test_dimensions_put_the_reference_first():
    dims = atlas.dimension_cases(["idealized", "TA_VHF_Right"], "mwf")
    assert dims["mesh"][0][0]["refine"] == 1
    assert dims["quadrature TA_VHF_Right"][0][0]["quadrature_degree"] == 6
    assert [ranks for _, ranks in dims["ranks idealized"]] == [1, 2]


def test_collect_keeps_the_solver_comparison():
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        row = {"solver": "iterative", "unknowns": 78120, "krylov_iterations": 42, "newton_iterations": 4,
               "difference_from_lu": {"u": 5e-12, "p": 1e-13, "volume": 1e-14}, "series": [1, 2, 3]}
        (Path(tmp) / "solvers.json").write_text(json.dumps({"levels": [row], "precision": [], "gamg": []}))
        collected = atlas.collect(Path(tmp))
    assert "python -m hyper.bench solvers" not in collected["missing"]
    kept = collected["solvers"]["levels"][0]
    assert kept["difference_from_lu"]["u"] == 5e-12 and "series" not in kept
