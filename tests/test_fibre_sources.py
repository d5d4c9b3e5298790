"""Where a run's fibres come from (issue 32, items 5 and 6): a refined mesh's fibres are
the unrefined ones carried over, or the formula on the refined mesh; a mesh file's fibre
file is used, a mesh without one gets its Stokes fibres computed (and kept beside it),
an asked kind is honoured; every result records the kind, the method and the file's
SHA-256. The runs are a day long (one session, two growth steps) on the smallest mesh."""

from __future__ import annotations

import re
import shutil

import h5py
import numpy as np
import pytest
from mpi4py import MPI
from scipy.spatial import cKDTree

from hyper.commands import grow
from hyper.commands import inspect as inspect_job
from hyper.core import io
from hyper.fem import fibers, laplace
from hyper.fem import geometry as geo
from hyper.model import protocols
from hyper.runs import checkpoint as ckpt
from hyper.runs import driver, runspec

SMALLEST = "ST_VHM_Right"  # the smallest anatomical mesh (6707 cells)
SHORT = 'name = "short"\nend = 24.0\n[[session]]\nstart = 10\nduration = 1\nintensity = 1.0\n'
MESH = geo.MESHES_DIR / geo.GEOMETRIES[SMALLEST]


def nodal(a0):
    """(coordinates, values) of the owned nodes of a P1 vector field."""
    n = a0.function_space.dofmap.index_map.size_local
    return a0.function_space.tabulate_dof_coordinates()[:n], a0.x.array.reshape(-1, 3)[:n]


def shared(coarse, fine):
    """Indices (coarse, fine) of the nodes both meshes have (serial)."""
    distance, where = cKDTree(fine).query(coarse)
    assert distance.max() < 1e-12  # every coarse node is a node of the refined mesh
    return where


def test_refined_fibres_are_the_formula_or_the_unrefined_ones_at_shared_nodes():
    comm = MPI.COMM_SELF
    idealized = geo.refine(geo.load("idealized", comm))
    x, a = nodal(fibers.fiber_field(idealized))
    assert np.allclose(a, fibers.idealized_fiber(x.T).T, atol=1e-14)  # the formula at the refined nodes
    assert "interpolated onto" not in fibers.method(idealized, "auto")

    cylinder = geo.load("cylinder", comm)
    axis = nodal(fibers.fiber_field(cylinder, "principal"))[1][0]
    twice = geo.refine(geo.refine(cylinder))
    _, a = nodal(fibers.fiber_field(twice, "principal"))
    assert np.abs(a - axis).max() < 1e-12  # the loaded mesh's axis, not the refined vertices'
    assert "2 uniform refinement(s)" in fibers.method(twice, "principal")

    muscle = geo.load(SMALLEST, comm)
    xc, ac = nodal(fibers.fiber_field(muscle))
    assert fibers.resolved(muscle, "auto") == "laplace"  # what the shipped fibre file holds
    fine = geo.refine(muscle)
    xf, af = nodal(fibers.fiber_field(fine))  # auto: the stored fibres, carried over
    where = shared(xc, xf)
    assert np.abs(af[where] - ac).max() < 1e-12
    assert np.abs(np.linalg.norm(af, axis=1) - 1).max() < 1e-12  # unit at every node, midpoints too
    assert fine.refinements == 1 and fine.base is muscle


def argv(tmp_path, name, *options):
    protocol = tmp_path / "short.toml"
    protocol.write_text(SHORT)
    return ["--protocol", str(protocol), "--growth-dt", "24", "--output", str(tmp_path / f"{name}.h5"), *options]


def run(tmp_path, name, *options):
    """A day of growth; (series, attributes) of its result."""
    assert grow.main([*argv(tmp_path, name, *options), "--quiet"]) == 0
    out = tmp_path / f"{name}.h5"
    with h5py.File(out, "r") as f:
        return io.read_series(out), dict(f.attrs)


def copied(tmp_path) -> runspec.MeshFile:
    """The smallest mesh's files in a folder of its own, without its fibres."""
    folder = tmp_path / "mine"
    folder.mkdir()
    for path in runspec.mesh_files(MESH):
        shutil.copy(path, folder / path.name)
    return runspec.MeshFile(folder / MESH.name, "mm")


