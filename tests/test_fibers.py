"""Stokes-flow fibres: the straight cylinder, unit length, storage and exact read-back on
any number of ranks, and the CLI."""

import shutil

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import h5py
import numpy as np
import pytest
from mpi4py import MPI

from hyper.commands import fibers as fibers_job
from hyper.core.io import is_complete, write_series
from hyper.core.params import InputError
from hyper.fem import fibers
from hyper.fem import geometry as geo

STORED = "ST_VHM_Right"  # the smallest anatomical mesh (6707 cells)


def by_node(a0):
    """{file node index: nodal value} for this rank's owned nodes, gathered on every rank."""
    n = a0.function_space.dofmap.index_map.size_local
    keys = fibers.node_index(a0.function_space)[:n]
    values = a0.x.array.reshape(-1, 3)[:n]
    parts = a0.function_space.mesh.comm.allgather((keys, values))
    keys, values = (np.concatenate(p) for p in zip(*parts))
    order = np.argsort(keys)
    return keys[order], values[order]


@pytest.fixture(scope="module")
def cylinder_fibers():
    geometry = geo.load("cylinder", MPI.COMM_WORLD)
    a0, speed = fibers.compute(geometry)
    return geometry, a0, speed


def test_straight_cylinder_flows_along_its_axis(cylinder_fibers):
    """On a straight cylinder the exact flow is uniform along the axis; the faceted mesh
    bends it by at most ~1° (with vertex normals in the slip condition)."""
    geometry, a0, speed = cylinder_fibers
    axis = fibers.principal_axis(geometry)
    assert abs(abs(axis[2]) - 1.0) < 1e-4  # the coarse mesh's principal axis is within 1° of z
    assert fibers.aligned_share(geometry, a0, [0, 0, 1], angle_deg=2.0) > 0.999
    assert fibers.aligned_share(geometry, a0, [0, 0, 1], angle_deg=1.0) > 0.9
    stats = fibers.statistics(geometry, a0, speed)
    assert stats["share_within_30deg"] == 1.0
    assert 0.97 < stats["min_speed"] <= stats["max_speed"] < 1.03  # plug flow at the inflow speed
    assert stats["max_norm_error"] < 1e-12
    # From end 1 (z = 0) to end 2 (z = 0.1): the flow goes up everywhere.
    assert a0.x.array.reshape(-1, 3)[:, 2].min() > 0.99


def test_flux_in_equals_flux_out(cylinder_fibers):
    """Mass balance of the discrete flow: what enters through end 1 leaves through end 2."""
    import ufl
    from dolfinx import fem

    geometry, a0, speed = cylinder_fibers
    u = fem.Function(a0.function_space)
    u.x.array[:] = (a0.x.array.reshape(-1, 3) * speed.x.array[:, None]).ravel()
    n = ufl.FacetNormal(geometry.mesh)
    flux = [geometry.comm.allreduce(fem.assemble_scalar(fem.form(ufl.dot(u, n) * geometry.ds(t))), op=MPI.SUM)
            for t in geometry.ends]
    area = geometry.area(geometry.ends[0])
    assert abs(flux[0] + area) < 0.01 * area and abs(flux[1] - area) < 0.01 * area


def test_store_and_load_roundtrip(cylinder_fibers, tmp_path):
    geometry, a0, speed = cylinder_fibers
    comm = geometry.comm
    path = comm.bcast(str(tmp_path / "fibers.h5"), root=0)
    data = fibers.gather_nodal(a0, speed)
    if comm.rank == 0:
        assert np.array_equal(data["node"], np.arange(geometry.mesh.topology.index_map(0).size_global))
        write_series(path, data, attrs={"geometry": "cylinder"})
    comm.barrier()
    back = fibers.load(geometry, path)
    assert np.array_equal(back.x.array, a0.x.array)  # ghosts included
    assert fibers.max_norm_error(back) < 1e-12


