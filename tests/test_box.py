"""The original code's box measure of a cross-section (hyper.box, MODEL.md §9)."""

import math
from pathlib import Path

import dolfinx
import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np
import pytest
from dolfinx import fem
from mpi4py import MPI

from hyper.analysis import cohortsummary
from hyper.commands import grow
from hyper.core import io
from hyper.core.params import InputError
from hyper.fem import boxsection as box
from hyper.fem import geometry as geo
from hyper.fem import section
from hyper.runs import driver, runspec

# A prism [-A, A] × [-B, B] × [-L, L] (m), long along z: the box is 2.4 A × 2.4 B in 30 × 30
# squares of 0.08 A × 0.08 B, and the prism's sides cross the middle of columns and rows
# 2 and 27 (0.2 A = 2.5 squares in from the box's edge).
A, B, L = 0.01, 0.015, 0.05
SQUARE = 0.08 * A * 0.08 * B  # m², two staircase facets


def prism(comm):
    return dolfinx.mesh.create_box(comm, [[-A, -B, -L], [A, B, L]], [4, 6, 20])


def displacement(mesh, f):
    u = fem.Function(fem.functionspace(mesh, ("Lagrange", 2, (3,))))
    u.interpolate(f)
    return u


def uniform_growth(theta):
    """The stress-free answer of a uniform transverse growth ϑ about the z axis."""
    s = math.sqrt(theta) - 1.0
    return lambda x: np.array([s * x[0], s * x[1], 0.0 * x[2]])


def test_inside_a_tetrahedron_by_its_barycentric_coordinates():
    tet = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    flat = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    tets = np.array([tet, tet, tet, tet, flat])
    points = np.array([[0.2, 0.2, 0.2], [0.5, 0.5, 0.1], [0.0, 0.3, 0.3], [-0.1, 0.2, 0.2], [0.3, 0.3, 0.0]])
    # inside; beyond the slanted face; on a face (not strictly inside); outside; a degenerate tetrahedron
    assert box.inside(tets, points).tolist() == [True, False, False, False, False]


def test_prism_staircase_is_the_faces_of_the_touching_cells():
    mesh = prism(MPI.COMM_SELF)
    u = displacement(mesh, lambda x: np.zeros_like(x))
    measure = box.BoxSection(mesh, u)
    assert np.allclose(measure.half, [0.5e-3, 1.2 * B, 1.2 * A], rtol=1e-12)  # by decreasing variance
    # every cell of the 26 × 26 columns that reach into the prism touches it (each of a
    # column's 6 tetrahedra holds the column's diagonal, which crosses the side); the
    # 24 × 24 columns of those wholly inside are the inner part
    inner, rim = measure.areas0
    assert inner == pytest.approx(24**2 * SQUARE, rel=1e-12)
    assert inner + rim == pytest.approx(26**2 * SQUARE, rel=1e-12)
    assert measure.area0() / (4 * A * B) == pytest.approx(1.0816, rel=1e-12)
    # at rest the staircase reads its own area
    assert measure.deformed_areas() == pytest.approx(measure.areas0, rel=1e-13)


def test_prism_inner_faces_read_theta_rim_faces_read_less():
    theta = 1.1
    mesh = prism(MPI.COMM_SELF)
    measure = box.BoxSection(mesh, displacement(mesh, uniform_growth(theta)))
    inner, rim = measure.deformed_areas() / measure.areas0
    assert inner == pytest.approx(theta, rel=1e-12)
    assert rim < 1.0  # the displacement falls to zero across the rim: it reads as shrinking


def cylinder():
    return geo.load("cylinder", MPI.COMM_SELF).mesh


def axis_distance(tets) -> np.ndarray:
    """The distance of each tetrahedron (n, 4, 3) from the z axis: of the convex hull of
    its corners' projections (x, y) from the origin."""
    p = tets[:, :, :2]
    inside = np.zeros(len(p), dtype=bool)
    for i, j, k in ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)):
        a, b, c = p[:, i], p[:, j], p[:, k]
        signs = [(q1 - q0)[:, 0] * -q0[:, 1] + (q1 - q0)[:, 1] * q0[:, 0] for q0, q1 in ((a, b), (b, c), (c, a))]
        inside |= np.all(np.stack(signs) >= 0, axis=0) | np.all(np.stack(signs) <= 0, axis=0)
    dist = np.full(len(p), np.inf)
    for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)):
        a, d = p[:, i], p[:, j] - p[:, i]
        t = np.clip(-np.einsum("ij,ij->i", a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-300), 0, 1)
        dist = np.minimum(dist, np.linalg.norm(a + t[:, None] * d, axis=1))
    return np.where(inside, 0.0, dist)