def same_series(a, b):
    assert set(a) == set(b)
    for name in a:
        if name != "wall_s":
            assert np.array_equal(a[name], b[name]), name


def test_a_mesh_file_with_its_fibres_beside_it_runs_as_its_geometry_bit_for_bit(tmp_path):
    built_in, attrs = run(tmp_path, "geometry", "--geometry", SMALLEST)
    mine, mesh_attrs = run(tmp_path, "mesh", "--mesh", str(MESH), "--mesh-unit", "mm")
    same_series(built_in, mine)
    stored = fibers.fiber_path(SMALLEST)
    for a in (attrs, mesh_attrs):  # the shipped meshes' own fibres: Laplace
        assert a["fibers"] == "laplace" and a["fibers_sha256"] == ckpt.file_digest(stored)
        assert a["fibers_method"] == f"{laplace.method()}; read from {stored}"
        assert a["refine"] == 0
    lines = inspect_job.describe(tmp_path / "mesh.h5")
    assert f"fibres: laplace, {laplace.method()}; read from {stored}; file SHA-256 {attrs['fibers_sha256']}" in lines


def test_a_mesh_without_fibres_gets_its_stokes_fibres_kept_beside_it(tmp_path):
    mesh = copied(tmp_path)
    series, attrs = run(tmp_path, "mine", "--mesh", str(mesh.path), "--mesh-unit", "mm")
    assert io.is_complete(mesh.fibres)
    assert attrs["fibers"] == "stokes" and attrs["fibers_sha256"] == ckpt.file_digest(mesh.fibres)
    # computed before the run and kept, then read as any fibre file is
    assert attrs["fibers_method"] == f"{fibers.METHOD}; read from {mesh.fibres}"
    with h5py.File(mesh.fibres, "r") as f:
        assert f.attrs["mesh"] == str(mesh.path) and f.attrs["method"] == fibers.METHOD
    # the digest names the kept file: the same command again finds its result current
    again = grow.plan(MPI.COMM_WORLD, argv(tmp_path, "mine", "--mesh", str(mesh.path), "--mesh-unit", "mm"))
    assert again.outputs[0].is_current(again.specs[0].digest())
    # the same method as the shipped Stokes file's: the same fibres, to round-off
    with h5py.File(mesh.fibres, "r") as mine, h5py.File(fibers.fiber_path(SMALLEST, kind="stokes"), "r") as shipped:
        assert np.array_equal(mine["node"][()], shipped["node"][()])
        assert np.abs(mine["a0"][()] - shipped["a0"][()]).max() < 1e-6


def test_fibers_principal_is_honoured_and_recorded(tmp_path):
    mesh = copied(tmp_path)
    _, attrs = run(tmp_path, "principal", "--mesh", str(mesh.path), "--mesh-unit", "mm", "--fibers", "principal")
    assert attrs["fibers"] == "principal" and attrs["fibers_sha256"] == ""
    assert attrs["fibers_method"] == fibers.METHODS["principal"]
    assert not mesh.fibres.exists()  # no Stokes fibres asked, none computed


def test_fibres_are_never_kept_in_a_shipped_or_unwritable_folder(tmp_path, monkeypatch):
    assert runspec.MeshFile(MESH, "mm").fibre_cache() == (None, "a shipped mesh folder, which runs never write")
    mesh = copied(tmp_path)
    assert mesh.fibre_cache() == (mesh.fibres, "")
    monkeypatch.setattr(runspec.os, "access", lambda path, mode: False)
    assert mesh.fibre_cache() == (None, "its folder is not writable")
    a0, path, how = driver.mesh_stokes_fibres(MPI.COMM_WORLD, mesh)
    assert path is None and how == "computed for this run (not kept: its folder is not writable)"
    assert not mesh.fibres.exists()
    assert runspec.RunSpec(mesh.path.stem, protocols.named("mwf"), mesh=mesh).mesh_fibres() == "computed"


def test_grow_refine_runs_the_refined_mesh_and_records_it(tmp_path):
    _, coarse = run(tmp_path, "coarse", "--geometry", "cylinder")
    _, fine = run(tmp_path, "fine", "--geometry", "cylinder", "--refine", "1")
    assert (coarse["refine"], fine["refine"]) == (0, 1) and fine["unknowns"] > 6 * coarse["unknowns"]
    assert fine["fibers"] == "axial" and fine["run_digest"] != coarse["run_digest"]
    assert "refine = 1" in fine["study"]


