"""Laplace fibres (the potential flow between the ends): exact where the flow is known, at
their observed order on a bent tube, the same on two ranks as on one, written by `hyper
mesh --method laplace` and `hyper fibers --method laplace` and recorded by the runs that
read them."""

import json
import shutil
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import h5py
import numpy as np
import pytest
from dolfinx import mesh as dmesh
from mpi4py import MPI

from hyper.commands import fibers as fibers_job
from hyper.commands import grow
from hyper.commands import mesh as mesh_job
from hyper.commands.bench import convergence
from hyper.core import io
from hyper.core.params import InputError
from hyper.fem import fiberread as fr
from hyper.fem import fibers, laplace
from hyper.fem import geometry as geo
from hyper.runs import checkpoint as ckpt
from hyper.runs import fidelity, runspec
from test_convergence import SWEEP, sector

STL = Path(__file__).parent / "data" / "TA_VHF_Right_coarse.stl"


def prism(comm) -> geo.Geometry:
    """A box of 2 × 3 × 4 cm, skewed in x: inflow (1) at z = 0, outflow (2) at z = 4 cm."""
    mesh = dmesh.create_box(comm, [[0, 0, 0], [0.02, 0.03, 0.04]], [3, 3, 5], dmesh.CellType.tetrahedron)
    mesh.topology.create_connectivity(2, 3)
    facets = dmesh.exterior_facet_indices(mesh.topology)
    z = dmesh.compute_midpoints(mesh, 2, facets)[:, 2]
    values = np.where(np.isclose(z, 0.0), 1, np.where(np.isclose(z, 0.04), 2, 3)).astype(np.int32)
    return geo.Geometry("prism", mesh, dmesh.meshtags(mesh, 2, facets, values), ends=(1, 2), lateral=3)


def test_a_straight_prism_gives_its_axis_exactly():
    """φ = z meets every condition of a prism along z: P1 and P2 hold it exactly, so the
    fibres are e_z and the speed the inflow speed 1. (A tetrahedral cylinder's lateral
    chords are not vertical: there the fibres tilt by up to 2°, as the Stokes fibres do.)"""
    geometry = prism(MPI.COMM_WORLD)
    for degree in (1, 2):
        a0, speed = laplace.compute(geometry, laplace.LaplaceParams(degree=degree))
        assert np.abs(a0.x.array.reshape(-1, 3) - [0.0, 0.0, 1.0]).max() < 1e-9
        assert np.abs(speed.x.array - 1.0).max() < 1e-9


def angle_to_exact(n: int, degree: int = 2) -> tuple[float, float]:
    """(mean, largest) angle (°) between the fibres on the bent tube and e_θ: with flux
    density 1/ρ on both ends, φ = θ is the exact potential (harmonic, ∇φ = e_θ/ρ tangent to
    the walls)."""
    geometry = sector(n, MPI.COMM_WORLD)
    a0, _ = laplace.compute(geometry, laplace.LaplaceParams(degree=degree, smoothing_m=0.0),
                            inflow_speed=lambda x: 1.0 / np.hypot(x[0], x[1]))
    exact = a0.copy()
    exact.interpolate(lambda x: np.vstack([-x[1], x[0], 0 * x[2]]) / np.hypot(x[0], x[1]))
    got = convergence.angles(a0, exact)
    return got["mean_deg"], got["max_deg"]


def test_fibres_on_a_bent_tube_converge_at_their_observed_order():
    errors = np.array([angle_to_exact(n) for n in (2, 4, 8)])
    orders = np.log2(errors[:-1] / errors[1:])
    # measured: mean 2.31°, 0.564°, 0.129° (orders 2.03, 2.12: the chords' O(h²)), largest
    # 6.98°, 3.40°, 1.68° (order 1: at the rims, where the flux jumps); the Stokes fibres on
    # the same meshes: mean 5.31°, 1.45°, 0.371° (test_convergence)
    assert errors[:, 0] == pytest.approx([2.308, 0.5636, 0.1295], rel=0.02)
    assert orders[:, 0] == pytest.approx([2.03, 2.12], abs=0.05) and np.all(orders[:, 1] > 0.95)
    assert SWEEP > 1.5  # the tube bends by a right angle: the fibres turn by 90° along it