def test_separated_tetrahedra_are_apart_by_gjk_and_touching_ones_never_separated():
    rng = np.random.default_rng(7)
    a = rng.uniform(0, 1, (4000, 4, 3))
    b = rng.uniform(0, 1, (4000, 4, 3)) + rng.uniform(-0.9, 0.9, (4000, 1, 3))
    distance = np.array([np.linalg.norm(dolfinx.geometry.compute_distance_gjk(p, q)) for p, q in zip(a, b)])
    gap = 0.05
    apart = box.separated(a, b, gap)
    assert np.all(distance[apart] > gap)
    # a sufficient test that still decides most pairs that are apart, and no touching one
    assert np.count_nonzero(apart) > 0.6 * np.count_nonzero(distance > gap)
    assert not np.any(apart[distance <= 1e-14])
    assert np.count_nonzero(distance <= 1e-14) > 200


def test_touching_cells_are_those_gjk_finds_for_every_candidate_pair():
    mesh = cylinder()
    centre, axes, half = box.box_frame(mesh.geometry.x, padding=box.PADDING, thickness=box.THICKNESS)
    serial, _ = box.box_mesh(MPI.COMM_SELF, centre, axes, half)
    n = serial.topology.index_map(3).size_local
    owned = np.arange(mesh.topology.index_map(3).size_local, dtype=np.int32)
    pairs = dolfinx.geometry.compute_collisions_trees(dolfinx.geometry.bb_tree(mesh, 3, entities=owned),
                                                      dolfinx.geometry.bb_tree(serial, 3))
    xm, xb = box.cell_coordinates(mesh, owned), box.cell_coordinates(serial, np.arange(n))
    brute = np.zeros(n, dtype=bool)
    for m, c in np.asarray(pairs).reshape(-1, 2):
        brute[c] |= np.linalg.norm(dolfinx.geometry.compute_distance_gjk(xm[m], xb[c])) <= box.TOUCH
    expected = np.zeros(n, dtype=bool)
    expected[np.asarray(serial.topology.original_cell_index)[:n]] = brute
    assert np.array_equal(box.touching(serial, mesh), expected)
    assert 100 < np.count_nonzero(expected) < n


def test_cylinder_staircase_is_the_faces_of_the_touching_cells():
    mesh = cylinder()
    u = displacement(mesh, lambda x: np.zeros_like(x))
    measure = box.BoxSection(mesh, u)
    r = np.linalg.norm(mesh.geometry.x[:, :2], axis=1).max()  # the corners of the meshed circle

    # the kept cells: every one that reaches well into the circle, none outside it
    serial, _ = box.box_mesh(MPI.COMM_SELF, measure.centre, measure.axes, measure.half)
    n = serial.topology.index_map(3).size_local
    by_original = box.touching(serial, mesh)
    kept = by_original[np.asarray(serial.topology.original_cell_index)[:n]]
    distance = axis_distance(box.cell_coordinates(serial, np.arange(n)) - [measure.centre[0], measure.centre[1], 0])
    assert np.all(kept[distance < 0.95 * r]) and not np.any(kept[distance > r])
    assert np.count_nonzero(distance < 0.95 * r) > 1000

    # the staircase: the box faces of the kept cells on the face at -0.5 mm, one triangle each
    facets = measure.tags.indices
    face = 0.5 * (2 * measure.half[1] / 30) * (2 * measure.half[2] / 30)
    assert measure.area0() == pytest.approx(len(facets) * face, rel=1e-12)
    cells = [measure.mesh.topology.connectivity(2, 3).links(f)[0] for f in facets]
    original = np.asarray(measure.mesh.topology.original_cell_index)
    assert np.all(by_original[original[cells]])
    # it covers the section at its plane, and overhangs it
    cut = section.CutSection(mesh, *measure.plane()).area0()
    assert 1.05 < measure.area0() / cut < 1.15


