"""Geometries: every mesh loads in metres with its tags; fibres; refinement; bad input."""

import dolfinx_solver  # noqa: F401
import numpy as np
import pytest
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh
from dolfinx.io import XDMFFile
from mpi4py import MPI

from hyper.core.params import InputError
from hyper.fem import fibers
from hyper.fem import geometry as geo

# Paper: group means of the baseline volumes (cm³), MODEL.md §5.
PAPER_MEANS = {"BFLH": 252.4, "ST": 190.1, "TA": 132.4}


def _sum(comm, value):
    return comm.allreduce(value, op=MPI.SUM)


def test_identifiers():
    assert list(geo.GEOMETRIES)[:2] == ["idealized", "cylinder"]
    # every id names a mesh file that is there, and every mesh folder shipped is an id
    assert [name for name, file in geo.GEOMETRIES.items() if not (geo.MESHES_DIR / file).is_file()] == []
    folders = {p.parent.name for p in geo.MESHES_DIR.glob("*/*") if p.suffix in (".xdmf", ".msh")}
    assert folders == {(geo.MESHES_DIR / file).parent.name for file in geo.GEOMETRIES.values()}
    assert len(geo.ANATOMICAL) == 12 and len(geo.GEOMETRIES) == 14 + len(geo.MESHED)
    # The 19 shipped meshes of `hyper mesh`: 3 rectus femoris (no VHM right surface), 4 of each other muscle.
    assert len(geo.NEW) == 19 and set(geo.NEW) <= set(geo.MESHED)
    assert {m: sum(n.startswith(m + "_") for n in geo.NEW) for m in geo.NEW_MUSCLES} == {
        "RF": 3, "VL": 4, "VM": 4, "VI": 4, "GM": 4}
    assert geo.split_id("VL_VHM_Right") == ("VL", "VHM", "Right")
    assert geo.split_id("ST_VHM_Right") == ("ST", "VHM", "Right")
    assert {geo.split_id(n)[0] for n in geo.ANATOMICAL} == set(geo.MUSCLES)
    with pytest.raises(InputError, match="not an anatomical geometry"):
        geo.split_id("cylinder")


def test_anatomical_meshes_load_in_metres_with_the_paper_volumes():
    comm = MPI.COMM_WORLD
    volumes = {}
    for name in geo.ANATOMICAL:
        geometry = geo.load(name, comm)
        assert 6707 <= geometry.num_cells() <= 9668
        assert geometry.midsection is None
        total = _sum(comm, fem.assemble_scalar(fem.form(1.0 * geometry.ds)))
        parts = sum(geometry.area(t) for t in (*geometry.ends, geometry.lateral))
        assert parts == pytest.approx(total, rel=1e-12)  # ends + lateral = the whole surface
        volumes[name] = geometry.reference_volume() * 1e6  # cm³
    for muscle, mean in PAPER_MEANS.items():
        ours = np.mean([v for n, v in volumes.items() if n.startswith(muscle + "_")])
        assert ours == pytest.approx(mean, abs=0.05)


@pytest.mark.parametrize(
    ("name", "cells", "volume", "end_area", "mid_area"),
    [
        # the idealized end disks are heptagons of radius 7 mm; the mid disk has radius 25 mm
        ("idealized", 1997, 239.2608, 3.5 * 0.007**2 * np.sin(2 * np.pi / 7), 1.913417e-3),
        ("cylinder", 895, 122.0849, 1.208280e-3, 1.214128e-3),
    ],
)
def test_gmsh_meshes(name, cells, volume, end_area, mid_area):
    comm = MPI.COMM_WORLD
    geometry = geo.load(name, comm)
    assert geometry.num_cells() == cells
    assert (geometry.ends, geometry.lateral, geometry.midsection) == ((1, 2), geo.LATERAL_TAG, 3)
    assert geometry.reference_volume() * 1e6 == pytest.approx(volume, rel=1e-6)
    for tag in geometry.ends:
        assert geometry.area(tag) == pytest.approx(end_area, rel=1e-6)
    assert geometry.area(geometry.midsection) == pytest.approx(mid_area, rel=1e-6)
    total = _sum(comm, fem.assemble_scalar(fem.form(1.0 * geometry.ds)))
    assert sum(geometry.area(t) for t in (1, 2, geo.LATERAL_TAG)) == pytest.approx(total, rel=1e-12)
    assert geometry.ds.metadata() == {"quadrature_degree": 4}


