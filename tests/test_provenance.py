"""Every result says where it came from: the command, the versions, the commit, the
mesh's hash, and a unit on every series; `hyper inspect` prints it."""

from __future__ import annotations

import hashlib

import h5py
import pytest

from hyper import cli, geometry, io

SHORT = 'name = "short"\nend = 48.0\n[[session]]\nstart = 0.0\nduration = 1.0\nintensity = 0.8\n'


@pytest.fixture(scope="module")
def grown(tmp_path_factory):
    d = tmp_path_factory.mktemp("provenance")
    (d / "short.toml").write_text(SHORT)
    out = d / "run.h5"
    argv = ["grow", "--geometry", "cylinder", "--protocol", str(d / "short.toml"), "--growth-dt", "24",
            "--output", str(out), "--quiet"]
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
    mesh = geometry.MESHES_DIR / geometry.GEOMETRIES["cylinder"]
    assert attrs["mesh_sha256"] == hashlib.sha256(mesh.read_bytes()).hexdigest()
    assert attrs["quadrature_degree"] == 4
    assert units["t"] == "h" and units["kM"] == "1/h" and units["wall_s"] == "s"
    assert "unspecified" not in units.values(), units


def test_inspect_prints_the_provenance_and_the_series(grown, capsys):
    out, _ = grown
    assert cli.main(["inspect", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"{out}: complete" in text and "run_digest = " in text and "[settings]" in text
    assert "csa_ratio [1]: shape (4,)" in text and "t [h]: shape (4,), first 0, last 48" in text  # 0, 1, 24, 48 h


def test_inspect_refuses_what_is_not_a_result(tmp_path, capsys):
    (tmp_path / "x.h5").write_text("not HDF5")
    for path in (tmp_path / "x.h5", tmp_path / "absent.h5"):
        assert cli.main(["inspect", str(path)]) == cli.EXIT_INPUT
        assert capsys.readouterr().err.startswith("error: ")


def test_every_series_name_the_jobs_write_has_a_unit():
    from hyper import ensemble, run, signaling

    names = [*run.SERIES, *ensemble.STD, "final_x", "final_u", "final_N", "final_detGbar", *signaling.STATES]
    assert all(io.unit(name) != "unspecified" for name in names)
