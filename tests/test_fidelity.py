"""Scene-adaptive fidelity (hyper.runs.fidelity) and `python -m hyper.grow --accuracy / --ask signaling`."""

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from hyper.core.params import InputError
from hyper.model import protocols, signaling
from hyper.runs import driver, fidelity
from hyper.runs.fidelity import Scene, choose

ROOT = Path(__file__).resolve().parents[1]
GROWTH = Scene("idealized", "mwf", heterogeneous=False, ask="growth")
SIGNALING = Scene(None, "mwf", heterogeneous=False, ask="signaling")


def rung(longest: float) -> float:
    """The largest step of the ladder within ``longest``."""
    return max(dt for dt in fidelity.SIGNALING_LADDER if dt <= longest)


def test_accuracy_1e3_of_the_growth_takes_one_step_per_period_and_the_rk4_step_of_the_formula():
    choice = choose(GROWTH, 1e-3)
    assert choice.model == "uniform"
    assert choice.growth_dt == 168.0  # 7.16e-6 x 10 <= 5e-4
    # half of 1e-3 for RK4: dt = 0.05 h (5e-4 / (2 x 4.9e-6))^(1/4) = 0.134 h -> 0.125 h
    longest = 0.05 * (0.5e-3 / (fidelity.SIGNALING_SAFETY * 4.9e-6)) ** 0.25
    assert longest == pytest.approx(0.1336, abs=1e-4)
    assert choice.signaling_dt == rung(longest) == 0.125
    assert choice.predicted_error == pytest.approx(7.16e-6 + 4.9e-6 * 2.5**4)  # 1.99e-4
    assert choice.accuracy == 1e-3
    assert choice.describe() == ("uniform model, growth step 168 h, RK4 step 0.125 h; predicted error 0.0002 "
                                 "of the growth <= accuracy 0.001")


def test_a_signaling_question_builds_no_mesh_and_gives_rk4_all_of_the_accuracy():
    choice = choose(SIGNALING, 1e-3)
    assert choice.model == "signaling-only"
    assert choice.growth_dt is None and "growth_dt" not in choice.as_attributes()
    longest = 0.05 * (1e-3 / (fidelity.SIGNALING_SAFETY * 4.1e-7)) ** 0.25  # 0.296 h
    assert choice.signaling_dt == rung(longest) == 0.25
    assert choice.predicted_error == pytest.approx(4.1e-7 * 5.0**4)  # 2.6e-4 of N
    assert any("no mesh" in r for r in choice.reasons)


def test_heterogeneous_parameters_need_one_ode_per_cell_with_the_same_steps():
    uniform = choose(GROWTH, 1e-4)
    per_cell = choose(Scene("BFLH_VHF_Left", "mwf", heterogeneous=True, ask="growth"), 1e-4)
    assert per_cell.model == "per-cell"
    assert (per_cell.growth_dt, per_cell.signaling_dt) == (uniform.growth_dt, uniform.signaling_dt) == (24.0, 0.05)
    assert any("measured on idealized/mwf; for BFLH_VHF_Left/mwf they are an estimate" in r for r in per_cell.reasons)


def test_a_tighter_accuracy_never_takes_longer_steps():
    accuracies = np.geomspace(0.4, fidelity.smallest_accuracy("growth"), 60)
    choices = [choose(GROWTH, float(a)) for a in accuracies]
    for looser, tighter in zip(choices, choices[1:]):
        assert tighter.growth_dt <= looser.growth_dt and tighter.signaling_dt <= looser.signaling_dt
        assert tighter.predicted_error <= tighter.accuracy
    assert [choose(GROWTH, a).growth_dt for a in (1e-3, 1e-4, 1e-5, 1.4e-6, 1.34e-6)] == [168.0, 24.0, 2.0, 2.0, 1.0]
    assert choices[0].signaling_dt == 0.5  # capped below the stability limit 0.65 h