def test_load_refuses_another_mesh(cylinder_fibers, tmp_path):
    geometry, a0, speed = cylinder_fibers
    comm = geometry.comm
    path = comm.bcast(str(tmp_path / "moved.h5"), root=0)
    data = fibers.gather_nodal(a0, speed)
    if comm.rank == 0:
        data["x"] = data["x"] + 1e-6  # the same node numbers, moved nodes
        write_series(path, data)
    comm.barrier()
    with pytest.raises(InputError, match="another mesh"):
        fibers.load(geometry, path)
    with pytest.raises(InputError, match="no complete fibre file"):
        fibers.load(geometry, comm.bcast(str(tmp_path / "missing.h5"), root=0))


def test_stored_anatomical_fibres_are_unit_and_complete():
    """The committed files of one anatomical mesh: complete, their provenance, unit fibres;
    its own (fibers.h5) the Laplace fibres, the paper's Stokes fibres beside them."""
    path = fibers.fiber_path(STORED, kind="stokes")
    assert path.name == fibers.STOKES_FILE_NAME and is_complete(path)
    assert fibers.stored_kind(fibers.fiber_path(STORED)) == "laplace" and fibers.stored_kind(path) == "stokes"
    with h5py.File(path, "r") as f:
        assert f.attrs["geometry"] == STORED and "Stokes" in f.attrs["method"]
        assert f["parameters"].attrs["penalty"] == fibers.StokesParams().penalty
        stored = f["a0"][()]
    assert np.abs(np.linalg.norm(stored, axis=1) - 1.0).max() < 1e-12
    geometry = geo.load(STORED, MPI.COMM_WORLD)
    a0 = fibers.load(geometry)  # the Stokes fibres by default
    assert np.array_equal(a0.x.array, fibers.fiber_field(geometry, "stokes").x.array)
    assert fibers.max_norm_error(a0) < 1e-12
    assert fibers.aligned_share(geometry, a0, fibers.principal_axis(geometry)) > 0.95
    with pytest.raises(InputError, match="holds stokes fibres, not laplace"):
        fibers.fiber_field(geometry, "laplace", path)


@pytest.mark.mpi
def test_load_on_two_ranks_equals_serial():
    comm = MPI.COMM_WORLD
    assert comm.size == 2
    parallel = fibers.load(geo.load(STORED, comm))
    serial = fibers.load(geo.load(STORED, MPI.COMM_SELF))
    keys_p, values_p = by_node(parallel)
    keys_s, values_s = by_node(serial)
    assert np.array_equal(keys_p, keys_s)
    assert np.array_equal(values_p, values_s)  # bitwise, node by node
    # ... ghosts too: every local node of the partitioned mesh has the serial value.
    local = fibers.node_index(parallel.function_space)
    assert np.array_equal(parallel.x.array.reshape(-1, 3), values_s[np.searchsorted(keys_s, local)])


@pytest.mark.mpi
def test_solve_on_two_ranks_matches_the_stored_serial_fibres():
    """The solver partitioned over 2 ranks (vertex normals summed across the cut, MUMPS in
    parallel) reproduces the fibres computed on 1 rank, node by node."""
    comm = MPI.COMM_WORLD
    geometry = geo.load(STORED, comm)
    a0, _ = fibers.compute(geometry)
    keys, values = by_node(a0)
    stored_keys, stored = by_node(fibers.load(geometry))
    assert np.array_equal(keys, stored_keys)
    assert np.abs(values - stored).max() < 1e-6  # LU round-off, amplified by the conditioning


def test_cli_computes_skips_and_recomputes(tmp_path):
    comm = MPI.COMM_WORLD
    root = comm.bcast(tmp_path, root=0)
    meshes, out = root / "meshes", root / "out"
    if comm.rank == 0:
        shutil.copytree(geo.MESHES_DIR / "muscle-cylinder", meshes / "muscle-cylinder")
    comm.barrier()
    argv = ["--geometries", "cylinder", "--meshes-dir", str(meshes), "--output", str(out)]
    assert fibers_job.main(argv) == 0
    path = meshes / "muscle-cylinder" / fibers.FILE_NAME
    assert is_complete(path) and (out / "cylinder.png").is_file()
    lines = (out / "summary.csv").read_text().splitlines()
    assert lines[0].split(",") == list(fibers_job.SUMMARY_COLUMNS)
    assert lines[1].startswith("cylinder,,,,895,272,1.0,") and lines[1].endswith(",done")
    stamp = path.stat().st_mtime_ns
    assert fibers_job.main(argv) == 0  # nothing to do: the file and the picture exist
    assert path.stat().st_mtime_ns == stamp
    assert (out / "summary.csv").read_text().splitlines()[1].endswith(",skipped")
    assert fibers_job.main(argv + ["--force"]) == 0
    assert path.stat().st_mtime_ns != stamp


