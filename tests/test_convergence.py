"""Spatial convergence: the Stokes fibres on a curved tube whose flow is known converge at
their observed order, and --accuracy counts the mesh (hyper.runs.fidelity.spatial): it
refines where refining helps and refuses where the fibres' resolution bounds the error."""

from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np
import pytest
from dolfinx import mesh as dmesh
from mpi4py import MPI

from hyper.commands import grow
from hyper.commands.bench import convergence
from hyper.core.params import InputError
from hyper.fem import fibers
from hyper.fem import geometry as geo
from hyper.runs import fidelity
from hyper.runs.fidelity import Scene

R1, R2, SWEEP, HEIGHT = 1.0, 2.0, np.pi / 2, 0.5  # an annular sector: a bent tube of square section


def sector(n: int, comm) -> geo.Geometry:
    """The sector R1 <= ρ <= R2, 0 <= θ <= SWEEP, 0 <= z <= HEIGHT from a box of n × 2n × n
    cubes: inflow (1) at θ = 0, outflow (2) at θ = SWEEP, the rest lateral (3). Its curved
    walls are chords, as an anatomical mesh's surface is."""
    mesh = dmesh.create_box(comm, [[0, 0, 0], [1, 1, 1]], [n, 2 * n, n], dmesh.CellType.tetrahedron)
    x = mesh.geometry.x
    rho, theta = R1 + (R2 - R1) * x[:, 0], SWEEP * x[:, 1]
    x[:, 0], x[:, 1], x[:, 2] = rho * np.cos(theta), rho * np.sin(theta), HEIGHT * x[:, 2]
    mesh.topology.create_connectivity(2, 3)
    facets = dmesh.exterior_facet_indices(mesh.topology)
    middle = dmesh.compute_midpoints(mesh, 2, facets)
    angle = np.arctan2(middle[:, 1], middle[:, 0])
    values = np.full(len(facets), 3, dtype=np.int32)
    values[np.isclose(angle, 0.0, atol=1e-9)] = 1
    values[np.isclose(angle, SWEEP, atol=1e-9)] = 2
    return geo.Geometry("sector", mesh, dmesh.meshtags(mesh, 2, facets, values), ends=(1, 2), lateral=3)


def angle_to_exact(n: int) -> tuple[float, float]:
    """(mean, largest) angle (°) at the nodes between the fibres and e_θ, the direction of
    the exact flow: with inflow speed ρ the rigid rotation u = ρ e_θ is strain-free, so it
    meets every condition (free slip, zero traction at the outflow) with p = 0."""
    geometry = sector(n, MPI.COMM_WORLD)
    a0, _ = fibers.StokesFibers(geometry, inflow_speed=lambda x: np.hypot(x[0], x[1])).fibers()
    exact = a0.copy()
    exact.interpolate(lambda x: np.vstack([-x[1], x[0], 0 * x[2]]) / np.hypot(x[0], x[1]))
    got = convergence.angles(a0, exact)
    return got["mean_deg"], got["max_deg"]


def test_fibres_on_a_bent_tube_converge_at_their_observed_order():
    errors = np.array([angle_to_exact(n) for n in (2, 4, 8)])  # (level, mean/max)
    orders = np.log2(errors[:-1] / errors[1:])
    # measured: mean 5.31°, 1.45°, 0.371° (orders 1.88, 1.96: the chords' O(h²)); largest
    # 12.1°, 5.65°, 2.84° (1.10, 0.99: at the rims, where the vertex normal averages two walls)
    assert errors[:, 0] == pytest.approx([5.31, 1.446, 0.3711], rel=0.02)
    assert orders[:, 0] == pytest.approx([1.88, 1.96], abs=0.05) and np.all(orders[:, 1] > 0.9)


def carried_angle_to_exact(n: int) -> tuple[float, float]:
    """`angle_to_exact` of the flow solved on the 2n mesh and carried onto the n mesh's
    nodes (`fibers.carried_over`, what `hyper mesh --flow-cells` does)."""
    geometry, flow = sector(n, MPI.COMM_WORLD), sector(2 * n, MPI.COMM_WORLD)
    fine = fibers.StokesFibers(flow, inflow_speed=lambda x: np.hypot(x[0], x[1])).fibers()
    a0, _ = fibers.carried_over(*fine, geometry, fibers.StokesParams().min_speed)
    exact = a0.copy()
    exact.interpolate(lambda x: np.vstack([-x[1], x[0], 0 * x[2]]) / np.hypot(x[0], x[1]))
    got = convergence.angles(a0, exact)
    return got["mean_deg"], got["max_deg"]


