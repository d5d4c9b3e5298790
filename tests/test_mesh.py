"""hyper mesh: surfaces refused before anything is written, the end rule on a cylinder,
a meshed cylinder's volume and cross-section against the analytic ones, and one real
surface (tests/data) meshed end to end."""

import math
import struct
from pathlib import Path

import numpy as np
import pytest

from hyper.commands import cli
from hyper.commands import mesh as mesh_job
from hyper.core.params import InputError
from hyper.fem import fiberread as fr
from hyper.fem import meshing as hm

RADIUS, LENGTH = 20.0, 100.0  # mm
AROUND, ALONG = 48, 10


def cylinder() -> tuple[np.ndarray, np.ndarray]:
    """A closed cylinder along z, outward triangles: caps as fans around their centres."""
    phi = 2 * np.pi * np.arange(AROUND) / AROUND
    rings = [np.column_stack([RADIUS * np.cos(phi), RADIUS * np.sin(phi), np.full(AROUND, z)])
             for z in np.linspace(0.0, LENGTH, ALONG + 1)]
    points = np.vstack(rings + [[[0, 0, 0]], [[0, 0, LENGTH]]])
    bottom, top = len(points) - 2, len(points) - 1
    tris = []
    for k in range(ALONG):
        for i in range(AROUND):
            a, b = k * AROUND + i, k * AROUND + (i + 1) % AROUND
            tris += [[a, b, b + AROUND], [a, b + AROUND, a + AROUND]]
    for i in range(AROUND):
        tris.append([bottom, (i + 1) % AROUND, i])
        tris.append([top, ALONG * AROUND + i, ALONG * AROUND + (i + 1) % AROUND])
    return points, np.array(tris)


def write_stl(path, points, tris, ascii=False):
    corners = points[tris]
    if ascii:
        lines = ["solid s"] + ["facet normal 0 0 0\nouter loop\n" + "".join(f"vertex {p[0]} {p[1]} {p[2]}\n"
                                                                              for p in c) + "endloop\nendfacet"
                               for c in corners] + ["endsolid s"]
        path.write_text("\n".join(lines))
    else:
        data = bytearray(80) + struct.pack("<I", len(tris))
        for c in corners.astype(np.float32):
            data += struct.pack("<12fH", 0, 0, 0, *c.ravel(), 0)
        path.write_bytes(bytes(data))
    return path


def refused(tmp_path, capsys, stl, *extra) -> str:
    out = tmp_path / "meshes" / "M_X_Left"
    status = mesh_job.main([str(stl), "--output", str(out), *extra])
    assert status == cli.EXIT_INPUT
    assert not (tmp_path / "meshes").exists()  # nothing written
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ")
    return lines[0]


def test_a_surface_with_a_hole_is_refused(tmp_path, capsys):
    points, tris = cylinder()
    assert "not closed" in refused(tmp_path, capsys, write_stl(tmp_path / "s.stl", points, tris[1:]))


def test_two_bodies_are_refused(tmp_path, capsys):
    points, tris = cylinder()
    both = np.vstack([points, points + [3 * RADIUS, 0, 0]])
    stl = write_stl(tmp_path / "s.stl", both, np.vstack([tris, tris + len(points)]))
    assert "2 separate bodies" in refused(tmp_path, capsys, stl)


def test_an_inward_surface_is_refused(tmp_path, capsys):
    points, tris = cylinder()
    assert "oriented inward" in refused(tmp_path, capsys, write_stl(tmp_path / "s.stl", points, tris[:, ::-1]))


def test_a_flipped_triangle_is_refused(tmp_path, capsys):
    points, tris = cylinder()
    tris[5] = tris[5, ::-1]
    assert "inconsistently oriented" in refused(tmp_path, capsys, write_stl(tmp_path / "s.stl", points, tris))


def test_a_self_intersection_is_refused(tmp_path, capsys):
    points, tris = cylinder()
    dented = points.copy()
    dented[5 * AROUND] = [-1.5 * RADIUS, 0, LENGTH / 2]  # one side vertex pushed through the far wall
    assert "intersects itself" in refused(tmp_path, capsys, write_stl(tmp_path / "s.stl", dented, tris))


def test_a_metre_surface_declared_as_mm_is_refused(tmp_path, capsys):
    points, tris = cylinder()
    message = refused(tmp_path, capsys, write_stl(tmp_path / "s.stl", points * 1e-3, tris), "--unit", "mm")
    assert "its length unit is not 'mm'" in message


def test_a_file_that_is_not_stl_is_refused(tmp_path, capsys):
    text = tmp_path / "s.stl"
    text.write_text("ply\nformat ascii 1.0\n")
    assert "not an STL file" in refused(tmp_path, capsys, text)


def test_ascii_and_binary_read_the_same(tmp_path):
    points, tris = cylinder()
    binary = hm.read_stl(write_stl(tmp_path / "b.stl", points, tris))
    text = hm.read_stl(write_stl(tmp_path / "a.stl", points, tris, ascii=True))
    assert len(binary[1]) == len(text[1]) == len(tris)
    np.testing.assert_allclose(binary[0], text[0], atol=1e-5)


