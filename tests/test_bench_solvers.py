"""The solver benchmark's own arithmetic: the memory law and the comparison of solutions."""

import numpy as np
import pytest

from hyper.commands.bench import refinement, solvers
from hyper.model import material as mat


def test_memory_fit_recovers_a_power_law_through_the_two_largest_runs():
    rows = [{"unknowns": n, "mumps_used_mb": 3.0 * n**1.3} for n in (1e4, 8e4, 6e5)]
    rows.append({"unknowns": 5e6, "failed": "out of memory"})
    fit = refinement.memory_fit(rows)
    assert fit["exponent"] == pytest.approx(1.3, rel=1e-12)
    assert fit["coefficient_mb"] == pytest.approx(3.0, rel=1e-9)
    assert refinement.memory_fit(rows[:1]) is None


def test_compare_measures_u_against_u_and_p_against_its_change_from_rest(tmp_path):
    p0 = mat.reference_pressure(mat.MaterialParams())
    ref, new = tmp_path / "ref", tmp_path / "new"
    ref.mkdir(), new.mkdir()
    for rank in range(2):
        w = np.array([1e-3, -2e-3, p0 + 100.0, 4e-4, p0 - 50.0])
        p_dofs = np.array([2, 4])
        np.save(ref / f"w_{rank}.npy", w)
        np.save(ref / f"p_{rank}.npy", p_dofs)
        moved = w.copy()
        moved[1] += 2e-9 * (rank + 1)  # u: largest change 4e-9 against max |u| 2e-3
        moved[4] += 1e-3  # p: 1e-3 Pa against max |p - p0| = 100 Pa
        np.save(new / f"w_{rank}.npy", moved)
    diff = solvers.compare(ref, new, 2)
    assert diff["u"] == pytest.approx(2e-6, rel=1e-6)
    assert diff["p"] == pytest.approx(1e-5, rel=1e-6)


def test_parts_not_run_are_kept_from_the_previous_results(tmp_path, capsys):
    import json

    failed = {"geometry": "idealized", "unknowns": 11306, "failed": "an earlier run's failure"}
    old = {"ranks": 2, "levels": [{"solver": "lu", **failed}],
           "precision": [{"solver": "iterative", "precision": 0.1, **failed}],
           "gamg": [{"solver": "gamg", "variant": "GAMG", **failed}]}
    (tmp_path / "solvers.json").write_text(json.dumps(old))
    assert solvers.main(["--parts", "levels", "--levels", "0", "--output", str(tmp_path)]) == 0
    new = json.loads((tmp_path / "solvers.json").read_text())
    assert new["precision"] == old["precision"] and new["gamg"] == old["gamg"]
    assert [r["solver"] for r in new["levels"]] == ["lu", "iterative", "pmg"]
    assert new["levels"][1]["difference_from_lu"]["u"] < 1e-9
    assert new["levels"][2]["difference_from_lu"]["u"] < 1e-9 and new["levels"][2]["krylov_iterations"] > 10
    capsys.readouterr()
    assert solvers.main(["--parts", "levels", "bogus", "--output", str(tmp_path)]) == 2
    assert "error:" in capsys.readouterr().err
    assert solvers.main(["--parts", "levels", "--levels", "4", "--output", str(tmp_path)]) == 2
    assert "error:" in capsys.readouterr().err
    # the kept parts ran on 2 ranks
    assert solvers.main(["--parts", "levels", "--ranks", "1", "--output", str(tmp_path)]) == 2
    assert "error:" in capsys.readouterr().err


