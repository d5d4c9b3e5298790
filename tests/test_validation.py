"""Every malformed input of `python -m hyper.grow` is refused before any work (issue 8).

Table-driven: each case is a command line (with the file it names), the message it
must give (a regex), exit status 2, and a results folder that stays as it was (here:
never created). Protocol and parameter files go through the shared parsers
(hyper.model.protocols.load, hyper.model.signaling.load_params), so these cases cover them too.
"""

import re
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import h5py
import numpy as np
import pytest
from dolfinx import mesh as dmesh
from dolfinx.io import XDMFFile
from mpi4py import MPI

from hyper.commands import grow

SESSION = "[[session]]\nstart = {start}\nduration = {duration}\nintensity = {intensity}\n"


def session(start=0.0, duration=1.0, intensity=0.8):
    return SESSION.format(start=start, duration=duration, intensity=intensity)


PROTOCOL_OK = "name = \"short\"\nend = 96.0\n" + session() + session(start=48.0)

# name -> (protocol file text, message)
BAD_PROTOCOLS = {
    "protocol_syntax": ("end = \n", r"malformed TOML: Invalid value \(at line 1, column 7\)"),
    "protocol_unknown_key": ("end = 96.0\nends = 1\n", r"unknown key\(s\) ends; known: end, name, repeat, session"),
    "protocol_missing_end": (session(), r"missing 'end' \(the end time of the protocol in hours\)"),
    "protocol_end_text": ("end = \"96 h\"\n", r"end: expected a number, got '96 h'"),
    "protocol_end_nan": ("end = nan\n", r"end: expected a finite number, got nan"),
    "protocol_end_negative": ("end = -5.0\n", r"end must be a finite number > 0 h, got -5"),
    "protocol_session_missing": ("end = 96.0\n[[session]]\nstart = 0.0\nduration = 1.0\n",
                                 r"session 0: missing intensity"),
    "protocol_session_unknown": ("end = 96.0\n" + session() + "power = 3\n",
                                 r"session 0: unknown key\(s\) power; known: start, duration, intensity"),
    "protocol_negative_duration": ("end = 96.0\n" + session(duration=-1.0),
                                   r"session 0: duration must be > 0 h, got -1"),
    "protocol_intensity_high": ("end = 96.0\n" + session(intensity=1.5),
                                r"session 0: intensity must lie in \[0, 1\], got 1.5"),
    "protocol_intensity_bool": ("end = 96.0\n[[session]]\nstart = 0.0\nduration = 1.0\nintensity = true\n",
                                r"session 0: intensity: expected a number, got True"),
    "protocol_overlap": ("end = 96.0\n" + session(duration=2.0) + session(start=1.0),
                         r"session 1: overlaps session 0: it starts at 1 h, before session 0 ends \(2 h\)"),
    "protocol_unsorted": ("end = 96.0\n" + session(start=48.0) + session(start=0.0),
                          r"session 1: sessions must be sorted by start"),
    "protocol_session_not_table": ("end = 96.0\nsession = 3\n", r"'session' must be an array of tables"),
    "protocol_end_early": ("end = 24.0\n" + session(start=48.0),
                           r"end \(24 h\) lies before the end of the last session 0 \(49 h\)"),
    "protocol_name_number": ("end = 96.0\nname = 5\n", r"name must be a string, got 5"),
}

# name -> (parameter file text, message)
BAD_PARAMS = {
    "params_syntax": ("kM = = 0.01\n", r"malformed TOML: Invalid value \(at line 1, column 6\)"),
    "params_unknown": ("kMx = 0.01\n", r"unknown parameter\(s\) kMx; known: .*kM"),
    "params_text": ("kM = \"fast\"\n", r"kM: expected a number, got 'fast'"),
    "params_table": ("[kM]\nvalue = 0.01\n", r"kM: expected a number, got \{'value': 0.01\}"),
    "params_negative": ("kM = -0.01\n", r"kM must be >= 0, got -0.01"),
    "params_nan": ("kF = nan\n", r"kF: expected a finite number, got nan"),
    "params_inf": ("b1 = inf\n", r"b1: expected a finite number, got inf"),
    "params_zero_rate": ("b1 = 0.0\n", r"b1 must be a finite positive number, got 0.0"),
    "params_range": ("Nmin = 1.5\n", r"Nmin must be < Nmax, got Nmin=1.5, Nmax=1.3"),
}