def _refinement(comm):
    geometry = geo.load("idealized", comm)
    fine = geo.refine(geometry)
    assert fine.num_cells() == 8 * geometry.num_cells()
    assert fine.reference_volume() == pytest.approx(geometry.reference_volume(), rel=1e-12)
    for tag in (1, 2, 3, 4):
        assert fine.area(tag) == pytest.approx(geometry.area(tag), rel=1e-12)


def test_refinement_keeps_volume_and_tagged_areas():
    _refinement(MPI.COMM_WORLD)


@pytest.mark.mpi
def test_refinement_keeps_volume_and_tagged_areas_in_parallel():
    _refinement(MPI.COMM_WORLD)


def _nodal(a0):
    n = a0.function_space.dofmap.index_map.size_local
    x = a0.function_space.tabulate_dof_coordinates()[:n]
    return x, a0.x.array.reshape(-1, 3)[:n]


def test_fibres():
    comm = MPI.COMM_WORLD
    idealized = geo.load("idealized", comm)
    x, a = _nodal(fibers.fiber_field(idealized))
    assert np.allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-14)
    assert np.allclose(a, fibers.idealized_fiber(x.T).T, atol=1e-14)
    # MODEL.md §5 by hand at (r, 0, z): slope y'(0.05) = 0.045, y'(0.15) = -0.045
    for z, slope in [(0.05, 0.06 - 6 * 0.05**2), (0.15, 6 * 0.15**2 - 2.4 * 0.15 + 0.18), (0.1, 0.0)]:
        expected = np.array([slope, 0.0, 0.2]) / np.hypot(slope, 0.2)
        assert np.allclose(fibers.idealized_fiber(np.array([[0.01], [0.0], [z]]))[:, 0], expected)
    assert np.allclose(fibers.idealized_fiber(np.array([[0.0], [0.0], [0.03]]))[:, 0], [0, 0, 1])

    _, a = _nodal(fibers.fiber_field(geo.load("cylinder", comm)))
    assert np.allclose(a, [0, 0, 1])

    ta = geo.load("TA_VHF_Left", comm)
    _, a = _nodal(fibers.fiber_field(ta, "principal"))
    _, axes = geo.principal_axes(ta.mesh)
    assert np.allclose(np.abs(a @ axes[:, 0]), 1.0)
    along = (geo.facet_centroid(ta, 2) - geo.facet_centroid(ta, 1)) @ a[0] if len(a) else 1.0
    assert along > 0  # from end 1 towards end 2
    with pytest.raises(InputError, match="unknown fibre kind"):
        fibers.fiber_field(ta, "helical")
    # anatomical meshes default to their stored Stokes-flow fibres
    _, stokes = _nodal(fibers.fiber_field(ta))
    assert np.allclose(np.linalg.norm(stokes, axis=1), 1.0, atol=1e-12)
    assert not np.allclose(np.abs(stokes @ axes[:, 0]), 1.0)


def test_principal_axis_of_cylinder_is_its_axis():
    centre, axes = geo.principal_axes(geo.load("cylinder", MPI.COMM_WORLD).mesh)
    assert abs(axes[2, 0]) > 0.9999
    assert centre[2] == pytest.approx(0.05, abs=1e-3)


# ---- bad input (serial: the files live in a per-process temporary folder)


def test_unknown_name_lists_the_known_ones():
    with pytest.raises(InputError, match="unknown geometry 'BFLH'; known: idealized, cylinder, BFLH_VHF_Left"):
        geo.load("BFLH", MPI.COMM_SELF)


def test_missing_files(tmp_path):
    with pytest.raises(InputError, match="muscle-idealized.msh: no such mesh file"):
        geo.load("idealized", MPI.COMM_SELF, meshes_dir=tmp_path)
    with pytest.raises(InputError, match="TibialisAnterior_smooth.xdmf: no such mesh file"):
        geo.load("TA_VHM_Left", MPI.COMM_SELF, meshes_dir=tmp_path)