def test_fibres_carried_from_a_twice_finer_flow_converge_at_its_order():
    """The flow of the mesh twice as fine, carried onto each mesh's nodes: the fine mesh's
    error at those nodes (about a quarter of the mesh's own), at the same order 2."""
    errors = np.array([carried_angle_to_exact(n) for n in (2, 4)])
    own = np.array([angle_to_exact(n) for n in (2, 4)])
    order = np.log2(errors[0, 0] / errors[1, 0])
    # measured: mean 2.18°, 0.533° (own 5.31°, 1.45°), order 2.03; largest 5.65°, 2.83°
    assert errors[:, 0] == pytest.approx([2.184, 0.5333], rel=0.02)
    assert order == pytest.approx(2.03, abs=0.05)
    assert np.all(errors[:, 0] < 0.45 * own[:, 0])


def test_observed_order_and_richardson_limit_of_a_known_sequence():
    h = [4.0, 2.5, 1.6]
    f = [3.0 + 0.7 * x**1.5 for x in h]
    order = convergence.observed(h, f)
    assert order == pytest.approx(1.5, abs=1e-9)
    e = convergence.estimate(h, f, relative_to_growth=True)
    assert e["limit"] == pytest.approx(3.0, rel=1e-9)
    assert e["errors"][-1] == pytest.approx(0.7 * 1.6**1.5 / 3.0, rel=1e-9)
    assert convergence.observed(h, [1.0, 2.0, 1.5]) is None  # changes alternate: no order


GROWTH = Scene("idealized", "mwf", heterogeneous=False, ask="growth")


def test_the_mesh_takes_its_share_and_the_steps_the_rest():
    choice = fidelity.choose_on_mesh(GROWTH, 1e-3)
    steps = fidelity.choose(GROWTH, 1e-3 - choice.spatial_error)
    assert choice.refine == 0 and choice.spatial_error == fidelity.SPATIAL_ERROR["idealized"].error
    assert (choice.growth_dt, choice.signaling_dt) == (steps.growth_dt, steps.signaling_dt) == (168.0, 0.125)
    assert choice.predicted_error == pytest.approx(steps.predicted_error + choice.spatial_error)
    assert "mesh refined 0 time(s) (spatial error 0.00015)" in choice.describe()


def test_an_accuracy_below_the_mesh_refines_it():
    entry = fidelity.SPATIAL_ERROR["idealized"]
    choice = fidelity.choose_on_mesh(GROWTH, 1e-4)
    # 1.5e-4, 7.5e-5, 3.75e-5 at order 1: the first within half of 1e-4 is twice refined
    assert choice.refine == 2 and choice.spatial_error == pytest.approx(entry.error / 4)
    assert choice.predicted_error <= 1e-4
    assert fidelity.choose_on_mesh(GROWTH, 1e-4, refine=3).refine == 3  # never fewer than given


def test_an_accuracy_below_what_the_fibres_allow_is_refused(monkeypatch):
    monkeypatch.setitem(fidelity.SHIPPED_ERROR["laplace"], "TA_VHF_Left",
                        fidelity.MeshError(4e-3, 3e-3, 2.0, "a test"))
    scene = Scene("TA_VHF_Left", "mwf", heterogeneous=False, ask="growth")
    assert fidelity.choose_on_mesh(scene, 1e-2, fibres="laplace").refine == 0  # 4e-3 within half of 1e-2
    with pytest.raises(InputError, match=r"accuracy 0.001 is tighter than the mesh of TA_VHF_Left can give: its "
                       r"spatial error is 0.003 of the growth even refined 3 time\(s\), 0.003 of it from the "
                       r"fibres and the surface's facets.*accuracy is 0.006"):
        fidelity.choose_on_mesh(scene, 1e-3, fibres="laplace")