def test_the_scaling_part_runs_one_mesh_on_each_rank_count_and_reports_the_speedup(tmp_path):
    import json

    assert solvers.main(["--parts", "scaling", "--scaling-level", "0", "--scaling-ranks", "2", "1",
                         "--output", str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "solvers.json").read_text())["scaling"]
    assert [r["ranks"] for r in rows] == [1, 2]
    assert rows[0]["unknowns"] == rows[1]["unknowns"] == 11306
    assert rows[1]["speedup"] == pytest.approx(rows[0]["solve_s"] / rows[1]["solve_s"])
    assert rows[1]["efficiency"] == pytest.approx(rows[1]["speedup"] / 2)
    # the same Newton path on either partition; GMRES counts may differ by a few
    assert rows[0]["newton_iterations"] == rows[1]["newton_iterations"]
    assert rows[0]["volume_ratio"] == pytest.approx(rows[1]["volume_ratio"], rel=1e-12)


def test_the_answers_part_runs_lu_and_pmg_side_by_side_and_they_agree(tmp_path):
    import json

    assert solvers.main(["--parts", "answers", "--answers-levels", "0", "--output", str(tmp_path)]) == 0
    rows = {r["job"]: r for r in json.loads((tmp_path / "solvers.json").read_text())["answers"]}
    grow, contraction = rows["grow"], rows["contraction"]
    assert grow["csa_ratio_final"]["lu"] > 1.05  # nine weeks of mwf grow the idealized CSA by ~8 %
    assert grow["csa_ratio_difference"] < 1e-6 and grow["volume_ratio_difference"] < 1e-6
    assert contraction["end_force"]["lu"] > 0.5 and contraction["end_force_difference"] < 1e-8
    assert contraction["krylov_iterations"]["pmg"] > 10 * contraction["krylov_iterations"]["lu"]


def test_the_weak_part_meshes_the_unknowns_it_asks_for_on_each_rank_count(tmp_path):
    import json

    assert solvers.main(["--parts", "weak", "--weak-unknowns", "8000", "--scaling-ranks", "2", "1",
                         "--output", str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "solvers.json").read_text())["weak"]
    assert [r["ranks"] for r in rows] == [1, 2]
    for r in rows:
        # the mesher's count of P2-P1 unknowns is the mechanics' own, which adds a multiplier
        # for each free rigid motion of the flat-ended cylinder (two translations, one rotation)
        assert r["unknowns"] == r["meshed_unknowns"] + 3
        assert r["unknowns_per_rank"] == pytest.approx(8000, rel=solvers.WEAK_TOLERANCE)
        # incompressible: the volume grows by det Fg = ϑ² whatever the fibres
        assert r["volume_ratio"] == pytest.approx(solvers.THETA**2, rel=1e-9)
        assert r["krylov_per_newton"] == pytest.approx(r["krylov_iterations"] / r["newton_iterations"])
    assert rows[1]["efficiency"] == pytest.approx(rows[0]["solve_s"] / rows[1]["solve_s"])


def test_the_projection_recovers_the_iteration_and_communication_growth_it_is_given():
    levels = [{"solver": "pmg", "unknowns": n, "newton_iterations": 4, "krylov_iterations": 4 * 50 * (n / 1e4) ** 0.05}
              for n in (1e4, 8e4, 6.4e5)]
    levels.append({"solver": "lu", "unknowns": 1e4, "newton_iterations": 4, "krylov_iterations": 4})
    key = "solve_s_per_iteration_and_unknown_a_rank"
    weak = [{"ranks": 1, "unknowns": 1e5, "unknowns_per_rank": 1e5, "solve_s": 10.0, key: 1e-6},
            {"ranks": 2, "unknowns": 2e5, "unknowns_per_rank": 1e5, "solve_s": 13.0, key: 1.2e-6}]
    out = solvers.projection(weak, levels)
    assert out["beta"] == pytest.approx(0.05) and out["gamma"] == pytest.approx(0.2)
    at64 = out["rows"][0]
    assert at64["ranks"] == 64 and at64["unknowns"] == pytest.approx(6.4e6)
    assert at64["solve_s"] == pytest.approx(10.0 * 64**0.05 * (1 + 0.2 * 6))
    assert at64["efficiency"] == pytest.approx(10.0 / at64["solve_s"])
    assert solvers.projection(weak[:1], levels) == {} and solvers.projection(weak, levels[:1]) == {}