def test_the_end_rule_finds_the_two_caps_of_a_cylinder_exactly():
    points, tris = cylinder()
    tags, rule = hm.find_ends(points, tris)
    top = np.isclose(points[tris][:, :, 2], LENGTH).all(axis=1)
    bottom = np.isclose(points[tris][:, :, 2], 0.0).all(axis=1)
    assert np.array_equal(tags == 1, top) and np.array_equal(tags == 2, bottom)  # origin toward +z
    assert abs(abs(rule["axis"][2]) - 1) < 1e-12


def test_the_end_rule_refuses_bands_that_would_touch():
    points, tris = cylinder()
    with pytest.raises(InputError, match="touch"):
        hm.find_ends(points, tris, band=0.5)


@pytest.fixture(scope="module")
def meshed(tmp_path_factory):
    root = tmp_path_factory.mktemp("meshed")
    points, tris = cylinder()
    out = root / "CYL_X_Left"
    # the paper's Stokes fibres: the finer flow of --flow-cells is theirs (the default is Laplace's)
    status = mesh_job.main([str(write_stl(root / "c.stl", points, tris)), "--output", str(out), "--cells", "3000",
                            "--method", "stokes", "--quiet"])
    assert status == cli.EXIT_OK
    return out


def test_a_meshed_cylinder_has_the_analytic_volume_and_cut_area(meshed):
    import json

    import h5py
    from mpi4py import MPI

    from hyper.fem import fibers, section
    from hyper.fem import geometry as geo

    record = json.loads((meshed / "mesh.json").read_text())
    stats = record["statistics"]
    # gmsh's surface nodes lie on the STL, and its edges (about 7 mm here) are chords of
    # the 20 mm circle; fill_surface moves them out by one offset that restores the STL's volume.
    polygon = 0.5 * AROUND * RADIUS**2 * math.sin(2 * math.pi / AROUND)  # mm²
    assert abs(stats["volume_cm3"] / (polygon * LENGTH * 1e-3) - 1) < 1e-8
    assert 0.05 < record["quality"]["surface_offset_mm"] < 0.3  # the chords' mean sagitta, a fraction of 20²/(8 R)
    assert abs(stats["csa0_cm2"] / (polygon * 1e-2) - 1) < 0.01
    assert abs(stats["length_cm"] / (LENGTH / 10) - 1) < 5e-3  # the principal axis of the vertices tilts a little
    # The solid's frame is the cylinder's own: the cut across its axis, and the caps' distance
    # (the offset moves the flat caps out by the same 0.1 mm). The cut is 0.85 % short: the
    # fine surface near the two tips (a rim point of each cap here) needs less offset than
    # the coarse middle, and the one offset is their mean.
    assert abs(stats["csa_solid_cm2"] / (polygon * 1e-2) - 1) < 0.0125
    offset_cm = record["quality"]["surface_offset_mm"] / 10
    assert abs(stats["length_solid_cm"] - (LENGTH / 10 + 2 * offset_cm)) < 1e-3
    assert 2500 < stats["cells"] < 3500 and record["quality"]["min_dihedral_deg"] > 5
    # The ends hold every cap facet; gmsh's side facets are chords across the 48-gon, whose
    # normals tilt off the horizontal, so the band also takes a few of them next to the rim.
    with h5py.File(meshed / "CYL_X_Left.h5", "r") as f:
        x = f["Mesh/Grid/geometry"][()]
        corners = x[f["MeshTags/ft_small/topology"][()]]
        tags = f["MeshTags/ft_small/Values"][()].ravel()
        origin, normal = section.inertia_plane(*section.solid_moments(x[f["Mesh/Grid/topology"][()]]))
    # The volume's centroid and inertia axis are the cylinder's centre and axis to the
    # mesher's accuracy (gmsh's tetrahedra are not symmetric: 0.01 mm, 0.01°).
    assert np.allclose(origin, [0, 0, LENGTH / 2], atol=0.02)
    assert normal[2] > math.cos(math.radians(0.02))
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    for tag, z in ((1, LENGTH), (2, 0.0)):
        cap = (np.abs(corners[:, :, 2] - z) < 0.5).all(axis=1)  # moved out by the offset, rim nodes less
        assert (tags[cap] == tag).all()
        assert area[(tags == tag) & ~cap].sum() < 0.05 * area[cap].sum()
    geometry = geo.load_file(meshed / "CYL_X_Left.xdmf", MPI.COMM_WORLD, name="CYL_X_Left", scale=geo.MM)
    a0 = fibers.load(geometry, meshed / fibers.FILE_NAME)
    assert fibers.aligned_share(geometry, a0, (0, 0, 1), angle_deg=10.0) > 0.99
    assert (meshed / "CYL_X_Left.png").is_file()


def test_an_existing_output_is_kept_without_force(meshed, capsys):
    status = mesh_job.main([str(meshed / "missing.stl"), "--output", str(meshed)])
    assert status == cli.EXIT_INPUT and "exists" in capsys.readouterr().err