def test_cylinder_inner_faces_read_theta_rim_faces_read_less():
    theta = 1.08
    mesh = cylinder()
    measure = box.BoxSection(mesh, displacement(mesh, uniform_growth(theta)))
    inner, rim = measure.deformed_areas() / measure.areas0
    # the meshed cylinder's first principal axis is e_z to a few 1e-3: the box face tilts
    # by as much, and F = G reads |cof(G) N| = ϑ (1 - 2e-7) on it
    s = math.sqrt(theta)
    exact = section.nanson_density(np.diag([s, s, 1.0]), measure.axes[:, 0])
    assert abs(exact / theta - 1) < 1e-6
    assert inner == pytest.approx(exact, rel=1e-12)
    assert rim < 1.0
    total = measure.deformed_area() / measure.area0()
    assert 1.0 < total < theta
    picture = measure.picture()
    assert len(picture["triangles"]) == len(measure.tags.indices)
    assert np.allclose(picture["ratio"][picture["inner"]], exact, rtol=1e-12)
    assert np.all(picture["ratio"][~picture["inner"]] < exact)
    # the outline of the exact cut: the meshed circle, cut by a plane tilted a few 1e-3
    points = measure.centre + picture["outline"].reshape(-1, 2) @ measure.axes[:, 1:].T
    radius = np.linalg.norm(points[:, :2], axis=1)
    r = np.linalg.norm(mesh.geometry.x[:, :2], axis=1).max()
    assert 0.99 * r < radius.min() and radius.max() < 1.001 * r


def nonlinear(x):
    return np.array([0.05 * x[0] + 3 * x[1] ** 2, 0.04 * x[1] * (1 + 10 * x[0]), 0.01 * x[2] + x[0] * x[1]])


@pytest.mark.mpi
@pytest.mark.parametrize("outside", box.OUTSIDE)
def test_parallel_equals_serial(outside):
    comm = MPI.COMM_WORLD
    assert comm.size == 2
    values = {}
    for c in (MPI.COMM_SELF, comm):
        mesh = geo.load("cylinder", c).mesh
        measure = box.BoxSection(mesh, displacement(mesh, nonlinear), outside=outside)
        picture = measure.picture()
        values[c.size] = (measure.centre, measure.axes, measure.areas0, measure.deformed_areas(),
                          None if picture is None else np.sort(picture["ratio"]), measure.outside_nodes)
    (c1, x1, a1, d1, p1, n1), (c2, x2, a2, d2, p2, n2) = values[1], values[2]
    assert np.array_equal(c1, c2) and np.array_equal(x1, x2)  # the frame: the file's order on any ranks
    assert a2 == pytest.approx(a1, rel=1e-12)
    assert n1 == n2 and n1[1] > 0
    assert abs(d1[0] / a1[0] - 1) > 1e-3 and d2 == pytest.approx(d1, rel=1e-11)  # the inner part moves
    if comm.rank == 0:
        assert p2 == pytest.approx(p1, rel=1e-11)


def write_prism(path: Path, turn: float = 0.0):
    """A prism muscle 2 × 3 × 10 cm, turned by ``turn`` (rad) about its length, as an XDMF
    file with the anatomical meshes' tags."""
    mesh = dolfinx.mesh.create_box(MPI.COMM_SELF, [[0, 0, 0], [0.02, 0.03, 0.1]], [2, 2, 5])
    c, s = math.cos(turn), math.sin(turn)
    mesh.geometry.x[:, :2] = mesh.geometry.x[:, :2] @ np.array([[c, s], [-s, c]])
    mesh.name = "Grid"
    mesh.topology.create_connectivity(2, 3)
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    z = dolfinx.mesh.compute_midpoints(mesh, 2, facets)[:, 2]
    values = np.where(np.isclose(z, 0), 1, np.where(np.isclose(z, 0.1), 2, 3)).astype(np.int32)
    tags = dolfinx.mesh.meshtags(mesh, 2, facets, values)
    tags.name = "ft_small"
    with dolfinx.io.XDMFFile(MPI.COMM_SELF, str(path), "w") as xdmf:
        xdmf.write_mesh(mesh)
        xdmf.write_meshtags(tags, mesh.geometry)


