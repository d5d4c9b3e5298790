"""The contraction job, and convergence of the reaction force under refinement."""

import dolfinx_solver  # noqa: F401
import h5py
import numpy as np
import pytest
import ufl
from dolfinx import fem
from mpi4py import MPI

from hyper import contraction, fibers
from hyper import geometry as geo_mod
from hyper.io import read_series
from hyper.mechanics import MechanicsProblem


def test_cli_writes_series_fields_and_plot(tmp_path, capsys):
    out = tmp_path / "cyl.h5"
    assert contraction.main(["--geometry", "cylinder", "--steps", "2", "--output", str(out)]) == 0
    series = read_series(out)
    assert np.allclose(series["alpha"], [0.0, 0.5, 1.0])
    assert list(series["newton_iterations"][:1]) == [0]
    force = series["reaction_force"]
    assert force[0] == pytest.approx(0.0, abs=1e-12) and 0 < force[1] < force[2]
    # the end face grows as the muscle shortens: the force along the current normal is larger
    assert np.all(series["reaction_force_current"][1:] > force[1:])
    assert np.allclose(series["volume_ratio"], 1.0, atol=1e-8)
    assert 0.6 < series["stretch_min"][-1] <= series["stretch_max"][-1] < 0.8
    with h5py.File(out) as f:
        assert f.attrs["geometry"] == "cylinder" and f.attrs["unknowns"] == 5228
        assert f["material"].attrs["sigma_act"] == 3.0e5
    assert (tmp_path / "cyl_fields.xdmf").is_file() and (tmp_path / "cyl_fields.h5").is_file()
    assert (tmp_path / "cyl.png").stat().st_size > 10_000
    assert "peak reaction force" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--geometry", "BFLH"], "error: unknown geometry 'BFLH'"),
        (["--steps", "0"], "error: argument --steps: expected an integer in [1, 10000], got 0"),
        (["--output", "x.txt"], "error: argument --output: x.txt: expected a .h5 file"),
        (["--fibers", "helical"], "error: unknown fibre kind 'helical'"),
        (["--stepz", "3"], "error: unknown option(s) --stepz"),
    ],
)
def test_cli_rejects_bad_input_and_writes_nothing(tmp_path, capsys, argv, message):
    out = tmp_path / "res" / "c.h5"
    assert contraction.main(argv + (["--output", str(out)] if "--output" not in argv else [])) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "res").exists() or not any((tmp_path / "res").iterdir())


def _spring_force(problem):
    """The force the springs carry on Γ1: ∫ k (n·u) |cof F N| dA (the exact value of the
    reaction along n for the continuous problem, from displacements only)."""
    geometry = problem.geometry
    u = ufl.split(problem.w)[0]
    N = ufl.FacetNormal(geometry.mesh)
    cofN = ufl.det(problem.F) * ufl.inv(problem.F).T * N
    area = ufl.sqrt(ufl.dot(cofN, cofN))
    form = fem.form(-problem.material.k_tendon * ufl.dot(cofN / area, u) * area * geometry.ds(geometry.ends[0]))
    return problem.comm.allreduce(fem.assemble_scalar(form), op=MPI.SUM)


def test_reaction_force_converges_under_refinement():
    """Full activation on the idealized shape, on the mesh and one uniform refinement.

    Level 1 starts from level 0's solution (nested iteration). A third level (578k
    unknowns) does not fit a direct solver on this machine; see the closing note of
    the issue for what was measured there. Two levels still give an observed rate:
    in the continuum the force along the current normal equals the spring force
    ∫ -k (n·u) |cof F N| dA, and the gap between the two shrinks under refinement.
    """
    comm = MPI.COMM_WORLD
    geometry = geo_mod.load("idealized", comm)
    problems = []
    for level in range(2):
        # Newton converges quadratically: stopping at 1e-6 changes the forces by < 1e-9.
        problem = MechanicsProblem(geometry, fibers.fiber_field(geometry), petsc_options={"snes_rtol": 1e-6})
        if level == 0:
            for alpha in (0.1, 0.2, 0.35, 0.55, 0.8, 1.0):
                problem.alpha.value = alpha
                problem.solve()
        else:
            problem.start_from(problems[-1])
            problem.solve()
        problems.append(problem)
        geometry = geo_mod.refine(geometry)
    # rows: level; columns: R (original), R along the current normal, spring force (N)
    values = np.array([[p.reaction_force(), p.reaction_force_current(), _spring_force(p)] for p in problems])
    assert values == pytest.approx(np.array([[0.38785, 0.56610, 0.59032], [0.41250, 0.57559, 0.58393]]), rel=1e-3)
    change = np.abs(values[1] - values[0]) / np.abs(values[1])
    assert change[0] < 0.07 and change[1] < 0.02 and change[2] < 0.015
    gap = np.abs(values[:, 1] - values[:, 2])
    rate = np.log2(gap[0] / gap[1])
    assert rate > 1.3  # observed 1.54 (h -> h/2)