REAL = Path(__file__).parent / "data" / "TA_VHF_Right_coarse.stl"  # tests/data/README.md


def test_a_real_surface_meshes_end_to_end(tmp_path):
    """The right female tibialis anterior (a coarse copy of its Visible Human surface) to a
    loadable geometry with proximal origin, distal insertion and fibres along the muscle."""
    import json

    import h5py
    from mpi4py import MPI
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from hyper.fem import fibers
    from hyper.fem import geometry as geo

    out = tmp_path / "TA_VHF_Right"
    assert mesh_job.main([str(REAL), "--output", str(out), "--cells", "3000", "--quiet"]) == cli.EXIT_OK
    points, tris = hm.read_stl(REAL)
    record = json.loads((out / "mesh.json").read_text())
    stats = record["statistics"]
    assert 2700 <= stats["cells"] <= 3300 and record["quality"]["min_dihedral_deg"] > 5
    # The surface offset gives the mesh the STL's volume (gmsh's chords alone lose a few % at 3000 cells).
    assert abs(stats["volume_cm3"] / (hm.enclosed_volume(points, tris) * 1e-3) - 1) < 1e-8
    assert 0 < record["quality"]["surface_offset_mm"] < 0.5
    with h5py.File(out / "TA_VHF_Right.h5", "r") as f:
        x = f["Mesh/Grid/geometry"][()]
        facets = f["MeshTags/ft_small/topology"][()]
        tags = f["MeshTags/ft_small/Values"][()].ravel()
    assert set(tags) == {1, 2, 3}
    z = {}
    for tag in (1, 2):
        patch = facets[tags == tag]
        incidence = coo_matrix((np.ones(patch.size), (np.repeat(np.arange(len(patch)), 3), patch.ravel()))).tocsr()
        assert connected_components(incidence @ incidence.T, directed=False)[0] == 1  # one patch per end
        z[tag] = x[patch].mean(axis=(0, 1))[2]
    # The VHF frame's z points proximally: the origin (knee end of the TA) lies above the insertion (ankle).
    assert z[1] - z[2] > 0.9 * np.ptp(points[:, 2])
    geometry = geo.load_file(out / "TA_VHF_Right.xdmf", MPI.COMM_WORLD, name="TA_VHF_Right", scale=geo.MM)
    assert geometry.num_cells() == stats["cells"]
    a0 = fibers.load(geometry, out / fibers.FILE_NAME)
    assert fibers.aligned_share(geometry, a0, record["ends"]["axis"], angle_deg=30.0) > 0.95
    # the default fibres: Laplace's, which converge with the mesh (docs/convergence.md)
    assert record["fibres_method"] == "laplace" and fr.stored_fibres(out / fibers.FILE_NAME)[0] == "laplace"


def test_flow_cells_solves_the_fibres_on_a_finer_mesh_of_the_surface(meshed, tmp_path):
    """--flow-cells 3000 on a 1000-cell mesh: the flow of the surface's 3000-cell mesh (the
    `meshed` fixture's, gmsh being deterministic) interpolated onto the coarse nodes."""
    import json

    import h5py
    from mpi4py import MPI

    from hyper.fem import fibers
    from hyper.fem import geometry as geo

    out = tmp_path / "CYL_Y_Left"
    assert mesh_job.main([str(meshed.parent / "c.stl"), "--output", str(out), "--cells", "1000", "--flow-cells", "3000",
                          "--method", "stokes", "--quiet"]) == cli.EXIT_OK
    assert json.loads((out / "mesh.json").read_text())["flow_cells_target"] == 3000
    assert sorted(p.name for p in out.iterdir()) == ["CYL_Y_Left.h5", "CYL_Y_Left.png", "CYL_Y_Left.xdmf",
                                                     "fibers.h5", "mesh.json"]
    flow_cells = json.loads((meshed / "mesh.json").read_text())["statistics"]["cells"]
    with h5py.File(out / fibers.FILE_NAME) as f:
        params = fibers.StokesParams(smoothing_m=mesh_job.FIBERS_SMOOTHING_MM * geo.MM)
        assert f.attrs["method"] == fibers.stokes_method(params) + fibers.TRANSFERRED_METHOD.format(cells=flow_cells)
    coarse = geo.load_file(out / "CYL_Y_Left.xdmf", MPI.COMM_WORLD, name="CYL_Y_Left", scale=geo.MM)
    fine = geo.load_file(meshed / "CYL_X_Left.xdmf", MPI.COMM_WORLD, name="CYL_X_Left", scale=geo.MM)
    mine = fibers.load(coarse, out / fibers.FILE_NAME).x.array
    expected = fibers.transferred(fibers.load(fine, meshed / fibers.FILE_NAME), coarse).x.array.reshape(-1, 3)
    expected /= np.linalg.norm(expected, axis=1)[:, None]
    np.testing.assert_allclose(mine, expected.ravel(), atol=1e-9)