@pytest.mark.parametrize("options, message", [
    (["--geometry", "cylinder", "--fibers", "principal"], r"--fibers principal applies to a --mesh file"),
    (["--mesh", str(MESH), "--mesh-unit", "mm", "--fibers", "original"],
     r"--fibers original: a --mesh file's fibres are one of auto, stokes, axial, principal"),
])
def test_fibre_kinds_that_do_not_apply_are_refused(tmp_path, capsys, options, message):
    out = tmp_path / "out"
    assert grow.main(["--protocol", "mwf", "--output", str(out), *options]) == 2
    err = capsys.readouterr().err
    assert re.search(message, err), err
    assert not out.exists()


def test_study_cohort_and_contraction_take_refine_alike(tmp_path):
    """[numerics] refine (or --refine) reaches every run of a study; cohort and
    contraction record the refinements of their runs."""
    from hyper.analysis import study
    from hyper.commands import cohort as cohort_job
    from hyper.commands import contraction as contraction_job
    from hyper.commands import study as study_job

    path = tmp_path / "s.toml"
    path.write_text('geometries = ["cylinder"]\nprotocols = ["mwf"]\n[numerics]\nrefine = 1\n')
    loaded = study.load(path)
    settings, choice = study.steps(loaded)
    spec = study.first_spec(loaded, settings, choice)
    assert spec.refine == 1 and spec.describe()["refine"] == 1
    overridden = study_job.from_args(study_job.parser().parse_args([str(path), "--refine", "2"]))
    assert overridden.numerics.refine == 2

    protocol = tmp_path / "short.toml"
    protocol.write_text(SHORT)
    out = tmp_path / "cohort"
    assert cohort_job.main(["--geometries", "cylinder", "--protocols", str(protocol), "--growth-dt", "24",
                            "--refine", "1", "--output", str(out), "--quiet"]) == 0
    with h5py.File(out / "runs" / "cylinder_short.h5", "r") as f:
        assert f.attrs["refine"] == 1 and f.attrs["fibers"] == "axial"

    c = tmp_path / "c.h5"
    assert contraction_job.main(["--geometry", "cylinder", "--steps", "1", "--refine", "1", "--output", str(c)]) == 0
    with h5py.File(c, "r") as f:
        assert f.attrs["refine"] == 1 and f.attrs["fibers"] == "axial" and f.attrs["fibers_sha256"] == ""
        assert f.attrs["cells"] == 8 * geo.load("cylinder", MPI.COMM_SELF).num_cells()


def test_fibers_stokes_on_a_mesh_file_reads_or_makes_its_stokes_fibres_not_its_own(tmp_path):
    """A shipped mesh given as a file runs its Stokes fibres as its geometry does; a mesh
    whose own fibres are Laplace fibres gets Stokes fibres computed and kept beside them."""
    built_in, attrs = run(tmp_path, "geometry", "--geometry", SMALLEST, "--fibers", "stokes")
    mine, mesh_attrs = run(tmp_path, "mesh", "--mesh", str(MESH), "--mesh-unit", "mm", "--fibers", "stokes")
    same_series(built_in, mine)
    stokes = fibers.fiber_path(SMALLEST, kind="stokes")
    for a in (attrs, mesh_attrs):
        assert a["fibers"] == "stokes" and a["fibers_sha256"] == ckpt.file_digest(stokes)
    mesh = copied(tmp_path)  # no fibre file: give it Laplace fibres as its own
    shutil.copy(fibers.fiber_path(SMALLEST), mesh.fibres)
    own = mesh.fibres.read_bytes()
    _, attrs = run(tmp_path, "mine", "--mesh", str(mesh.path), "--mesh-unit", "mm", "--fibers", "stokes")
    kept = mesh.fibres.parent / fibers.STOKES_FILE_NAME
    assert attrs["fibers"] == "stokes" and attrs["fibers_sha256"] == ckpt.file_digest(kept)
    assert mesh.fibres.read_bytes() == own  # its own fibres stay as they were
    _, attrs = run(tmp_path, "mine_auto", "--mesh", str(mesh.path), "--mesh-unit", "mm")
    assert attrs["fibers"] == "laplace" and attrs["fibers_sha256"] == ckpt.file_digest(mesh.fibres)
