"""Every result says where it came from: the command, the versions, the commit, the
mesh's hash, and a unit on every series; `hyper inspect` prints it."""

from __future__ import annotations

import hashlib

import h5py
import pytest

from hyper.analysis import study
from hyper.commands import cli
from hyper.core import io
from hyper.fem import geometry as geo
from hyper.model import material as mat
from hyper.runs import runspec

SHORT = 'name = "short"\nend = 48.0\n[[session]]\nstart = 0.0\nduration = 1.0\nintensity = 0.8\n'


@pytest.fixture(scope="module")
def grown(tmp_path_factory):
    d = tmp_path_factory.mktemp("provenance")
    (d / "short.toml").write_text(SHORT)
    (d / "soft.toml").write_text("sigma_act = 2.5e5\nc1 = 1.2e4\n")
    out = d / "run.h5"
    argv = ["grow", "--geometry", "cylinder", "--protocol", str(d / "short.toml"), "--growth-dt", "24",
            "--material", str(d / "soft.toml"), "--output", str(out), "--quiet"]
    assert cli.main(argv) == 0
    return out, argv


def test_a_result_carries_its_command_versions_and_mesh_hash(grown):
    out, argv = grown
    with h5py.File(out) as f:
        attrs = dict(f.attrs)
        units = {name: f[name].attrs["units"] for name in f if isinstance(f[name], h5py.Dataset)}
    assert attrs["command"] == "hyper " + " ".join(argv)
    for package in ("hyper", "numpy", "scipy", "h5py", "SALib", "mpi4py", "dolfinx", "petsc4py", "petsc",
                    "mpi_library"):
        assert attrs[f"version_{package}"], package
    assert len(attrs["version_git_commit"].split("-")[0]) == 40  # run from this checkout
    mesh = geo.MESHES_DIR / geo.GEOMETRIES["cylinder"]
    assert attrs["mesh_sha256"] == hashlib.sha256(mesh.read_bytes()).hexdigest()
    assert attrs["quadrature_degree"] == 4 and attrs["ranks"] == 1 and attrs["linear_solver"] == "lu"
    assert units["t"] == "h" and units["kM"] == "1/h" and units["wall_s"] == "s"
    assert "unspecified" not in units.values(), units