PROTOCOL = """name = "one"
end = 48.0
[[session]]
start = 0.0
duration = 1.0
intensity = 0.8
"""


def test_grow_records_every_measure_and_feeds_back_the_chosen_one(tmp_path):
    write_prism(tmp_path / "prism.xdmf")
    (tmp_path / "one.toml").write_text(PROTOCOL)
    series = {}
    for method in ("cut", "box", "solid"):
        out = tmp_path / f"{method}.h5"
        picture = ["--plot-box", str(tmp_path / "box.png")] if method == "box" else []
        assert grow.main(["--mesh", str(tmp_path / "prism.xdmf"), "--protocol", str(tmp_path / "one.toml"),
                          "--growth-dt", "24", "--csa-method", method, "--output", str(out), *picture],
                         MPI.COMM_SELF) == 0
        series[method] = io.read_series(out)
    assert (tmp_path / "box.png").stat().st_size > 10_000
    for method, s in series.items():
        assert np.array_equal(s["csa_ratio"], s[f"csa_ratio_{method}"])
        assert s["csa_ratio_cut"][-1] > 1.0005 and s["csa_ratio_box"][-1] < s["csa_ratio_cut"][-1]
        assert s["csa_ratio_solid"][-1] > 1.0005
    # the box reads less, so the feedback lowers synthesis less and the muscle grows more
    assert series["box"]["kM"][-1] > series["cut"]["kM"][-1]


def test_cohort_summary_has_both_measures(tmp_path):
    attrs = {"geometry": "BFLH_VHF_Left", "muscle": "BFLH", "subject": "VHF", "side": "Left", "protocol": "mwf",
             "csa0_m2": 1e-3, "volume0_m3": 2e-4, "wall_s": 1.0}
    ratios = {"csa_ratio": [1.0, 1.04], "csa_ratio_cut": [1.0, 1.08], "csa_ratio_box": [1.0, 1.04],
              "volume_ratio": [1.0, 1.09]}
    io.write_series(tmp_path / "r.h5", {k: np.array(v) for k, v in ratios.items()}, attrs=attrs)
    rows = [cohortsummary.summary_row(tmp_path / "r.h5")]
    assert (rows[0]["final_csa_ratio"], rows[0]["final_csa_ratio_cut"], rows[0]["final_csa_ratio_box"]) == \
        (1.04, 1.08, 1.04)
    cohortsummary.write_csv(rows, tmp_path / "s.csv")
    assert cohortsummary.read_csv(tmp_path / "s.csv")[0]["final_csa_ratio_cut"] == 1.08
    table = cohortsummary.markdown(rows, cohortsummary.GrowthSettings())
    assert "| mid-belly CSA increase, cut (n = 1) | +8.00 % |" in table
    assert "| mid-belly CSA increase, box (n = 1) | +4.00 % |" in table


def test_plot_box_needs_a_mesh_without_a_tagged_section(tmp_path, capsys):
    assert grow.main(["--geometry", "idealized", "--plot-box", str(tmp_path / "b.png"),
                      "--output", str(tmp_path / "r.h5")], MPI.COMM_SELF) == 2
    assert "--plot-box: idealized has a tagged mid-section" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_a_resumed_run_records_both_measures_as_an_uninterrupted_one(tmp_path):
    from hyper.fem.coupled import GrowthSettings
    from hyper.model import protocols, signaling

    write_prism(tmp_path / "prism.xdmf")
    (tmp_path / "one.toml").write_text(PROTOCOL)
    spec = runspec.RunSpec("prism", protocols.from_option(str(tmp_path / "one.toml"))[0],
                       signaling.SignalingParams(thetaM=0.46), GrowthSettings(growth_dt=8.0, csa_method="box"),
                       mesh=runspec.MeshFile(tmp_path / "prism.xdmf"))
    comm = MPI.COMM_SELF
    whole = driver.execute(comm, spec, runspec.Outputs(tmp_path / "whole.h5"), checkpoints=False).series
    out = runspec.Outputs(tmp_path / "parts.h5")
    reports = iter(range(100))
    with pytest.raises(driver.Interrupted):
        driver.execute(comm, spec, out, stop=lambda: next(reports) >= 2)
    parts = driver.execute(comm, spec, out).series
    assert len(parts["t"]) == len(whole["t"]) > 4
    for name in ("csa_ratio", "csa_ratio_cut", "csa_ratio_box", "csa_ratio_solid", "volume_ratio", "kM"):
        np.testing.assert_array_equal(parts[name], whole[name], err_msg=name)
    assert whole["csa_ratio_box"][-1] < whole["csa_ratio_cut"][-1]