# name -> (extra options, message); {d} is the folder of input files
BAD_OPTIONS = {
    "growth_dt_negative": (["--growth-dt", "-1"], r"--growth-dt: expected a finite number of hours > 0, got -1"),
    "growth_dt_nan": (["--growth-dt", "nan"], r"--growth-dt: expected a finite number of hours > 0, got nan"),
    "growth_dt_text": (["--growth-dt", "1day"], r"argument --growth-dt: expected a number of hours, got '1day'"),
    "signaling_dt_zero": (["--signaling-dt", "0"], r"--signaling-dt: expected a finite number of hours > 0, got 0"),
    "signaling_dt_above_growth_dt": (["--growth-dt", "8", "--signaling-dt", "12"],
                                     r"--signaling-dt: 12 h must not exceed the growth step \(8 h\)"),
    "feedback": (["--feedback", "cubic"], r"argument --feedback: invalid choice: 'cubic'"),
    "growth_fields": (["--growth-fields", "p1"], r"argument --growth-fields: invalid choice: 'p1'"),
    "ends_off_the_idealized_shape": (["--ends", "tags"], r"--ends applies to the idealized shape only"),
    "original_fibres_on_the_cylinder": (["--fibers", "original"],
                                        r"--fibers original: the original code's fibres are the idealized shape's "
                                        r"and the anatomical meshes' \(their Stokes fibres\), not the cylinder's"),
    "stokes_fibres_on_the_cylinder": (["--fibers", "stokes"],
                                      r"--fibers stokes applies to a --mesh file and the anatomical meshes"),
    "snapshot_every": (["--snapshot-every", "0"],
                       r"--snapshot-every: expected a finite number of hours > 0, got 0"),
    "snapshot_every_text": (["--snapshot-every", "daily"],
                            r"--snapshot-every: expected a number of hours, got 'daily'"),
    "data_missing": (["--data", "{d}/none.csv"], r"none.csv: no such file"),
    "checkpoint_every": (["--checkpoint-every", "-2"], r"--checkpoint-every: expected an integer >= 0"),
    "checkpoint_every_fraction": (["--checkpoint-every", "2.5"],
                                  r"argument --checkpoint-every: expected an integer, got '2.5'"),
    "max_halvings": (["--max-halvings", "40"], r"argument --max-halvings: expected an integer in \[0, 12\], got 40"),
    "refine_above": (["--refine", "4"], r"argument --refine: expected an integer in \[0, 3\], got 4"),
    "refine_negative": (["--refine", "-1"], r"argument --refine: expected an integer in \[0, 3\], got -1"),
    "refine_fraction": (["--refine", "1.5"], r"argument --refine: expected an integer, got '1.5'"),
    "mesh_fibres_on_a_geometry": (["--fibers", "principal"], r"--fibers principal applies to a --mesh file"),
    "original_fibres_on_a_mesh": (["--mesh", "{d}/muscle_m.xdmf", "--fibers", "original"],
                                  r"--fibers original: a --mesh file's fibres are one of auto, stokes, axial"),
    "fibres_unknown": (["--fibers", "helical"], r"--fibers helical: expected one of auto, original, stokes"),
    "petsc_option_no_value": (["--petsc-option", "snes_max_it"], r"--petsc-option 'snes_max_it': expected KEY=VALUE"),
    "petsc_option_dash": (["--petsc-option=-snes_max_it=3"], r"--petsc-option '-snes_max_it=3': expected KEY=VALUE"),
    "petsc_option_lag": (["--petsc-option", "snes_lag_jacobian=0"], r"snes_lag_jacobian must be a positive integer"),
    "geometry": (["--geometry", "biceps"], r"--geometry: unknown geometry 'biceps'; known: idealized, cylinder, BFLH"),
    "protocol": (["--protocol", "daily"], r"--protocol: unknown protocol 'daily'; known: mwf, .*or 'all'"),
    "protocol_file_absent": (["--protocol", "{d}/absent.toml"], r"absent.toml: no such file"),
    "params_absent": (["--params", "{d}/absent_params.toml"], r"absent_params.toml: no such file"),
    "output_not_h5": (["--output", "{out}/run.xdmf"], r"--output .*run.xdmf: expected an .h5 file or a folder"),
    "output_h5_for_all": (["--protocol", "all"], r"--output .*run.h5: several protocols need a folder"),
    "output_under_a_file": (["--output", "{d}/a_file/run.h5"], r"a_file is a file, not a folder"),
    "plot_not_png": (["--plot", "{out}/figure.pdf"], r"--plot: .*figure.pdf: expected a .png file"),
    "unknown_option": (["--bogus"], r"unrecognized arguments: --bogus"),
    "mesh_and_geometry": (["--mesh", "{d}/muscle_m.xdmf", "--geometry", "idealized"],
                          r"--geometry and --mesh exclude each other"),
    "mesh_unit_without_mesh": (["--mesh-unit", "mm"], r"--mesh-unit declares the length unit of a --mesh file"),
    "mesh_absent": (["--mesh", "{d}/absent.xdmf"], r"absent.xdmf: no such mesh file"),
    "mesh_in_mm_read_as_m": (["--mesh", "{d}/muscle_mm.xdmf"],
                             r"muscle_mm.xdmf: the mesh is 200 m long .*outside the 0.01-1 m of a muscle: "
                             r"its length unit is not 'm'; declare the file's unit with --mesh-unit"),
    "mesh_in_m_read_as_mm": (["--mesh", "{d}/muscle_m.xdmf", "--mesh-unit", "mm"],
                             r"muscle_m.xdmf: the mesh is 0.2 mm long .*i.e. 0.0002 m, outside"),
    "mesh_unit": (["--mesh", "{d}/muscle_m.xdmf", "--mesh-unit", "cm"],
                  r"--mesh-unit: expected one of m, mm, got 'cm'"),
    "mesh_missing_end_tag": (["--mesh", "{d}/missing_end.xdmf"],
                             r"missing_end.xdmf: facet tag 2 \(end\) is missing; the file has tags \[1, 3\]"),
    "mesh_not_xdmf": (["--mesh", "{d}/muscle.msh"], r"muscle.msh: expected an XDMF mesh file"),
    "mesh_garbage": (["--mesh", "{d}/garbage.xdmf"], r"garbage.xdmf: cannot read a mesh 'Grid' with facet tags"),
    "mesh_tangled": (["--mesh", "{d}/tangled.xdmf"],
                     r"tangled.xdmf: the mesh is tangled: \d+ of its 96 cells are inverted"),
    "mesh_flat": (["--mesh", "{d}/flat.xdmf"], r"flat.xdmf: degenerate cells: the smallest has 0 of the mean"),
    "mesh_collapsed_cells": (["--mesh", "{d}/collapsed.xdmf"], r"collapsed.xdmf: degenerate cells"),
    "mesh_truncated": (["--mesh", "{d}/truncated.xdmf"],
                       r"truncated.xdmf: cannot read its data file truncated.h5 \(truncated or damaged\?\)"),
    "mesh_data_missing": (["--mesh", "{d}/no_data.xdmf"], r"no_data.xdmf: its data file no_data.h5 is missing"),
    "petsc_option_misspelt": (["--petsc-option", "snes_maxit=50"],
                              r"--petsc-option: PETSc does not read snes_maxit for the mechanics solver"),
    "petsc_option_bad_type": (["--petsc-option", "snes_type=bogus"],
                              r"^error: PETSc refused --petsc-option snes_type=bogus: Unable to find requested SNES"),
    "petsc_option_bad_value": (["--petsc-option", "snes_max_it=many"],
                               r"^error: PETSc refused --petsc-option snes_max_it=many: Input string many has no"),
    "geometry_empty": (["--geometry", ""], r"--geometry: unknown geometry ''"),
    "signaling_dt_tiny": (["--signaling-dt", "1e-300"], r"--signaling-dt: expected at least 0.0001 h, got 1e-300"),
    "output_under_proc": (["--output", "/proc/hyper/run.h5"], r"--output: /proc/hyper/run.h5: under /proc"),
    "output_a_file_as_folder": (["--protocol", "all", "--output", "{d}/a_file"],
                                r"--output: .*a_file: exists and is not a folder|--output .*a_file: exists"),
    "plot_under_a_file": (["--plot", "{d}/a_file/figure.png"], r"--plot: .*a_file is a file, not a folder"),
    "plot_under_proc": (["--plot", "/proc/figure.png"], r"--plot: /proc/figure.png: under /proc"),
    "lock_is_a_folder": (["--output", "{d}/locked/run.h5"], r"cannot take the output lock: .*run.h5.lock"),
    "params_folder": (["--params", "{d}/a_folder"], r"a_folder: is a folder, not a TOML file"),
    # issue 35: the regional sections and detraining
    "sections_negative": (["--sections", "-1"], r"argument --sections: expected an integer in \[0, 99\], got -1"),
    "sections_fraction": (["--sections", "2.5"], r"argument --sections: expected an integer, got '2.5'"),
    "sections_huge": (["--sections", "100"], r"argument --sections: expected an integer in \[0, 99\], got 100"),
    "detraining_zero": (["--detraining", "0"], r"argument --detraining: expected a finite number of hours > 0, got 0"),
    "detraining_nan": (["--detraining", "nan"], r"argument --detraining: expected a finite number of hours > 0"),
    "detraining_negative": (["--detraining", "-1"],
                            r"argument --detraining: expected a finite number of hours > 0, got -1"),
    "detraining_inf": (["--detraining", "inf"], r"argument --detraining: expected a finite number of hours > 0"),
    # issue 35 item 3: along-fibre growth
    "fiber_growth_unknown": (["--fiber-growth", "along"], r"argument --fiber-growth: invalid choice: 'along'"),
    # issue 35 item 2: local mechanosensing
    "stimulus_unknown": (["--stimulus", "regional"], r"argument --stimulus: invalid choice: 'regional'"),
    "data_section_without_sections": (["--data", "{d}/at_section.csv", "--sections", "0"],
                                      r"at_section.csv: measured at section 0.45 of the length; the runs record no "
                                      r"regional sections \(--sections 0\)"),
    "data_section_outside": (["--data", "{d}/at_section.csv", "--sections", "1"],
                             r"at_section.csv: measured at section 0.45 .*outside the 1 regional sections"),
    "data_section_bad": (["--data", "{d}/bad_section.csv"],
                         r"bad_section.csv: line 1: section: expected a number in \(0, 1\), got 1.5"),
    "data_setting_unknown": (["--data", "{d}/bad_setting.csv"],
                             r"bad_setting.csv: line 1: unknown setting 'sectoin'; known: muscle, measure, section"),
}