def test_inspect_prints_the_provenance_and_the_series(grown, capsys):
    out, _ = grown
    assert cli.main(["inspect", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"{out}: complete" in text and "run_digest = " in text and "[settings]" in text
    assert "csa_ratio [1]: shape (4,)" in text and "t [h]: shape (4,), first 0, last 48" in text  # 0, 1, 24, 48 h


def test_inspect_against_another_result_compares_every_series_bit_for_bit(grown, tmp_path, capsys):
    out, argv = grown
    again = tmp_path / "again.h5"  # the same run once more: the same bits, but its own wall time
    assert cli.main([*argv[:argv.index("--output")], "--output", str(again), "--quiet"]) == 0
    capsys.readouterr()
    assert cli.main(["inspect", str(out), "--against", str(again)]) == cli.EXIT_OK
    text = capsys.readouterr().out
    assert "csa_ratio: identical (4 values)" in text and "wall_s" not in text and "differs" not in text
    series = io.read_series(again)
    series["csa_ratio"] = series["csa_ratio"] + [0, 0, 0, 2.5e-12]
    series.pop("kM")
    io.write_series(tmp_path / "other.h5", series)
    assert cli.main(["inspect", str(out), "--against", str(tmp_path / "other.h5")]) == cli.EXIT_SOME_FAILED
    text = capsys.readouterr().out
    assert "csa_ratio: differs, largest |difference| 2.5e-12" in text and f"kM: only in {out}" in text
    assert cli.main(["inspect", str(out), "--against", str(tmp_path / "absent.h5")]) == cli.EXIT_INPUT
    assert "absent.h5: missing or incomplete" in capsys.readouterr().err


def test_inspect_refuses_what_is_not_a_result(tmp_path, capsys):
    (tmp_path / "x.h5").write_text("not HDF5")
    for path in (tmp_path / "x.h5", tmp_path / "absent.h5"):
        assert cli.main(["inspect", str(path)]) == cli.EXIT_INPUT
        assert capsys.readouterr().err.startswith("error: ")


def test_every_series_name_the_jobs_write_has_a_unit():
    from hyper.analysis import ensemble
    from hyper.model import signaling
    from hyper.runs import driver

    names = [*driver.SERIES, *ensemble.STD, "final_x", "final_u", "final_N", "final_detGbar", *signaling.STATES]
    assert all(io.unit(name) != "unspecified" for name in names)


def test_a_result_records_its_material_and_the_study_that_reruns_it(grown, tmp_path):
    out, _ = grown
    with h5py.File(out) as f:
        groups = {name: dict(f[name].attrs) for name in f if isinstance(f[name], h5py.Group)}
        text, digest = f.attrs["study"], f.attrs["run_digest"]
    assert {"signaling", "material", "protocol", "settings"} <= set(groups)
    assert groups["material"]["sigma_act"] == 2.5e5 and groups["material"]["c1"] == 1.2e4
    assert groups["material"]["c2"] == mat.MaterialParams().c2
    # the recorded study, loaded as a study file, is the same run: the same digest
    (tmp_path / "again.toml").write_text(text)
    loaded = study.load(tmp_path / "again.toml")
    assert loaded.material == mat.MaterialParams(sigma_act=2.5e5, c1=1.2e4)
    settings, choice = study.steps(loaded)
    assert study.first_spec(loaded, settings, choice).digest() == digest
    assert [p.name for p in loaded.protocols] == ["short"] and loaded.protocols[0].end == 48.0


def test_material_parameters_change_the_run(grown):
    from hyper.model import protocols

    out, _ = grown
    plain = runspec.RunSpec("cylinder", protocols.load(out.parent / "short.toml"))
    assert plain.digest() != h5py.File(out).attrs["run_digest"]
    # the defaults leave the digest of a run as it was before material parameters could be set
    assert "material" not in plain.describe()


def test_a_bad_material_file_is_refused_before_anything_is_written(tmp_path, capsys):
    (tmp_path / "bad.toml").write_text("lambda0 = -1.4\n")
    for job, out in ((["grow", "--geometry", "cylinder"], "out"), (["contraction", "--geometry", "cylinder"], "c.h5"),
                     (["cohort", "--geometries", "cylinder"], "out")):
        code = cli.main([*job, "--material", str(tmp_path / "bad.toml"), "--output", str(tmp_path / out)])
        assert code == cli.EXIT_INPUT, job
        err = capsys.readouterr().err
        assert err.startswith("error: ") and "lambda0: expected a number > 0" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.toml"]


def test_signaling_results_use_the_same_group_names(tmp_path):
    out = tmp_path / "s.h5"
    assert cli.main(["signaling", "--protocol", "weekly", "--output", str(out)]) == 0
    with h5py.File(out) as f:
        assert f["signaling"].attrs["kM"] == 0.01 and f["settings"].attrs["signaling_dt"] == 0.05
        assert f["protocol"].attrs["name"] == "weekly"
        assert "unspecified" not in {f[n].attrs["units"] for n in f if isinstance(f[n], h5py.Dataset)}


def test_inspect_shows_the_groups_and_the_study(grown, capsys):
    out, _ = grown
    assert cli.main(["inspect", str(out)]) == 0
    text = capsys.readouterr().out
    order = [text.index(f"[{g}]") for g in ("signaling", "material", "protocol", "settings")]
    assert order == sorted(order) and "  sigma_act = 250000.0" in text
    assert "study (the study file that reruns this result):" in text and '  geometries = ["cylinder"]' in text


def test_a_remade_mesh_or_fibre_file_is_another_run(tmp_path, monkeypatch):
    # A cohort skips a run whose result has its digest: after `hyper mesh --force` or
    # `make new-meshes` remade a geometry's files in place, the old result must not count.
    import shutil

    from hyper.model import protocols

    name = "TA_VHF_Left"
    spec = runspec.RunSpec(name, protocols.named("mwf"))
    before = spec.digest()
    folder = spec.input_files()[0].parent
    copy = tmp_path / folder.name
    shutil.copytree(folder, copy)
    monkeypatch.setattr(geo, "MESHES_DIR", tmp_path)
    assert [p.parent for p in spec.input_files()] == [copy] * 3  # the mesh, its data and its fibres
    assert spec.digest() == before  # the bytes count, not where they lie
    for changed in (copy / "fibers.h5", copy / f"{folder.name}.h5"):
        original = changed.read_bytes()
        changed.write_bytes(original + b"\0")
        assert spec.digest() != before, changed.name
        changed.write_bytes(original)
    assert spec.digest() == before


def test_a_run_of_the_stokes_fibres_counts_their_file_not_the_laplace_one(tmp_path, monkeypatch):
    import shutil

    from hyper.fem import fibers
    from hyper.model import protocols

    name = "TA_VHF_Left"
    own = runspec.RunSpec(name, protocols.named("mwf"))
    stokes = runspec.RunSpec(name, protocols.named("mwf"), fibers="stokes")
    assert own.input_files()[-1].name == fibers.FILE_NAME
    assert stokes.input_files()[-1].name == fibers.STOKES_FILE_NAME
    assert runspec.RunSpec(name, protocols.named("mwf"), fibers="original").input_files() == stokes.input_files()
    folder = own.input_files()[0].parent
    shutil.copytree(folder, tmp_path / folder.name)
    monkeypatch.setattr(geo, "MESHES_DIR", tmp_path)
    before = {"own": own.digest(), "stokes": stokes.digest()}
    assert before["own"] != before["stokes"]
    laplace_file = tmp_path / folder.name / fibers.FILE_NAME
    laplace_file.write_bytes(laplace_file.read_bytes() + b"\0")
    assert own.digest() != before["own"] and stokes.digest() == before["stokes"]