# ------------------------------------------------------------ what the box does outside


def in_plane_jacobian_area(measure) -> float:
    """∫ cof(F) N · N dA over the staircase, F = I + ∇u of the box field as it is now."""
    import ufl

    F = ufl.Identity(3) + ufl.grad(measure.field)
    N = ufl.FacetNormal(measure.mesh)
    ds = ufl.Measure("ds", domain=measure.mesh, subdomain_data=measure.tags,
                     metadata={"quadrature_degree": box.QUADRATURE_DEGREE})
    return fem.assemble_scalar(fem.form(ufl.dot(ufl.cofac(F) * N, N) * ds((box.INNER, box.RIM))))


def test_in_cells_is_a_point_in_cell_test_not_a_bounding_box_one():
    mesh = prism(MPI.COMM_SELF)
    d = box.INSIDE_DISTANCE
    points = [[0, 0, 0], [A, 0.3 * B, 0], [A + 0.5 * d, 0, 0], [A + 3 * d, 0, 0], [-A, -B, -L], [A, B, L + 1e-9]]
    assert box.in_cells(mesh, np.array(points)).tolist() == [True, True, True, False, True, False]
    # a tetrahedron's bounding box holds points outside it: (1, 1, 1)/4 of the unit cube's corner one is in
    # it, (0.9, 0.9, 0.9) only in its bounding box
    tet = dolfinx.mesh.create_mesh(MPI.COMM_SELF, np.array([[0, 1, 2, 3]], dtype=np.int64),
                                   dolfinx.fem.coordinate_element(dolfinx.mesh.CellType.tetrahedron, 1),
                                   np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float))
    assert box.in_cells(tet, np.array([[0.25, 0.25, 0.25], [0.9, 0.9, 0.9]])).tolist() == [True, False]


def test_outside_must_be_a_known_rule():
    mesh = prism(MPI.COMM_SELF)
    with pytest.raises(InputError, match=r"outside: expected one of extrapolate, zero, got 'nearest'"):
        box.BoxSection(mesh, displacement(mesh, lambda x: np.zeros_like(x)), outside="nearest")


def test_prism_has_nothing_to_extrapolate_and_reads_its_reference_area_by_both_rules():
    # an axis-aligned prism's cells have bounding boxes inside it: no box node outside it is
    # extrapolated to, and the staircase's edge (on cells that touch no muscle cell) has u = 0
    mesh = prism(MPI.COMM_SELF)
    u = displacement(mesh, uniform_growth(1.1))
    measures = {rule: box.BoxSection(mesh, u, outside=rule) for rule in box.OUTSIDE}
    for rule, m in measures.items():
        assert m.outside_nodes[1] == 0
        # ∫ cof(F) N · N dA depends on the edge's values alone: the reference area; here
        # cof(F) N is along N (u has no part along the prism), so Nanson reads the same
        assert m.deformed_area() / m.area0() == pytest.approx(1.0, abs=1e-12), rule
    assert np.array_equal(measures["zero"].deformed_areas(), measures["extrapolate"].deformed_areas())