def test_grow_refines_for_the_accuracy_and_refuses_below_the_mesh(tmp_path):
    plan = grow.plan(MPI.COMM_SELF, ["--geometry", "idealized", "--accuracy", "1e-4", "--output", str(tmp_path)])
    assert plan.specs[0].refine == 2 and plan.choice.refine == 2
    with pytest.raises(InputError, match=r"--accuracy 1e-05: accuracy 1e-05 is tighter than the mesh of idealized"):
        grow.plan(MPI.COMM_SELF, ["--geometry", "idealized", "--accuracy", "1e-5", "--output", str(tmp_path)])
    # an anatomical mesh: most of its error is its surface's and fibres', which refining keeps
    entry = fidelity.SHIPPED_ERROR["laplace"]["TA_VHF_Left"]  # its own (Laplace) fibres, measured on its mesh
    least = (entry.kept + (entry.error - entry.kept) / 8) / fidelity.SPATIAL_SHARE
    with pytest.raises(InputError, match=rf"--accuracy 0.001: .* the smallest supported accuracy is {least:.2g}$"):
        grow.plan(MPI.COMM_SELF, ["--geometry", "TA_VHF_Left", "--accuracy", "1e-3", "--output", str(tmp_path)])
    assert grow.plan(MPI.COMM_SELF, ["--geometry", "TA_VHF_Left", "--accuracy", "2e-2", "--output",
                                     str(tmp_path)]).specs[0].refine == 0
    # its Stokes fibres' error is three times larger: 2e-2 is beyond them
    with pytest.raises(InputError, match=r"--accuracy 0.02: .*--fibres-method stokes"):
        grow.plan(MPI.COMM_SELF, ["--geometry", "TA_VHF_Left", "--fibers", "stokes", "--accuracy", "2e-2",
                                  "--output", str(tmp_path)])


def test_every_result_records_its_spatial_error():
    spatial = fidelity.spatial("idealized", 1)
    assert spatial.error == pytest.approx(7.5e-5) and spatial.measured
    other = fidelity.spatial("a_mesh", 0, mesh_file=True)
    assert not other.measured and "no table for a mesh file" in other.reason
    assert other.error == max(e.error for e in fidelity.SPATIAL_ERROR.values())  # the worst measured


def test_every_muscle_has_its_spatial_error_or_its_other_side_s():
    muscles = set(geo.ANATOMICAL) | {m for m in geo.MESHED if m.count("_") == 2}
    assert set(fidelity.SURFACE_STUDIES) == muscles - {"BFLH_VHF_Right"}  # the one without a surface
    # the shipped mesh measured against its other side's surface, never below that study's entry
    right = fidelity.spatial("BFLH_VHF_Right")
    assert right.error == max(fidelity.SHIPPED_STUDIES["stokes"]["BFLH_VHF_Right"],
                              fidelity.SPATIAL_ERROR["BFLH_VHF_Left"].error) and right.measured
    assert "BFLH_VHF_Left's surface's limit" in right.reason
    # every shipped mesh is measured on itself (`bench convergence --shipped`)
    assert all(fidelity.spatial(m).measured for m in fidelity.SURFACE_STUDIES)
    assert fidelity.spatial("idealized").measured
    for muscle, (error, levels) in fidelity.SURFACE_STUDIES.items():
        assert 0 < error < 1 and 8000 in levels, muscle


def test_a_shipped_mesh_given_as_a_file_has_its_geometry_s_spatial_error(tmp_path):
    from hyper.runs import runspec

    shipped = Path(geo.MESHES_DIR) / geo.GEOMETRIES["VL_VHM_Left"]
    assert runspec.table_name(shipped.stem, runspec.MeshFile(shipped, "mm")) == ("VL_VHM_Left", False, "laplace")
    mine = tmp_path / "VL_VHM_Left.xdmf"  # the same name elsewhere is a user's mesh (its fibres computed: Stokes)
    assert runspec.table_name(mine.stem, runspec.MeshFile(mine, "mm")) == ("VL_VHM_Left", True, "stokes")
    assert runspec.table_name("idealized", None) == ("idealized", False, "stokes")
    assert runspec.table_name("VL_VHM_Left", None) == ("VL_VHM_Left", False, "laplace")  # what its file holds
    for asked in ("stokes", "original"):  # the paper's fibres
        assert runspec.table_name("VL_VHM_Left", None, asked) == ("VL_VHM_Left", False, "stokes")