def test_cli_rejects_unknown_geometry(tmp_path, capsys):
    assert fibers_job.main(["--geometries", "BFLH_nobody", "--output", str(tmp_path)]) == 2
    assert "unknown BFLH_nobody" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_params_are_validated():
    with pytest.raises(InputError, match="penalty"):
        fibers.StokesParams(penalty=0.0)
    with pytest.raises(InputError, match="quadrature_degree"):
        fibers.StokesParams(quadrature_degree=2.5)


@pytest.mark.mpi
def test_straight_cylinder_on_two_ranks(tmp_path):
    """The cylinder checks and the store/load round trip with the mesh cut in two."""
    comm = MPI.COMM_WORLD
    geometry = geo.load("cylinder", comm)
    a0, speed = fibers.compute(geometry)
    test_straight_cylinder_flows_along_its_axis((geometry, a0, speed))
    test_flux_in_equals_flux_out((geometry, a0, speed))
    test_store_and_load_roundtrip((geometry, a0, speed), tmp_path)


def test_original_idealized_fibres_are_p2_unit_at_the_nodes_and_axial_near_the_axis():
    g = geo.load("idealized", MPI.COMM_WORLD)
    a0 = fibers.fiber_field(g, "original")
    assert a0.function_space.ufl_element().degree == 2
    values = a0.x.array.reshape(-1, 3)
    np.testing.assert_allclose(np.linalg.norm(values, axis=1), 1.0, rtol=1e-14)
    # points at r = 1e-5, 5e-5 m are axial; at r = 2e-4 m the formula's radial part (y'(0.05) = 0.045) shows
    near = np.array([[1e-5, 5e-5, 2e-4], [0.0, 0.0, 0.0], [0.05, 0.05, 0.05]])
    a = fibers.original_idealized_fiber(near)
    np.testing.assert_array_equal(a[:, :2], [[0, 0], [0, 0], [1, 1]])
    assert a[0, 2] == pytest.approx(0.045 / np.hypot(0.045, 0.2), rel=1e-12)
    with pytest.raises(InputError, match="fibres are those of the idealized shape"):
        fibers.fiber_field(geo.load("cylinder", MPI.COMM_WORLD), "original")


def test_the_smoothing_damps_a_ripple_by_the_filter_s_factor():
    """`fibers.smoothed` solves w - l² Δw = u with zero normal gradient: a ripple cos(kx) of
    u (whose normal derivative vanishes on the box's faces) is damped by 1 / (1 + l² k²)
    exactly in the continuum (0.717 here); P1 on 24 cells a wavelength gets it within 3 % (2.3 %)."""
    from dolfinx import fem as dfem
    from dolfinx import mesh as dmesh

    k, ell, eps = 2 * np.pi, 0.1, 0.2
    box = dmesh.create_box(MPI.COMM_WORLD, [[0, 0, 0], [1, 0.25, 0.25]], [24, 4, 4])
    space = dfem.functionspace(box, ("Lagrange", 1, (3,)))
    u = dfem.Function(space)
    u.interpolate(lambda x: np.vstack([eps * np.cos(k * x[0]), np.zeros_like(x[0]), np.ones_like(x[0])]))
    w = fibers.smoothed(u, space, ell)
    n = space.dofmap.index_map.size_local
    x = space.tabulate_dof_coordinates()[:n]
    values = w.x.array.reshape(-1, 3)[:n]
    np.testing.assert_allclose(values[:, 2], 1.0, atol=1e-9)  # the mean flow is untouched
    expected = eps * np.cos(k * x[:, 0]) / (1 + (ell * k) ** 2)
    assert np.abs(values[:, 0] - expected).max() < 0.03 * eps / (1 + (ell * k) ** 2)