def test_the_smoothing_keeps_a_uniform_flow_and_damps_the_bend_s_turn_a_little():
    """On the prism the smoothed projection of a constant gradient is that constant (the
    filter's natural condition); on the bent tube 2 mm of smoothing on a 1 m tube moves the
    fibres by far less than the discretisation does."""
    geometry = prism(MPI.COMM_WORLD)
    a0, _ = laplace.compute(geometry, laplace.LaplaceParams(smoothing_m=0.01))
    assert np.abs(a0.x.array.reshape(-1, 3) - [0.0, 0.0, 1.0]).max() < 1e-9
    tube = sector(4, MPI.COMM_WORLD)
    fields = [laplace.compute(tube, laplace.LaplaceParams(smoothing_m=ell))[0] for ell in (0.0, 0.002)]
    assert convergence.angles(*fields)["max_deg"] < 0.05 * angle_to_exact(4)[0]


def test_p2_is_nearer_the_exact_flow_than_p1():
    # measured at n = 4: mean 0.564° (P2) against 2.30° (P1)
    assert angle_to_exact(4, degree=2)[0] < 0.3 * angle_to_exact(4, degree=1)[0]


def test_params_are_validated():
    for bad in ({"degree": 3}, {"degree": 0}, {"min_speed": 0.0}, {"min_speed": -1.0}, {"smoothing_m": -1e-3},
                {"smoothing_m": 0.1}, {"smoothing_m": float("nan")}):
        with pytest.raises(InputError):
            laplace.LaplaceParams(**bad)


@pytest.mark.mpi
def test_laplace_fibres_on_two_ranks_equal_serial():
    comm = MPI.COMM_WORLD
    assert comm.size == 2
    data = [fibers.gather_nodal(*laplace.compute(geo.load("TA_VHF_Left", c)), root=0) for c in (comm, MPI.COMM_SELF)]
    if comm.rank == 0:
        assert np.array_equal(data[0]["node"], data[1]["node"])
        assert np.abs(data[0]["a0"] - data[1]["a0"]).max() < 1e-9
        assert np.abs(data[0]["speed"] - data[1]["speed"]).max() < 1e-9 * data[1]["speed"].max()


def test_hyper_mesh_makes_laplace_fibres_which_runs_then_record(tmp_path):
    """--flow-cells 0: the Laplace flow on the mesh itself (the default's flow mesh: the next test)."""
    out = tmp_path / "TA_LAP"
    assert mesh_job.main([str(STL), "--output", str(out), "--cells", "2000", "--method", "laplace",
                          "--flow-cells", "0", "--quiet"]) == 0
    record = json.loads((out / "mesh.json").read_text())
    assert record["fibres_method"] == "laplace" and "fibers_smoothing_mm" not in record
    assert "flow_cells_target" not in record and record["fibers"]["share_within_30deg"] > 0.99
    path = out / fibers.FILE_NAME
    assert fr.stored_fibres(path) == ("laplace", laplace.method())
    with h5py.File(path, "r") as f:
        assert f.attrs["kind"] == "laplace" and f["parameters"].attrs["degree"] == 2
        assert f["parameters"].attrs["smoothing_m"] == 0.002 and "smoothed over 2 mm" in f.attrs["method"]
    mesh = runspec.MeshFile(out / "TA_LAP.xdmf", "mm")
    geometry = mesh.load(MPI.COMM_SELF)
    a0, _ = laplace.compute(geometry)
    assert np.abs(fibers.load(geometry, path).x.array - a0.x.array).max() < 1e-12
    protocol = tmp_path / "short.toml"
    protocol.write_text('name = "short"\nend = 24.0\n[[session]]\nstart = 10\nduration = 1\nintensity = 1.0\n')
    result = tmp_path / "run.h5"
    assert grow.main(["--mesh", str(out / "TA_LAP.xdmf"), "--mesh-unit", "mm", "--protocol", str(protocol),
                      "--growth-dt", "24", "--output", str(result), "--quiet"]) == 0
    with h5py.File(result, "r") as f:
        assert f.attrs["fibers"] == "laplace"
        assert f.attrs["fibers_method"] == f"{laplace.method()}; read from {path}"
        spatial = dict(f["spatial"].attrs)
    # its spatial error: the largest measured with Laplace fibres, not the Stokes fibres' 0.13
    assert runspec.table_name("TA_LAP", mesh) == ("TA_LAP", True, "laplace")
    largest = max(e.error for e in fidelity.LAPLACE_ERROR.values())
    assert spatial["error"] == largest < 0.5 * max(e.error for e in fidelity.SPATIAL_ERROR.values())
    assert "laplace fibres, no table for a mesh file" in spatial["reason"] and not spatial["measured"]