def test_the_spatial_table_takes_each_muscle_from_its_finest_study(tmp_path):
    import json

    def kept(folder, name, cells, csa):
        h = [10.0 / n ** (1 / 3) for n in cells]
        levels = [{"cells_target": n, "cells": n, "h_mm": hh, "own": {"csa_gain_pct": c, "volume_gain_pct": 8.4},
                   "finest": {"csa_gain_pct": 8.3 + 0.01 * (len(cells) - i), "volume_gain_pct": 8.4},
                   "fibre_angle_to_finest": {"p95_deg": 5.0 * (len(cells) - 1 - i)}}
                  for i, (n, hh, c) in enumerate(zip(cells, h, csa))]
        result = {"muscle": name, "levels": levels, "estimates": convergence.estimates_of(levels)}
        (tmp_path / folder / "convergence_all").mkdir(parents=True, exist_ok=True)
        (tmp_path / folder / "convergence_all" / f"{name}.json").write_text(json.dumps(result))

    kept("quick", "VL_VHM_Left", [1000, 2000, 4000, 8000], [8.30, 8.40, 8.30, 8.384])
    kept("fine", "VL_VHM_Left", [4000, 8000, 16000], [8.30, 8.384, 8.30])  # zigzags: no order
    kept("fine", "TA_VHF_Left", [4000, 16000], [8.3, 8.3])  # no 8000-cell level: not used
    rows = convergence.spatial_rows([tmp_path / "quick", tmp_path / "fine"], 8000)
    assert [r["muscle"] for r in rows] == ["VL_VHM_Left"] and rows[0]["levels"] == [4000, 8000, 16000]
    # the 8k level's error without an order: its distance to the finest plus the finest spread
    assert rows[0]["csa_error"] == pytest.approx((0.084 + 0.084) / 8.30)
    assert rows[0]["fibre_p95_deg"] == 5.0
    # with the finest fibres the gain moves steadily (8.33, 8.32, 8.31): the mechanics' own error, smaller here
    assert rows[0]["csa_error_finest_fibres"] < rows[0]["csa_error"]
    # the 8k level with the finest flow (8.32) against the own series' finest (8.30) plus its spread
    assert rows[0]["csa_error_finest_flow"] == pytest.approx((0.02 + 0.084) / 8.30)
    assert convergence.spatial_literal(rows[0]) == '    "VL_VHM_Left": (0.021, (4000, 8000, 16000)),'
    # where the own-fibre series' spread is smaller (fibres and mechanics cancelling), the mechanics' counts
    row = {**rows[0], "csa_error": 1e-4, "volume_error": 1e-5, "csa_error_finest_fibres": 3.01e-3}
    assert convergence.spatial_literal(row) == '    "VL_VHM_Left": (0.0031, (4000, 8000, 16000)),'
    assert convergence.main(["--spatial-table", str(tmp_path / "quick"), str(tmp_path / "fine"), "--output",
                             str(tmp_path / "out")]) == 0
    written = json.loads((tmp_path / "out" / "spatial_table.json").read_text())
    assert written["muscles"] == rows and (tmp_path / "out" / "spatial_table.png").stat().st_size > 0
    assert convergence.main(["--spatial-table", str(tmp_path / "nothing"), "--output", str(tmp_path / "out")]) == 2


@pytest.mark.mpi(min_size=2)
def test_the_study_farmed_over_two_ranks_gives_the_numbers_of_one_rank(tmp_path_factory):
    comm = MPI.COMM_WORLD
    out = Path(comm.bcast(str(tmp_path_factory.mktemp("convergence")) if comm.rank == 0 else None, root=0))
    # the coarse copy of a Visible Human tibialis the repository carries (tests/data)
    surface = Path(__file__).parent / "data" / "TA_VHF_Right_coarse.stl"
    args = convergence.parser().parse_args([str(surface), "--quick", "--cells", "1000", "1400", "2000",
                                            "--no-force-at-full-activation", "--output", str(out)])
    farmed = convergence.study(comm, args)
    # the same meshes (made above, reused), every run on one rank
    alone = convergence.study(MPI.COMM_SELF, args) if comm.rank == 0 else None
    if comm.rank == 0:
        assert {job["rank"] for job in farmed["jobs"]} == {0, 1}  # both ranks took levels
        assert len(farmed["jobs"]) == 3 + 2  # own growth at each level, finest growth below the top
        for mine, theirs in zip(farmed["levels"], alone["levels"]):
            for key in ("cells", "vertices", "h_mm", "fibre_angle_to_finest"):
                assert mine[key] == theirs[key]
            for variant in convergence.VARIANTS:
                for q in convergence.QUANTITIES:
                    assert mine[variant].get(q) == theirs[variant].get(q), (mine["cells"], variant, q)
        assert farmed["estimates"] == alone["estimates"]
    comm.barrier()