def test_explicit_steps_win_and_the_choice_says_so():
    choice = choose(GROWTH, 1e-3, growth_dt=24.0, signaling_dt=0.05)
    assert (choice.growth_dt, choice.signaling_dt) == (24.0, 0.05)
    assert choice.predicted_error == pytest.approx(2.86e-6 + 4.9e-6)
    assert "growth step 24 h given explicitly, kept instead of the chosen 168 h" in choice.reasons
    assert "RK4 step 0.05 h given explicitly, kept instead of the chosen 0.125 h" in choice.reasons


@pytest.mark.parametrize("accuracy", [0.0, -1e-3, 0.5, 2.0, math.nan, math.inf, True, "1e-3"])
def test_an_accuracy_outside_0_to_half_is_refused(accuracy):
    with pytest.raises(InputError, match=r"accuracy must be a finite number in \(0, 0.5\)"):
        choose(GROWTH, accuracy)


@pytest.mark.parametrize("scene, accuracy, smallest", [
    (GROWTH, 1e-9, "1.27e-06"),  # 10 x 6.37e-8 (growth step 1 h) / (1/2)
    (GROWTH, 1e-6, "1.27e-06"),
    (SIGNALING, 1e-9, "1.31e-09"),  # 2 x 4.1e-7 (0.01 / 0.05)^4
])
def test_an_accuracy_tighter_than_the_tables_is_refused_with_the_smallest_supported(scene, accuracy, smallest):
    with pytest.raises(InputError, match=rf"accuracy {accuracy:g} is tighter than the measured error tables can "
                                         rf"promise for a {scene.ask} question; the smallest supported accuracy "
                                         rf"is {smallest}"):
        choose(scene, accuracy)
    choose(scene, fidelity.smallest_accuracy(scene.ask))  # the bound itself is supported


def test_the_chosen_rk4_step_keeps_its_promise_on_mwf():
    """N(1512 h) at the step chosen for 1e-3 against 0.01 h (7e-10 from DOP853), both sampled
    every 0.5 h as the signaling series are."""
    choice = choose(SIGNALING, 1e-3)
    mwf = protocols.named("mwf")
    n = signaling.run(signaling.SignalingParams(), mwf, choice.signaling_dt)["N"][-1]
    n_ref = signaling.run(signaling.SignalingParams(), mwf, 0.01)["N"][-1]
    error = abs(n - n_ref) / n_ref
    assert 2e-4 < error <= fidelity.SIGNALING_SAFETY * choice.predicted_error <= choice.accuracy  # 2.7e-4


def test_grow_keeps_its_defaults_without_accuracy(tmp_path):
    from mpi4py import MPI

    from hyper.commands import grow
    from hyper.fem.coupled import GrowthSettings

    out = ["--geometry", "idealized", "--output", str(tmp_path / "run.h5")]
    fixed = grow.plan(MPI.COMM_WORLD, out)
    assert fixed.choice is None and fixed.settings == GrowthSettings()
    assert (fixed.settings.growth_dt, fixed.settings.signaling_dt) == (168.0, 0.05)
    chosen = grow.plan(MPI.COMM_WORLD, [*out, "--accuracy"])
    # the mesh counted (tests/test_convergence.py): its spatial error added, the same steps
    assert chosen.choice == fidelity.choose_on_mesh(GROWTH, 1e-3)
    assert (chosen.settings.growth_dt, chosen.settings.signaling_dt) == (168.0, 0.125)
    explicit = grow.plan(MPI.COMM_WORLD, [*out, "--accuracy", "1e-3", "--signaling-dt", "0.05"])
    assert explicit.settings.signaling_dt == 0.05 and explicit.choice.signaling_dt == 0.05
    assert not (tmp_path / "run.h5").exists()