def write_box(path: Path, size, tags=(1, 2, 3)):
    """A tetrahedral box [0, size] with facet tags: z = 0, z = top, the rest."""
    comm = MPI.COMM_SELF
    mesh = dmesh.create_box(comm, [np.zeros(3), np.asarray(size, dtype=float)], [2, 2, 4],
                            dmesh.CellType.tetrahedron)
    mesh.name = "Grid"
    mesh.topology.create_connectivity(2, 3)
    facets = dmesh.exterior_facet_indices(mesh.topology)
    z = dmesh.compute_midpoints(mesh, 2, facets)[:, 2]
    values = np.where(np.isclose(z, 0), tags[0], np.where(np.isclose(z, size[2]), tags[1], tags[2]))
    meshtags = dmesh.meshtags(mesh, 2, facets, values.astype(np.int32))
    meshtags.name = "ft_small"
    with XDMFFile(comm, str(path), "w") as xdmf:
        xdmf.write_mesh(mesh)
        xdmf.write_meshtags(meshtags, mesh.geometry)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """The input files, written by rank 0 into one folder that every rank reads."""
    comm = MPI.COMM_WORLD
    d = Path(comm.bcast(str(tmp_path_factory.mktemp("inputs")) if comm.rank == 0 else None, root=0))
    if comm.rank == 0:
        write_inputs(d)
    comm.barrier()
    return d