def test_the_all_muscles_table_reuses_kept_studies_and_judges_the_goal(tmp_path, monkeypatch):
    """Two kept studies (no run): one within the goal, one whose CSA gain moves by 1 % of
    the growth between its two finest levels (no order: that spread is its error)."""
    import json

    cells = list(convergence.QUICK_CELLS)
    h = [4.0, 3.2, 2.5, 2.0]

    def kept(name, csa):
        levels = [{"cells_target": n, "cells": n, "h_mm": hh, "fibre_angle_to_finest": {"p95_deg": 10.0 - i},
                   "own": {"csa_gain_pct": c, "volume_gain_pct": 8.4, "end_force_n": 0.5}}
                  for i, (n, hh, c) in enumerate(zip(cells, h, csa))]
        result = {"muscle": name, "levels": levels, "estimates": convergence.estimates_of(
            [{**lv, "finest": lv["own"]} for lv in levels]), "wall_s": 1.0}
        (tmp_path / "convergence_all").mkdir(exist_ok=True)
        (tmp_path / "convergence_all" / f"{name}.json").write_text(json.dumps(result))

    kept("TA_VHF_Left", [8.30, 8.36, 8.38, 8.385])  # converging: Richardson order
    kept("ST_VHM_Right", [8.30, 8.40, 8.30, 8.384])  # zigzags: the 2.5-2.0 spread, 0.084 points
    monkeypatch.setattr(convergence, "source", lambda muscle, surfaces: (muscle, None, []))
    # kept before --fibres-method: Stokes studies, which a Laplace study (the default) would not reuse
    assert convergence.main(["--all", "TA_VHF_Left", "ST_VHM_Right", "--quick", "--fibres-method", "stokes",
                             "--output", str(tmp_path)]) == 0
    table = {r["muscle"]: r for r in json.loads((tmp_path / "convergence_all.json").read_text())["muscles"]}
    ta, st = table["TA_VHF_Left"], table["ST_VHM_Right"]
    assert ta["csa_order"] is not None and ta["csa_error"] < convergence.GROWTH_GOAL and ta["goal_met"]
    assert st["csa_order"] is None and st["csa_error"] == pytest.approx(0.084 / 8.384)
    assert not st["goal_met"]
    assert ta["fibre_p95_deg_below"] == 8.0 and ta["cells"] == cells[-1]
    assert (tmp_path / "convergence_all.png").stat().st_size > 0


def test_shipped_measures_a_shipped_mesh_against_its_surface_s_limit(tmp_path):
    """--shipped: the 9-week gains on the shipped mesh with fibres made on it, and their
    errors against the kept study's limits (the study here a made-up one: its numbers are
    what the errors must be computed from)."""
    import json

    def series(limit, order, spread):
        return {"own": {"values": [limit], "order": order, "limit": limit, "errors": [spread]}}

    study = {"benchmark": "convergence", "muscle": "ST_VHM_Right", "fibres_method": "laplace",
             "levels": [{"cells_target": 8000, "cells": 1}, {"cells_target": 16000, "cells": 2}],
             "estimates": {"csa_gain_pct": series(8.4, None, 1e-4), "volume_gain_pct": series(8.39, 2.0, 0.0),
                           "csa_solid_gain_pct": series(8.41, 2.0, 0.0)}}
    (tmp_path / "studies" / "convergence_all").mkdir(parents=True)
    (tmp_path / "studies" / "convergence_all" / "ST_VHM_Right.json").write_text(json.dumps(study))
    assert convergence.main(["--shipped", "ST_VHM_Right", "--studies", str(tmp_path / "studies"),
                             "--output", str(tmp_path), "--quiet"]) == 0
    result = json.loads((tmp_path / "shipped_laplace.json").read_text())
    assert (tmp_path / "shipped_laplace.png").is_file()
    (row,) = result["rows"]
    assert row["cells"] == 6707 and not row["same_mesh"] and row["study_muscle"] == "ST_VHM_Right"
    # no order: the distance to the finest level plus its spread; an order: to the limit
    assert row["csa_error"] == pytest.approx(abs(row["csa_gain_pct"] - 8.4) / 8.4 + 1e-4, rel=1e-12)
    assert row["volume_error"] == pytest.approx(abs(row["volume_gain_pct"] - 8.39) / 8.39, rel=1e-12)
    assert row["goal_met"] == (max(row["csa_error"], row["volume_error"]) <= convergence.GROWTH_GOAL)
    # the same gains as the kept measurement of fidelity's table (its fibres made as the shipped file's)
    kept = json.loads((Path(__file__).parents[1] / "results/bench/shipped/shipped_laplace.json").read_text())
    (was,) = [r for r in kept["rows"] if r["geometry"] == "ST_VHM_Right"]
    assert row["csa_gain_pct"] == pytest.approx(was["csa_gain_pct"], rel=1e-9)
    # a geometry without a study of its surface (or its other side's) is a row that says so
    assert convergence.main(["--shipped", "TA_VHF_Left", "--studies", str(tmp_path / "studies"), "--output",
                             str(tmp_path / "none"), "--quiet"]) == 0
    (row,) = json.loads((tmp_path / "none" / "shipped_laplace.json").read_text())["rows"]
    assert "csa_error" not in row and row["study_muscle"] is None