def test_cylinder_zero_rim_takes_the_inner_growth_back_extrapolate_reads_more():
    theta = 1.08
    mesh = cylinder()
    u = displacement(mesh, uniform_growth(theta))
    measures = {rule: box.BoxSection(mesh, u, outside=rule) for rule in box.OUTSIDE}
    s = math.sqrt(theta)
    exact = section.nanson_density(np.diag([s, s, 1.0]), measures["zero"].axes[:, 0])
    outside, extrapolated = measures["zero"].outside_nodes
    assert measures["extrapolate"].outside_nodes == (outside, extrapolated) and 0 < extrapolated < outside
    inner0 = {rule: m.areas0[0] for rule, m in measures.items()}
    # the same staircase; the cells with an extrapolated node join the rim under "zero"
    assert measures["zero"].area0() == pytest.approx(measures["extrapolate"].area0(), rel=1e-14)
    assert inner0["zero"] < inner0["extrapolate"]
    ratios = {rule: m.deformed_areas() / m.areas0 for rule, m in measures.items()}
    for rule in box.OUTSIDE:  # where every node has the muscle's linear u, F = G exactly
        assert ratios[rule][0] == pytest.approx(exact, rel=1e-12), rule

    zero = measures["zero"]
    zero.update()
    # u = 0 on the whole edge: the in-plane Jacobian integrates to the reference area, so the
    # rim gives back what the inner part grows, rim / rim0 = 1 - (ϑ' - 1) inner0 / rim0
    assert in_plane_jacobian_area(zero) == pytest.approx(zero.area0(), rel=1e-12)
    inner0, rim0 = zero.areas0
    assert ratios["zero"][1] == pytest.approx(1 - (exact - 1) * inner0 / rim0, abs=1e-4)
    total = {rule: m.deformed_area() / m.area0() for rule, m in measures.items()}
    assert total["zero"] == pytest.approx(1.0, abs=1e-5)  # Nanson differs by the out-of-plane part only
    # extrapolated values on the edge: the staircase reads growth, still less than ϑ
    measures["extrapolate"].update()
    assert in_plane_jacobian_area(measures["extrapolate"]) / zero.area0() > 1.05
    assert 1.05 < total["extrapolate"] < theta


def test_job_remeasures_a_stored_run_by_both_rules(tmp_path, capsys):
    from hyper.commands import cli

    # turned, the prism's cells have bounding boxes that reach out of it: box nodes there
    # are extrapolated to
    write_prism(tmp_path / "prism.xdmf", turn=0.5)
    (tmp_path / "one.toml").write_text(PROTOCOL)
    out = tmp_path / "run.h5"
    assert grow.main(["--mesh", str(tmp_path / "prism.xdmf"), "--protocol", str(tmp_path / "one.toml"),
                      "--growth-dt", "24", "--output", str(out)], MPI.COMM_SELF) == 0
    recorded = io.read_series(out)
    capsys.readouterr()
    assert cli.main(["box", str(out), "--mesh", str(tmp_path / "prism.xdmf"), "--output",
                     str(tmp_path / "box.h5")]) == 0
    printed = capsys.readouterr().out
    series = io.read_series(tmp_path / "box.h5")
    assert series["t"].tolist() == [0.0, 24.5, 48.0]  # the snapshots: the first state, every 24 h, the last
    at = np.searchsorted(recorded["t"], series["t"])
    assert recorded["t"][at].tolist() == series["t"].tolist()
    # the snapshots hold the nodal values of the run's P2 u, which growth leaves near linear here
    box_run = recorded["csa_ratio_box"][at]
    np.testing.assert_allclose(series["csa_ratio_box_extrapolate"], box_run, rtol=1e-6)
    assert box_run[-1] - 1 > 0.1 * (recorded["csa_ratio_cut"][-1] - 1)  # the extrapolation reads growth
    # with u = 0 at every outside node the box reads its reference area, to second order
    np.testing.assert_allclose(series["csa_ratio_box_zero"], 1.0, atol=1e-9)
    assert "no muscle cell, " in printed and " of them inside a muscle cell's bounding box" in printed
    assert f"{series['csa_ratio_box_zero'][-1]:10.6f}" in printed.splitlines()[-3]
    assert "at t = 48 h the box reads CSA" in printed

    # the snapshots must be of the mesh given
    write_prism(tmp_path / "other.xdmf")
    assert cli.main(["box", str(out), "--mesh", str(tmp_path / "other.xdmf")]) == cli.EXIT_INPUT
    assert "the snapshots' mesh is not the run's" in capsys.readouterr().err
    assert cli.main(["box", str(out)]) == cli.EXIT_INPUT
    assert "ran on 'prism', not a built-in geometry; give its mesh with --mesh" in capsys.readouterr().err
    runspec.Outputs(out).fields.unlink()
    assert cli.main(["box", str(out), "--mesh", str(tmp_path / "prism.xdmf")]) == cli.EXIT_INPUT
    assert "run_fields.xdmf are not there" in capsys.readouterr().err