def write_inputs(d: Path) -> None:
    (d / "protocol.toml").write_text(PROTOCOL_OK)
    (d / "params.toml").write_text("thetaM = 0.46\n")
    for name, (text, _) in BAD_PROTOCOLS.items():
        (d / f"bad_{name}.toml").write_text(text)
    for name, (text, _) in BAD_PARAMS.items():
        (d / f"bad_{name}.toml").write_text(text)
    (d / "a_file").write_text("not a folder\n")
    write_box(d / "muscle_mm.xdmf", (20.0, 20.0, 200.0))  # a 20 cm muscle, in millimetres
    write_box(d / "muscle_m.xdmf", (0.02, 0.02, 0.2))  # the same in metres
    write_box(d / "missing_end.xdmf", (0.02, 0.02, 0.2), tags=(1, 3, 3))
    (d / "garbage.xdmf").write_text("this is not XDMF\n")
    (d / "muscle.msh").write_text("$MeshFormat\n4.1 0 8\n$EndMeshFormat\n")
    for name in ("tangled", "flat", "collapsed", "truncated", "no_data"):
        write_box(d / f"{name}.xdmf", (0.02, 0.02, 0.2))
    with h5py.File(d / "tangled.h5", "r+") as f:
        x = f["Mesh/Grid/geometry"]
        x[0] = x[0] + np.array([0.03, 0.03, 0.1])  # a corner pulled through the box
    with h5py.File(d / "flat.h5", "r+") as f:
        x = f["Mesh/Grid/geometry"]
        x[:, 2] = 0.0
    with h5py.File(d / "collapsed.h5", "r+") as f:
        x = f["Mesh/Grid/geometry"]
        cell = f["Mesh/Grid/topology"][0]
        x[cell[1]] = x[cell[0]]  # two vertices of a cell on one point
    data = (d / "truncated.h5").read_bytes()
    (d / "truncated.h5").write_bytes(data[: len(data) // 2])
    (d / "no_data.h5").unlink()
    (d / "at_section.csv").write_text("section = 0.45\nday,csa_change_percent\n0,0\n4,0.2\n")
    (d / "bad_section.csv").write_text("section = 1.5\nday,csa_change_percent\n0,0\n4,0.2\n")
    (d / "bad_setting.csv").write_text("# sectoin = 0.5\nday,csa_change_percent\n0,0\n4,0.2\n")
    (d / "a_folder").mkdir()
    (d / "locked").mkdir()
    (d / "locked" / "run.h5.lock").mkdir()


def base(files, out, protocol_file=True, geometry=True):
    protocol = ["--protocol", str(files / "protocol.toml")] if protocol_file else []
    return [*(["--geometry", "cylinder"] if geometry else []), *protocol, "--params", str(files / "params.toml"),
            "--output", str(out / "run.h5")]


def argv_for(files, out, options):
    """The base command with ``options``; a --mesh or --protocol there replaces the base's
    --geometry or --protocol."""
    return base(files, out, protocol_file="--protocol" not in options, geometry="--mesh" not in options) + [
        o.format(d=files, out=out) for o in options]


def cases():
    """Every case, as a list (pytest wants a collection)."""
    return list(_cases())


def _cases():
    for name, (_, message) in BAD_PROTOCOLS.items():
        yield pytest.param(["--protocol", "{d}/bad_" + name + ".toml"], rf"bad_{name}.toml: .*{message}", id=name)
    for name, (_, message) in BAD_PARAMS.items():
        yield pytest.param(["--params", "{d}/bad_" + name + ".toml"], rf"bad_{name}.toml: .*{message}", id=name)
    for name, (options, message) in BAD_OPTIONS.items():
        yield pytest.param(options, message, id=name)


@pytest.mark.parametrize("options, message", cases())
def test_malformed_input_is_refused_before_anything_is_written(files, tmp_path, capsys, options, message):
    out = tmp_path / "results"
    assert grow.main(argv_for(files, out, options)) == 2
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), captured.err
    assert re.search(message, lines[0]), lines[0]
    assert not out.exists()
    assert captured.out == ""


def test_the_table_is_long_enough():
    assert len(BAD_PROTOCOLS) + len(BAD_PARAMS) + len(BAD_OPTIONS) >= 30


def fake_checkpoint(path: Path, **attrs) -> None:
    with h5py.File(path, "w") as f:
        f.attrs.update(attrs)


@pytest.mark.parametrize("kind, message", [
    ("foreign", r"run.ckpt.h5: the checkpoint belongs to another run \(geometry, protocol, parameters, settings "
                r"or solver options differ.*remove it or pass --restart"),
    ("unfinished", r"run.ckpt.h5: not a complete hyper.grow checkpoint; remove it or pass --restart"),
    ("future", r"run.ckpt.h5: checkpoint format 99, this version reads 1"),
    ("garbage", r"run.ckpt.h5: not a readable checkpoint .*remove it or pass --restart"),
])
def test_a_checkpoint_that_is_not_this_runs_is_refused(files, tmp_path, capsys, kind, message):
    out = tmp_path / "results"
    out.mkdir()
    saved = out / "run.ckpt.h5"
    common = {"kind": "hyper.grow checkpoint", "format": 1, "complete": True, "run_digest": "0" * 64}
    if kind == "garbage":
        saved.write_bytes(b"\x89HDF not really")
    else:
        attrs = {"foreign": common, "unfinished": {**common, "complete": False},
                 "future": {**common, "format": 99}}[kind]
        fake_checkpoint(saved, **attrs)
    before = sorted((p.name, p.stat().st_mtime_ns, p.stat().st_size) for p in out.iterdir())
    assert grow.main(base(files, out)) == 2
    err = capsys.readouterr().err
    assert re.search(message, err), err
    assert sorted((p.name, p.stat().st_mtime_ns, p.stat().st_size) for p in out.iterdir()) == before
    # --restart is the way out, and it is accepted (checked without running)
    grow.plan(MPI.COMM_WORLD, base(files, out) + ["--restart"])


@pytest.mark.parametrize("extra", [
    [],
    ["--mesh", "{d}/muscle_mm.xdmf", "--mesh-unit", "mm"],
    ["--mesh", "{d}/muscle_m.xdmf"],
    ["--protocol", "all", "--output", "{out}"],
], ids=["files", "mesh_mm", "mesh_m", "all"])
def test_good_inputs_pass_the_checks_and_write_nothing(files, tmp_path, extra):
    out = tmp_path / "results"
    argv = argv_for(files, out, extra)
    work = grow.plan(MPI.COMM_WORLD, argv)
    assert len(work.outputs) == (3 if "all" in extra else 1)
    if "--mesh" in extra:
        assert work.geometry == Path(extra[1]).stem
        assert work.mesh.unit == ("mm" if "mm" in extra else "m")
    assert not out.exists()


@pytest.mark.mpi
@pytest.mark.parametrize("name", ["protocol_overlap", "params_nan", "mesh_in_mm_read_as_m", "mesh_missing_end_tag",
                                  "petsc_option_no_value", "mesh_tangled", "mesh_truncated", "petsc_option_misspelt",
                                  "petsc_option_bad_type", "lock_is_a_folder", "plot_under_proc"])
def test_every_rank_refuses_alike(files, tmp_path_factory, capsys, name):
    """On 2 ranks every rank returns 2 and only rank 0 speaks (no rank is left waiting)."""
    comm = MPI.COMM_WORLD
    out = Path(comm.bcast(str(tmp_path_factory.mktemp("results")) if comm.rank == 0 else None, root=0)) / "results"
    options = dict((p.id, p.values[0]) for p in cases())[name]
    assert grow.main(argv_for(files, out, options)) == 2
    err = capsys.readouterr().err
    assert (err.startswith("error: ") and err.count("\n") == 1) if comm.rank == 0 else err == ""
    comm.barrier()
    assert not out.exists()