def test_unreadable_files(tmp_path):
    bad = tmp_path / "bad.xdmf"
    bad.write_text("this is not XDMF")
    with pytest.raises(InputError, match="bad.xdmf: cannot read a mesh 'Grid' with facet tags 'ft_small'"):
        geo.load_file(bad, MPI.COMM_SELF)
    msh = tmp_path / "muscle-cylinder" / "muscle-cylinder.msh"
    msh.parent.mkdir()
    msh.write_text("$MeshFormat\ngarbage\n")
    with pytest.raises(InputError, match="muscle-cylinder.msh: cannot read as a Gmsh mesh"):
        geo.load("cylinder", MPI.COMM_SELF, meshes_dir=tmp_path)


def _write_box(path, tag_values):
    comm = MPI.COMM_SELF
    mesh = dmesh.create_unit_cube(comm, 2, 2, 2, dmesh.CellType.tetrahedron)
    mesh.name = "Grid"
    mesh.topology.create_connectivity(2, 3)
    facets = dmesh.exterior_facet_indices(mesh.topology)
    z = dmesh.compute_midpoints(mesh, 2, facets)[:, 2]
    values = np.where(np.isclose(z, 0), tag_values[0], np.where(np.isclose(z, 1), tag_values[1], tag_values[2]))
    tags = dmesh.meshtags(mesh, 2, facets, values.astype(np.int32))
    tags.name = "ft_small"
    with XDMFFile(comm, str(path), "w") as xdmf:
        xdmf.write_mesh(mesh)
        xdmf.write_meshtags(tags, mesh.geometry)


def test_user_mesh_and_missing_tags(tmp_path):
    good = tmp_path / "good.xdmf"
    _write_box(good, (1, 2, 3))
    geometry = geo.load_file(good, MPI.COMM_SELF, scale=1e-3)
    assert geometry.reference_volume() == pytest.approx(1e-9, rel=1e-12)  # 1 mm³
    assert geometry.name == "good"

    missing_end = tmp_path / "missing_end.xdmf"
    _write_box(missing_end, (1, 3, 3))
    with pytest.raises(InputError,
                       match=r"missing_end.xdmf: facet tag 2 \(end\) is missing; the file has tags \[1, 3\]"):
        geo.load_file(missing_end, MPI.COMM_SELF)
    with pytest.raises(InputError, match=r"facet tag 7 \(midsection\) is missing"):
        geo.load_file(good, MPI.COMM_SELF, midsection=7)
    with pytest.raises(InputError, match="cannot read a mesh 'Grid' with facet tags 'ft'"):
        geo.load_file(good, MPI.COMM_SELF, tags="ft")


def test_measures_carry_the_quadrature_degree():
    geometry = geo.load("cylinder", MPI.COMM_WORLD, quadrature_degree=2)
    for measure in (geometry.dx, geometry.ds, geometry.dS):
        assert measure.metadata() == {"quadrature_degree": 2}
    assert isinstance(geometry.dS(geometry.midsection), ufl.Measure)


def test_idealized_xdmf_end_tags_add_the_lateral_band():
    """ends="tags": the XDMF's 64 facets per end (7 disk facets and 57 of the side) on the
    same mesh; the midsection stays, and the side loses the band (MODEL.md §9)."""
    disks = geo.load("idealized", MPI.COMM_WORLD)
    tags = geo.load("idealized", MPI.COMM_WORLD, ends="tags")
    assert tags.num_cells() == disks.num_cells() == 1997
    assert disks.area(1) == pytest.approx(1.3408e-4, rel=1e-4)
    assert tags.area(1) == pytest.approx(1.2026e-3, rel=1e-4)
    for shape in (disks, tags):
        total = shape.area(1) + shape.area(2) + shape.area(shape.lateral)
        assert total == pytest.approx(disks.area(1) + disks.area(2) + disks.area(disks.lateral), rel=1e-12)
    assert tags.area(3) == pytest.approx(disks.area(3), rel=1e-12)
    counts = [MPI.COMM_WORLD.allreduce(int(np.count_nonzero(tags.facet_tags.values[
        tags.facet_tags.indices < tags.mesh.topology.index_map(2).size_local] == t)), op=MPI.SUM) for t in (1, 2)]
    assert counts == [64, 64]
    with pytest.raises(InputError, match="idealized shape only"):
        geo.load("cylinder", MPI.COMM_WORLD, ends="tags")