def test_grow_ask_signaling_runs_the_odes_alone_without_dolfinx(tmp_path):
    out = tmp_path / "mwf.h5"
    script = ("import json, sys\nfrom hyper import grow\n"
              "code = grow.main(['--ask', 'signaling', '--protocol', 'mwf', '--accuracy', '1e-3', "
              f"'--output', {str(out)!r}])\n"
              "print(json.dumps({'code': code, 'dolfinx': 'dolfinx' in sys.modules}))\n")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run([sys.executable, "-c", script], cwd=ROOT, env=env, capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert json.loads(lines[-1]) == {"code": 0, "dolfinx": False}
    assert lines[0] == ("fidelity: signaling-only model, RK4 step 0.25 h; predicted error 0.00026 of N "
                        "<= accuracy 0.001")
    assert lines[1].startswith("mwf: N(1512 h) = ") and "no mesh built" in lines[1]
    with h5py.File(out, "r") as f:
        assert f.attrs["complete"] and f.attrs["dt"] == 0.25
        chosen = dict(f["fidelity"].attrs)
        n_end = f["N"][-1]
    assert chosen["model"] == "signaling-only" and chosen["signaling_dt"] == 0.25 and chosen["accuracy"] == 1e-3
    assert "growth_dt" not in chosen and "no mesh" in chosen["reasons"]
    direct = signaling.run(signaling.SignalingParams(), protocols.named("mwf"), 0.25)
    assert abs(n_end - direct["N"][-1]) <= 1e-12


def test_lu_memory_law_passes_through_its_measurements_and_grows_faster_than_the_unknowns():
    for n, m in fidelity.LU_MEMORY_MB:
        assert fidelity.lu_memory_mb(n) == pytest.approx(m, rel=1e-12)
    n0, n1 = fidelity.LU_MEMORY_MB[0][0], fidelity.LU_MEMORY_MB[1][0]
    exponent = math.log(fidelity.lu_memory_mb(n1) / fidelity.lu_memory_mb(n0)) / math.log(n1 / n0)
    assert 1.0 < exponent < 2.0  # 3-D nested dissection: n^(4/3) in theory


def test_the_linear_solver_is_lu_on_small_meshes_while_it_fits_and_pmg_beyond():
    gib = 1024.0
    solver, why = fidelity.linear_solver(78120, 22 * gib)
    assert solver == "lu" and "MUMPS LU" in why
    # where pmg is the faster, LU fitting or not
    assert fidelity.linear_solver(fidelity.PMG_FASTER_FROM - 1, 22 * gib)[0] == "lu"
    solver, why = fidelity.linear_solver(fidelity.PMG_FASTER_FROM, 22 * gib)
    assert solver == "pmg" and "faster than LU" in why
    # the largest mesh LU may take on 2 GiB, and one unknown in a hundred more
    small = 2 * gib
    limit = fidelity.LU_MEMORY_MB[1][0] * (fidelity.LU_MEMORY_SHARE * small / fidelity.LU_MEMORY_MB[1][1]) ** (
        1 / (math.log(fidelity.LU_MEMORY_MB[1][1] / fidelity.LU_MEMORY_MB[0][1])
             / math.log(fidelity.LU_MEMORY_MB[1][0] / fidelity.LU_MEMORY_MB[0][0])))
    assert limit < fidelity.PMG_FASTER_FROM
    assert fidelity.linear_solver(int(limit * 0.99), small)[0] == "lu"
    solver, why = fidelity.linear_solver(int(limit * 1.01), small)
    assert solver == "pmg" and "GMRES" in why and "LU would need" in why and "may not fit" not in why
    solver, why = fidelity.linear_solver(1_500_000, 22 * gib)
    assert solver == "pmg" and "may not fit" not in why
    solver, why = fidelity.linear_solver(20_000_000, 22 * gib)
    assert solver == "pmg" and "may not fit" in why


def test_grow_takes_the_linear_solver_asked_for_or_auto_with_accuracy(tmp_path):
    from mpi4py import MPI

    from hyper.commands import grow

    out = ["--geometry", "idealized", "--output", str(tmp_path / "run.h5")]
    assert grow.plan(MPI.COMM_WORLD, out).linear_solver == "lu"
    assert grow.plan(MPI.COMM_WORLD, [*out, "--accuracy"]).linear_solver == "auto"
    assert grow.plan(MPI.COMM_WORLD, [*out, "--accuracy", "--linear-solver", "lu"]).linear_solver == "lu"
    assert grow.plan(MPI.COMM_WORLD, [*out, "--linear-solver", "iterative"]).linear_solver == "iterative"
    assert driver.available_memory_mb(MPI.COMM_WORLD) > 100.0