def test_hyper_mesh_solves_the_laplace_flow_on_a_mesh_four_times_finer_by_default(tmp_path):
    """The default: the surface meshed again at 4 x --cells, its Laplace fibres carried onto
    the mesh's nodes (`fibers.carried_over`), as --flow-cells 8000 asks explicitly."""
    out, asked = tmp_path / "TA_LAP", tmp_path / "TA_ASK"
    assert mesh_job.main([str(STL), "--output", str(out), "--cells", "2000", "--quiet"]) == 0
    assert mesh_job.main([str(STL), "--output", str(asked), "--cells", "2000", "--flow-cells", "8000",
                          "--quiet"]) == 0
    record = json.loads((out / "mesh.json").read_text())
    assert record["flow_cells_target"] == mesh_job.FLOW_CELLS_FACTOR * 2000 == 8000
    assert sorted(p.name for p in out.iterdir()) == ["TA_LAP.h5", "TA_LAP.png", "TA_LAP.xdmf", "fibers.h5",
                                                     "mesh.json"]
    kind, method = fr.stored_fibres(out / fibers.FILE_NAME)
    assert kind == "laplace" and method.startswith(laplace.method())
    flow_mesh = tmp_path / "flow" / "flow.xdmf"
    options = mesh_job.parser().parse_args([str(STL), "--output", str(tmp_path / "unused"), "--cells", "2000"])
    fine = mesh_job.flow_mesh(MPI.COMM_SELF, options, flow_mesh, 8000)
    assert method == laplace.method() + fibers.TRANSFERRED_METHOD.format(cells=fine.num_cells())
    geometry = runspec.MeshFile(out / "TA_LAP.xdmf", "mm").load(MPI.COMM_SELF)
    expected, _ = fibers.carried_over(*laplace.compute(fine), geometry, laplace.LaplaceParams().min_speed)
    mine = fibers.load(geometry, out / fibers.FILE_NAME)
    assert np.abs(mine.x.array - expected.x.array).max() < 1e-12
    with h5py.File(asked / fibers.FILE_NAME) as f:
        assert np.array_equal(f["a0"][...], h5py.File(out / fibers.FILE_NAME)["a0"][...])
    # and not the field of the mesh itself (its coarse end patches: docs/convergence.md)
    own, _ = laplace.compute(geometry)
    assert convergence.angles(mine, own)["max_deg"] > 1.0


def test_hyper_mesh_refuses_the_stokes_options_for_laplace_fibres(tmp_path, capsys):
    out = tmp_path / "TA_LAP"
    assert mesh_job.main([str(STL), "--output", str(out), "--cells", "2000", "--fibers-smoothing", "4", "--quiet"]) == 2
    assert not out.exists() and "--method stokes" in capsys.readouterr().err


def test_hyper_fibers_writes_laplace_fibres_beside_a_mesh_file(tmp_path):
    source = geo.MESHES_DIR / geo.GEOMETRIES["ST_VHM_Right"]
    folder = tmp_path / "mine"
    folder.mkdir()
    for path in runspec.mesh_files(source):
        shutil.copy(path, folder / path.name)
    assert fibers_job.main(["--mesh", str(folder / source.name), "--method", "laplace", "--quiet"]) == 0
    assert fr.stored_fibres(folder / fibers.FILE_NAME)[0] == "laplace"
    assert (folder / "fibers.png").is_file()
    # pennate fibres need their aponeuroses: a mesh file's, not a shipped geometry's
    assert fibers_job.main(["--geometries", "ST_VHM_Right", "--method", "pennate", "--quiet"]) == 2


