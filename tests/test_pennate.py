"""Pennate fibres by rule (hyper.fem.pennate, issue 34): a bipennate block and a sheared
parallelepiped whose Laplacian flow is known exactly, the generator's tags, malformed
patches refused, the fibre file beside a mesh and what a run records of it, and parallel
equals serial."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from dolfinx import mesh as dmesh
from dolfinx.io import XDMFFile
from mpi4py import MPI

from hyper.commands import fibers as fibers_job
from hyper.commands import grow
from hyper.commands import mesh as mesh_job
from hyper.core import io
from hyper.core.params import InputError
from hyper.fem import fiberread as fr
from hyper.fem import fibers, pennate
from hyper.fem import geometry as geo
from hyper.model import protocols
from hyper.runs import driver, runspec

THETA = 20.0  # deg, the analytic pennation angle
L, W, T = 0.12, 0.03, 0.015  # m: aponeurosis length, width, half-thickness of the bipennate block
T_MM = T / geo.MM
# the two outer faces z = ±T (boundary facets whose centroid lies within 0.1 mm of them)
OUTER = f"halfspace:0,0,{T_MM - 0.1},0,0,1 | halfspace:0,0,{-T_MM + 0.1},0,0,-1"
CENTRAL = "plane:0,0,0,0,0,1"


def tagged_box(comm, n, where):
    """A box mesh of [0,1]×[0,1]×[-1,1] with facet tags 1 (x = 0), 2 (x = 1), 3 the rest,
    its vertices then moved by ``where(xi, eta, zeta) -> (x, y, z)``."""
    m = dmesh.create_box(comm, [[0, 0, -1], [1, 1, 1]], list(n), dmesh.CellType.tetrahedron)
    m.topology.create_connectivity(2, 3)
    exterior = dmesh.exterior_facet_indices(m.topology)
    values = np.full(len(exterior), 3, dtype=np.int32)
    for tag, at in ((1, 0.0), (2, 1.0)):
        values[np.isin(exterior, dmesh.locate_entities_boundary(m, 2, lambda x, at=at: np.isclose(x[0], at)))] = tag
    tags = dmesh.meshtags(m, 2, exterior, values)
    x = m.geometry.x
    x[:] = np.column_stack(where(x[:, 0].copy(), x[:, 1].copy(), x[:, 2].copy()))
    return geo.Geometry("block", m, tags, ends=(1, 2), lateral=3)


def bipennate(comm, layers=4, theta=THETA):
    """Two mirrored parallelepipeds meeting on the central aponeurosis z = 0: fibres run from
    the outer faces z = ±T to it at ``theta`` to the x axis. The mesh has vertices on z = 0,
    so the map is affine on every cell."""
    cot = 1.0 / np.tan(np.radians(theta))
    return tagged_box(comm, (12, 3, 2 * layers),
                      lambda xi, eta, zeta: (L * xi + T * (1 - np.abs(zeta)) * cot, W * eta, T * zeta))


def exact_bipennate(x, theta=THETA):
    c, s = np.cos(np.radians(theta)), np.sin(np.radians(theta))
    return np.where(x[:, 2:3] > 0, [c, 0.0, -s], [c, 0.0, s])


def angle_deg(a, b):
    cosine = np.abs(np.einsum("ij,ij->i", a, b)) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
    return np.degrees(np.arccos(np.clip(cosine, 0.0, 1.0)))


def owned(a0):
    n = a0.function_space.dofmap.index_map.size_local
    return a0.function_space.tabulate_dof_coordinates()[:n], a0.x.array.reshape(-1, 3)[:n]


def test_bipennate_block_recovers_the_analytic_pennation():
    g = bipennate(MPI.COMM_SELF)
    result = pennate.compute(g, OUTER, CENTRAL)
    x, a = owned(result.a0)
    error = angle_deg(a, exact_bipennate(x))
    on = np.abs(x[:, 2]) < 1e-12
    # P1 holds the exact potential (linear on each side of the aponeurosis): exact off it
    assert error[~on].max() < 1e-4
    # on the aponeurosis the two sides' fibres meet: the stored one lies between them
    assert angle_deg(a[on], np.tile([1.0, 0, 0], (on.sum(), 1))).max() <= THETA + 1e-9
    assert np.abs(a[on, 1]).max() < 1e-12
    stats = pennate.statistics(result)
    assert abs(stats["pennation_deg_p50"] - THETA) < 1e-6  # the line of action is the x axis
    # every fascicle runs straight from an outer face to the aponeurosis: T / sin θ
    assert stats["fascicles_reached_share"] == 1.0
    for key in ("fascicle_mm_p5", "fascicle_mm_p95", "fascicle_mm_mean"):
        assert stats[key] == pytest.approx(T / np.sin(np.radians(THETA)) / geo.MM, rel=1e-6)  # seeds 1e-6 in
    assert stats["origin_area_mm2"] == pytest.approx(2 * L * W / geo.MM**2, rel=1e-12)
    assert stats["insertion_area_mm2"] == pytest.approx(L * W / geo.MM**2, rel=1e-12)


def test_bipennate_block_mean_error_within_1deg_and_falling_with_the_mesh():
    """Volume-weighted mean over the cells of the angle between the cells' fibre (the mean
    of their nodal ones, as the pictures and statistics take it) and the analytic one: only
    the cells touching the aponeurosis err, a share that halves with each halving of h."""
    errors = []
    for layers in (4, 8, 16):
        g = bipennate(MPI.COMM_SELF, layers)
        result = pennate.compute(g, OUTER, CENTRAL)
        centroid, fiber, volume = fibers.cell_fibers(g, result.a0)
        errors.append(np.average(angle_deg(fiber, exact_bipennate(centroid)), weights=volume))
    assert errors[2] < 1.0
    assert errors[1] / errors[2] == pytest.approx(2.0, rel=0.05)
    assert errors[0] / errors[1] == pytest.approx(2.0, rel=0.05)


@pytest.mark.parametrize("theta", [12.0, 30.0])
def test_sheared_parallelepiped_unipennate_is_exact(theta):
    """Origin the bottom face, insertion the top face, the sides along the fibres: the
    uniform-flux potential is linear, its gradient along the shear at θ to x, whatever θ."""
    cot = 1.0 / np.tan(np.radians(theta))
    thickness = 0.01
    g = tagged_box(MPI.COMM_SELF, (10, 2, 4),
                   lambda xi, eta, zeta: (0.1 * xi + thickness * (zeta + 1) / 2 * cot, 0.02 * eta,
                                          thickness * (zeta + 1) / 2))
    top = thickness / geo.MM
    result = pennate.compute(g, "halfspace:0,0,0.05,0,0,-1", f"halfspace:0,0,{top - 0.05},0,0,1")
    _, a = owned(result.a0)
    d = np.array([np.cos(np.radians(theta)), 0.0, np.sin(np.radians(theta))])
    assert angle_deg(a, np.tile(d, (len(a), 1))).max() < 1e-5  # arccos near 1: ~1e-6° is round-off
    stats = pennate.statistics(result)
    assert stats["fascicle_mm_p50"] == pytest.approx(thickness / np.sin(np.radians(theta)) / geo.MM, rel=1e-6)


def test_generator_tags_the_outer_faces_and_the_central_aponeurosis():
    g = bipennate(MPI.COMM_SELF)
    result = pennate.compute(g, OUTER, CENTRAL)
    facet_tags, cell_tags = result.tags()
    m = g.mesh
    midpoint = m.geometry.x[dmesh.entities_to_geometry(m, 2, facet_tags.indices)].mean(axis=1)
    origin = facet_tags.values == pennate.ORIGIN_TAG
    insertion = facet_tags.values == pennate.INSERTION_TAG
    # 12 × 3 squares on each outer face, two triangles each; the same on the aponeurosis
    assert origin.sum() == 2 * 2 * 12 * 3 and insertion.sum() == 2 * 12 * 3
    assert np.allclose(np.abs(midpoint[origin, 2]), T) and np.allclose(midpoint[insertion, 2], 0.0)
    exterior = set(dmesh.exterior_facet_indices(m.topology))
    assert set(facet_tags.indices[origin]) <= exterior
    assert not set(facet_tags.indices[insertion]) & exterior  # an internal aponeurosis
    # the cells carrying the aponeurosis' section: those above it, one per in-plane facet
    cut = cell_tags.indices[cell_tags.values == pennate.INSERTION_TAG]
    assert len(cut) == 2 * 12 * 3
    assert np.all(m.geometry.x[m.geometry.dofmaps[0][cut]][:, :, 2].min(axis=1) > -1e-12)


@pytest.mark.parametrize("spec, message", [
    ("", "empty patch"),
    ("tags:1 | ", "empty alternative"),
    ("bogus:1", "unknown term"),
    ("plane:0,0,0,0,0", "expected 6 numbers"),
    ("plane:0,0,0,0,0,0", "normal (NX, NY, NZ) is zero"),
    ("halfspace:0,0,nan,0,0,1", "finite"),
    ("along:0.5,0.2", "0 <= A < B <= 1"),
    ("midplane:4", "midplane:2 or midplane:3"),
    ("side:1", "side:K or side:-K"),
    ("tags:1 & plane:0,0,0,1,0,0", "one selector"),
    ("tags:a", "integer tags"),
    ("stl:/no/such.stl", "no such file"),
])
def test_malformed_patches_are_refused(spec, message):
    with pytest.raises(InputError, match=re.escape(message)):
        pennate.parse(spec, "--origin")


@pytest.mark.parametrize("origin, insertion, message", [
    (OUTER, "plane:0,0,500,0,0,1", "does not cut the mesh"),
    ("halfspace:0,0,500,0,0,1", CENTRAL, "selects nothing"),
    ("tags:7", CENTRAL, "selects nothing"),
    ("boundary", "tags:2", "overlap: 48 boundary facets are in both"),
])
def test_bad_patches_on_the_mesh_are_refused(origin, insertion, message):
    with pytest.raises(InputError, match=re.escape(message)):
        pennate.compute(bipennate(MPI.COMM_SELF), origin, insertion)


def test_stl_and_vertex_patches_select_the_same_facets_as_a_halfspace(tmp_path):
    g = bipennate(MPI.COMM_SELF)
    frame = pennate.Frame(g)
    top = pennate.select(frame, pennate.parse(f"halfspace:0,0,{T_MM - 0.1},0,0,1"), "--origin")
    # an STL of two triangles covering the top face (mm), and the top face's node indices
    corners = np.array([[-10, -10, T_MM], [200, -10, T_MM], [200, 50, T_MM], [-10, 50, T_MM]], dtype="<f4")
    record = np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attribute", "<u2")])
    triangles = np.zeros(2, dtype=record)
    triangles["corners"] = [corners[[0, 1, 2]], corners[[0, 2, 3]]]
    stl = tmp_path / "top.stl"
    stl.write_bytes(b"\0" * 80 + np.uint32(2).tobytes() + triangles.tobytes())
    nodes = frame.file_node[np.unique(frame.facet_nodes[top.facets])]
    (tmp_path / "top.txt").write_text(" ".join(map(str, nodes)))
    for spec in (f"stl:{stl},0.5", f"vertices:{tmp_path / 'top.txt'}"):
        assert np.array_equal(pennate.select(frame, pennate.parse(spec), "--origin").facets, top.facets), spec


def write_mesh(path, geometry):
    """The geometry as a mesh file of `runspec.MeshFile` (metres, tags ft_small)."""
    geometry.mesh.name = "Grid"
    with XDMFFile(geometry.comm, str(path), "w") as xdmf:
        xdmf.write_mesh(geometry.mesh)
        geometry.facet_tags.name = "ft_small"
        xdmf.write_meshtags(geometry.facet_tags, geometry.mesh.geometry)


def test_hyper_fibers_writes_the_pennate_file_beside_the_mesh(tmp_path, capsys):
    geometry = bipennate(MPI.COMM_WORLD)
    mesh_file = tmp_path / "block" / "block.xdmf"
    mesh_file.parent.mkdir()
    write_mesh(mesh_file, geometry)
    base = ["--mesh", str(mesh_file), "--mesh-unit", "m", "--method", "pennate", "--quiet"]
    # bad patches: one error line, nothing written
    for bad in (["--origin", "plane:0,0,900,0,0,1", "--insertion", CENTRAL],
                ["--origin", "boundary", "--insertion", "tags:2"],
                ["--origin", OUTER, "--insertion", "along:0.9,0.1"]):
        assert fibers_job.main([*base, *bad]) == 2
        assert not (tmp_path / "block" / fibers.FILE_NAME).exists()
    errors = capsys.readouterr().err.splitlines()
    assert [line.split(":")[0] for line in errors] == ["error"] * 3, errors
    assert "does not cut" in errors[0] and "overlap" in errors[1] and "0 <= A < B <= 1" in errors[2]
    assert fibers_job.main([*base, "--origin", OUTER, "--insertion", CENTRAL]) == 0
    path = tmp_path / "block" / fibers.FILE_NAME
    assert io.is_complete(path) and path.with_suffix(".png").is_file()
    with h5py.File(path, "r") as f:
        assert f.attrs["kind"] == "pennate" and f.attrs["method"] == pennate.METHOD
        assert f.attrs["origin"] == OUTER and f.attrs["insertion"] == CENTRAL
        assert f["origin_facets"].shape == (144, 3) and f["insertion_facets"].shape == (72, 3)
        assert abs(f.attrs["pennation_deg_p50"] - THETA) < 1e-6
    assert fr.stored_fibres(path) == ("pennate", pennate.METHOD)
    loaded = runspec.MeshFile(mesh_file).load(MPI.COMM_WORLD)
    x, a = owned(fibers.load(loaded, path))
    on = np.abs(x[:, 2]) < 1e-12
    assert angle_deg(a[~on], exact_bipennate(x[~on])).max() < 1e-4
    # an existing fibre file is kept without --force
    assert fibers_job.main([*base, "--origin", OUTER, "--insertion", CENTRAL]) == 2
    assert fibers_job.main(["--mesh", str(mesh_file), "--origin", OUTER, "--quiet"]) == 2  # patches need pennate


SMALLEST = "ST_VHM_Right"
SHORT = 'name = "short"\nend = 24.0\n[[session]]\nstart = 10\nduration = 1\nintensity = 1.0\n'


def test_a_run_on_a_mesh_with_pennate_fibres_beside_it_records_them(tmp_path):
    source = geo.MESHES_DIR / geo.GEOMETRIES[SMALLEST]
    folder = tmp_path / "mine"
    folder.mkdir()
    for path in runspec.mesh_files(source):
        shutil.copy(path, folder / path.name)
    mesh = folder / source.name
    assert fibers_job.main(["--mesh", str(mesh), "--method", "pennate", "--quiet"]) == 0
    protocol = tmp_path / "short.toml"
    protocol.write_text(SHORT)
    out = tmp_path / "run.h5"
    assert grow.main(["--mesh", str(mesh), "--mesh-unit", "mm", "--protocol", str(protocol), "--growth-dt", "24",
                      "--output", str(out), "--quiet"]) == 0
    with h5py.File(out, "r") as f:
        assert f.attrs["fibers"] == "pennate"
        assert f.attrs["fibers_method"] == f"{pennate.METHOD}; read from {folder / fibers.FILE_NAME}"


@pytest.mark.mpi
def test_pennate_on_two_ranks_equals_serial():
    """The bipennate block and the shipped TA with the default patches: the nodal fibres
    by file node index, and the statistics, on 2 ranks as on 1."""
    comm = MPI.COMM_WORLD
    assert comm.size == 2
    for make, patches in ((bipennate, (OUTER, CENTRAL)),
                          (lambda c: geo.load("TA_VHF_Left", c), (pennate.DEFAULT_ORIGIN, pennate.DEFAULT_INSERTION))):
        results = [pennate.compute(make(c), *patches) for c in (comm, MPI.COMM_SELF)]
        stats = [pennate.statistics(r) for r in results]
        data = [fibers.gather_nodal(r.a0, r.speed, root=0) for r in results[:1]]
        serial = fibers.gather_nodal(results[1].a0, results[1].speed, root=0)
        if comm.rank == 0:
            assert np.array_equal(data[0]["node"], serial["node"])
            assert np.abs(data[0]["a0"] - serial["a0"]).max() < 1e-9
        for key in ("pennation_deg_mean", "pennation_deg_p50", "fascicle_mm_mean", "fascicle_mm_p50",
                    "origin_area_mm2", "insertion_area_mm2"):
            assert stats[0][key] == pytest.approx(stats[1][key], rel=1e-6, abs=1e-9), key


def test_hyper_mesh_makes_pennate_fibres_which_runs_then_use(tmp_path):
    out = tmp_path / "TA_PEN"
    stl = Path(__file__).parent / "data" / "TA_VHF_Right_coarse.stl"
    assert mesh_job.main([str(stl), "--output", str(out), "--cells", "3000", "--method", "pennate", "--quiet"]) == 0
    record = json.loads((out / "mesh.json").read_text())["pennate"]
    assert record["origin"] == pennate.DEFAULT_ORIGIN and 3.0 < record["pennation_deg_p50"] < 30.0
    assert fr.stored_fibres(out / "fibers.h5")[0] == "pennate"
    mesh = runspec.MeshFile(out / "TA_PEN.xdmf", "mm")
    spec = runspec.RunSpec("TA_PEN", protocols.from_option("mwf")[0], mesh=mesh)
    geometry = mesh.load(MPI.COMM_SELF)
    a0, made = driver.fiber_field(spec, geometry)
    assert made["fibers"] == "pennate"
    assert np.array_equal(a0.x.array, fibers.load(geometry, out / "fibers.h5").x.array)


def test_hyper_mesh_refuses_a_bad_patch_before_meshing(tmp_path, capsys):
    stl = Path(__file__).parent / "data" / "TA_VHF_Right_coarse.stl"
    out = tmp_path / "TA_BAD"
    bad = ["--method", "pennate", "--origin", "plane:0,0"]
    assert mesh_job.main([str(stl), "--output", str(out), *bad, "--quiet"]) == 2
    assert capsys.readouterr().err.count("error:") == 1 and not out.exists()
    assert mesh_job.main([str(stl), "--output", str(out), "--origin", "midplane", "--quiet"]) == 2
    assert "--method pennate" in capsys.readouterr().err and not out.exists()