def test_fibres_limit_measures_a_mesh_s_fibres_against_its_shape_s_finer_fields(tmp_path):
    """--fibres-limit's row (`limit_row`): a 1000-cell mesh of `hyper mesh`, whose Laplace flow
    was solved on the surface's 4000-cell mesh, against the surface meshed at 2000 and 4000
    cells: the finest level is that flow's mesh (made by the same steps), so the fibres lie
    on it to interpolation, and the flow on the mesh itself does not. As a paper mesh (no
    surface): its mesh refined once and twice, whose fields approach each other."""
    import re

    from hyper.commands import mesh as mesh_job
    from hyper.fem import laplace
    from hyper.runs import runspec

    stl = Path(__file__).parent / "data" / "TA_VHF_Right_coarse.stl"
    out = tmp_path / "TA_T"
    assert mesh_job.main([str(stl), "--output", str(out), "--cells", "1000", "--quiet"]) == 0
    geometry = runspec.MeshFile(out / "TA_T.xdmf", "mm").load(MPI.COMM_SELF)
    fibre_file = out / fibers.FILE_NAME
    row = convergence.limit_row(MPI.COMM_SELF, geometry, fibre_file, (stl, ["--end-rule", "surface"]),
                                [2000, 4000], tmp_path / "scratch")
    flow_cells = int(re.search(r"at (\d+) cells", row["fibres_method"]).group(1))
    assert row["reference"] == "meshes of its surface" and row["reference_cells"][-1] == flow_cells
    assert row["fibres"]["p95_deg"] < 0.05 and row["own_mesh"]["p95_deg"] > 0.5
    assert row["bound_p95_deg"] == row["fibres"]["p95_deg"] + row["spread"]["p95_deg"]
    assert row["goal_met"] == (row["bound_p95_deg"] <= convergence.FIBRES_GOAL_DEG)
    assert not (tmp_path / "scratch").exists()

    own = tmp_path / "own.h5"
    laplace.store(own, geometry, *laplace.compute(geometry))
    paper = convergence.limit_row(MPI.COMM_SELF, geometry, own, None, [], tmp_path / "unused")
    assert paper["reference"] == "its mesh refined uniformly" and "own_mesh" not in paper
    assert paper["reference_cells"] == [8 * geometry.num_cells(), 64 * geometry.num_cells()]
    # P2 potentials on nested meshes: once refined is nearer the twice refined than the mesh itself
    assert 0.0 < paper["spread"]["p95_deg"] < 0.7 * paper["fibres"]["p95_deg"]


def test_fibres_limit_refuses_what_it_cannot_measure(capsys):
    assert convergence.main(["--fibres-limit", "VM_VHM_Left", "--reference-cells", "64000", "--quiet"]) == 2
    assert "needs two or more levels" in capsys.readouterr().err
    assert convergence.main(["--fibres-limit", "idealized", "--quiet"]) == 2
    assert "not a shipped anatomical or meshed geometry" in capsys.readouterr().err