def test_the_laplace_table_has_each_studied_muscle_and_each_shipped_mesh():
    for entry in fidelity.LAPLACE_ERROR.values():
        assert entry.error < convergence.GROWTH_GOAL and "--fibres-method laplace" in entry.source
    assert set(fidelity.LAPLACE_STUDIES) == set(fidelity.SURFACE_STUDIES)  # every muscle with a surface
    shipped = set(geo.ANATOMICAL + geo.MESHED)
    for kind in ("laplace", "stokes"):
        assert set(fidelity.SHIPPED_STUDIES[kind]) == shipped
        for name in shipped:  # measured on the shipped mesh, never below its surface's entry
            got = fidelity.spatial(name, fibres=kind)
            surface = fidelity.TABLES[kind].get(name) or fidelity.TABLES[kind][fidelity.other_side(name)]
            assert got.measured and got.error == max(fidelity.SHIPPED_STUDIES[kind][name], surface.error)
            assert f"--shipped {name} --fibres-method {kind}" in got.reason
    right = fidelity.spatial("BFLH_VHF_Right", fibres="laplace")  # no surface: the other side's study
    assert "BFLH_VHF_Left's surface" in right.reason
    # the shipped meshes with their (Laplace) fibres: all but TA_VHF_Left's vertices' plane within the goal
    missed = [n for n in shipped if fidelity.spatial(n, fibres="laplace").error > convergence.GROWTH_GOAL]
    assert missed == ["TA_VHF_Left"] and fidelity.spatial("TA_VHF_Left", fibres="laplace").error < 0.006
    # with the paper's Stokes fibres 19 of the 31 miss it
    assert sum(fidelity.spatial(n).error > convergence.GROWTH_GOAL for n in shipped) == 19
    # a mesh file with Laplace fibres takes the largest of their table
    assert fidelity.spatial("mine", mesh_file=True, fibres="laplace").error == max(
        e.error for e in fidelity.LAPLACE_ERROR.values())


def test_fibers_laplace_makes_them_on_any_geometry_and_carries_them_onto_its_refinements(tmp_path):
    protocol = tmp_path / "short.toml"
    protocol.write_text('name = "short"\nend = 24.0\n[[session]]\nstart = 10\nduration = 1\nintensity = 1.0\n')
    made = {}
    for refine, fibres in ((0, "laplace"), (1, "laplace"), (0, "auto"), (0, "stokes"), (0, "cylinder")):
        out = tmp_path / f"run{refine}_{fibres}.h5"
        where = ["--geometry", "ST_VHM_Right", "--fibers", fibres] if fibres != "cylinder" else [
            "--geometry", "cylinder", "--fibers", "laplace"]
        assert grow.main([*where, "--refine", str(refine), "--protocol", str(protocol), "--growth-dt", "24",
                          "--output", str(out), "--quiet"]) == 0
        with h5py.File(out, "r") as f:
            made[refine, fibres] = (f.attrs["fibers"], f.attrs["fibers_method"], dict(f["spatial"].attrs),
                                    f.attrs["fibers_sha256"], io.read_series(out)["csa_ratio"][-1])
    # the shipped mesh's fibre file holds them: read, as auto reads them, the same run bit for bit
    stored = fibers.fiber_path("ST_VHM_Right")
    assert made[0, "laplace"][:4] == made[0, "auto"][:4] and made[0, "laplace"][4] == made[0, "auto"][4]
    assert made[0, "laplace"][0] == made[1, "laplace"][0] == "laplace"
    assert made[0, "laplace"][1] == f"{laplace.method()}; read from {stored}"
    assert made[0, "laplace"][3] == ckpt.file_digest(stored)
    assert made[1, "laplace"][1] == f"{laplace.method()}{fibers.CARRIED_METHOD.format(n=1)}; read from {stored}"
    assert "--fibres-method laplace" in made[0, "laplace"][2]["reason"]  # the Laplace table's error
    # the paper's Stokes fibres on request, with their own table's error and another answer
    assert made[0, "stokes"][0] == "stokes" and made[0, "stokes"][3] == ckpt.file_digest(
        fibers.fiber_path("ST_VHM_Right", kind="stokes"))
    assert "--fibres-method stokes" in made[0, "stokes"][2]["reason"] and made[0, "stokes"][4] != made[0, "auto"][4]
    # a geometry without a Laplace fibre file: made on the mesh run
    assert made[0, "cylinder"][:2] == ("laplace", f"{laplace.method()}; made on the mesh run")
    # --ends belongs to the idealized shape's own fibres: one error line, no run
    assert grow.main(["--geometry", "idealized", "--fibers", "laplace", "--ends", "tags", "--output",
                      str(tmp_path / "no.h5"), "--quiet"]) == 2
    assert not (tmp_path / "no.h5").exists()


