"""A non-editable install runs from an empty folder: `pip install .` copies the meshes,
fibres, data, studies and templates into the package (hyper.core.resources finds them there).

The installed copy goes into a temporary folder (pip install --no-deps --target, from a
copy of the checkout's files, so that the build leaves nothing in the checkout), and runs
with that folder first on PYTHONPATH: the installed hyper is imported, not src/. The
dependencies (DOLFINx, PETSc, ...) are the test interpreter's own."""

import hashlib
import os
import subprocess
import sys
import tarfile
from pathlib import Path

import h5py
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    if not (ROOT / ".git").exists():
        pytest.skip("needs the checkout's files (git ls-files)")
    base = tmp_path_factory.mktemp("install")
    files = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-co", "--exclude-standard", "-z"],
                           capture_output=True, check=True).stdout.decode().split("\0")
    source = base / "source"
    with tarfile.open(base / "source.tar", "w") as tar:
        for name in filter(None, files):
            if (ROOT / name).is_file():
                tar.add(ROOT / name, arcname=name)
    with tarfile.open(base / "source.tar") as tar:
        tar.extractall(source, filter="data")
    target = base / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
                    "--no-index", "--target", str(target), str(source)], check=True, timeout=600)
    env = {**os.environ, "PYTHONPATH": str(target), "OMP_NUM_THREADS": "1"}
    return target, env


def test_the_installed_package_carries_its_inputs(installed):
    target, env = installed
    code = ("import hyper, hyper.fem.geometry as g, hyper.core.resources as r, hyper.commands.slurm as s; "
            "print(hyper.__file__); print(g.MESHES_DIR); print(r.checkout()); "
            "print(all(p.is_file() for p in s.TEMPLATES.values()))")
    lines = subprocess.run([sys.executable, "-c", code], env=env, cwd=target.parent, capture_output=True,
                           text=True, check=True).stdout.split()
    assert lines == [str(target / "hyper" / "__init__.py"), str(target / "hyper" / "meshes"), "None", "True"]
    for name in ("data/defreitas.csv", "studies/paper-cohort.toml", "studies/custom.toml", "jobs/paraview_render.py",
                 "meshes/VHF_Left_Muscle_TibialisAnterior_smooth/fibers.h5",
                 "meshes/muscle-idealized/muscle-idealized.msh"):
        assert (target / "hyper" / name).read_bytes() == (ROOT / name).read_bytes(), name


def test_an_installed_hyper_grows_from_an_empty_folder(installed, tmp_path):
    target, env = installed
    done = subprocess.run([str(target / "bin" / "hyper"), "grow", "--geometry", "idealized", "--protocol", "weekly"],
                          env=env, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    out = tmp_path / "results" / "grow"
    assert sorted(p.name for p in out.iterdir()) == ["idealized_weekly.h5", "idealized_weekly_fields.h5",
                                                    "idealized_weekly_fields.xdmf", "idealized_weekly_growth.png"]
    mesh = ROOT / "meshes/muscle-idealized/muscle-idealized.msh"
    with h5py.File(out / "idealized_weekly.h5") as f:
        assert f.attrs["complete"] and f.attrs["mesh_sha256"] == hashlib.sha256(mesh.read_bytes()).hexdigest()
        assert f.attrs["version_git_commit"] == ""  # not run from a checkout
        assert 1.02 < f["csa_ratio"][-1] < 1.04  # 9 weeks of weekly sessions: +3.0 %
    # the installed study files find their mesh beside them
    code = ("from hyper.analysis import study; from hyper.core import resources; "
            "print(study.load(resources.folder('studies') / 'custom.toml').meshes[0].path.is_file())")
    assert subprocess.run([sys.executable, "-c", code], env=env, cwd=tmp_path, capture_output=True, text=True,
                          check=True).stdout.strip() == "True"