def test_a_study_remeshes_a_level_made_with_other_fibres():
    record = {"cells_target": 8000}  # an older record: Stokes fibres
    assert convergence.made_as(record, 8000, "stokes") and not convergence.made_as(record, 8000, "laplace")
    assert convergence.made_as({**record, "fibres_method": "laplace"}, 8000, "laplace")
    assert not convergence.made_as(record, 4000, "stokes")


def test_the_original_preset_runs_an_anatomical_mesh_s_stokes_fibres():
    from argparse import Namespace

    from hyper.runs import presets

    def shape(settings="default", fibers=None, geometries=("BFLH_VHF_Left",)):
        return presets.shape(Namespace(settings=settings, fibers=fibers, ends=None), list(geometries))

    assert shape() == {"ends": "disks", "fibers": "auto"}
    assert shape("original") == {"ends": "disks", "fibers": "original"}
    assert shape("original", geometries=("idealized",)) == {"ends": "tags", "fibers": "original"}
    assert shape("original", geometries=("cylinder",)) == {"ends": "disks", "fibers": "auto"}
    assert shape("original", fibers="laplace") == {"ends": "disks", "fibers": "laplace"}  # an explicit option wins
    assert shape(fibers="stokes") == {"ends": "disks", "fibers": "stokes"}
    with pytest.raises(InputError, match="--fibers stokes applies to a --mesh file and the anatomical meshes"):
        shape(fibers="stokes", geometries=("idealized",))
    muscle = geo.load("ST_VHM_Right", MPI.COMM_SELF)
    assert [fibers.resolved(muscle, k) for k in ("auto", "original", "stokes")] == ["laplace", "stokes", "stokes"]
    assert fibers.resolved(geo.load("idealized", MPI.COMM_SELF), "original") == "original"


def test_hyper_fibers_refuses_to_remake_fibres_hyper_mesh_solved_on_a_finer_mesh(tmp_path, capsys):
    """The 19 new meshes' Laplace fibres come from a 32k-cell mesh of their surface: solved on
    the 8k mesh itself they would be another field, so `hyper fibers` refuses to replace them
    (a paper mesh's, solved on itself, it remakes)."""
    before = (geo.MESHES_DIR / "VM_VHM_Left" / fibers.FILE_NAME).read_bytes()
    assert json.loads((geo.MESHES_DIR / "VM_VHM_Left" / "mesh.json").read_text())["flow_cells_target"] == 32000
    assert fibers_job.main(["--geometries", "VM_VHM_Left", "--method", "laplace", "--force", "--output",
                            str(tmp_path), "--quiet"]) == 2
    assert "VM_VHM_Left: its Laplace fibres were solved by hyper mesh on a 32000-cell mesh" in capsys.readouterr().err
    assert (geo.MESHES_DIR / "VM_VHM_Left" / fibers.FILE_NAME).read_bytes() == before
    # nor beside a copy of its folder, given as a mesh file
    folder = tmp_path / "mine"
    shutil.copytree(geo.MESHES_DIR / "VM_VHM_Left", folder)
    assert fibers_job.main(["--mesh", str(folder / "VM_VHM_Left.xdmf"), "--method", "laplace", "--force",
                            "--quiet"]) == 2
    assert "hyper mesh --flow-cells 0 gives the mesh's own" in capsys.readouterr().err
    assert (folder / fibers.FILE_NAME).read_bytes() == before
