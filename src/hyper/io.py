"""Results on disk: HDF5 time series with provenance, XDMF fields, atomic writes.

A file appears under its final name only once it is whole: writers fill a temporary
name and rename it (an atomic operation on POSIX file systems), and HDF5 files carry
a ``complete`` attribute written last. A killed job leaves at most a ``*.partial``
file behind, which no reader mistakes for a result.
"""

from __future__ import annotations

import contextlib
import datetime
import os
import platform
import shutil
import sys
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from hyper.params import InputError

PARTIAL = ".partial"


def versions() -> dict[str, str]:
    import h5py
    import scipy

    import hyper

    out = {
        "hyper": hyper.__version__,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "h5py": h5py.__version__,
    }
    # Importing dolfinx starts PETSc, which is collective: never do it here, on one rank.
    dolfinx = sys.modules.get("dolfinx")
    if dolfinx is not None:
        out["dolfinx"] = dolfinx.__version__
    return out


def _attr(value: Any):
    """HDF5 attributes hold numbers, strings and arrays; anything else is stored as text."""
    if isinstance(value, (str, bytes, int, float, np.integer, np.floating, np.bool_, bool)):
        return value
    if isinstance(value, np.ndarray) and value.dtype.kind in "biuf":
        return value
    if isinstance(value, (list, tuple)) and all(isinstance(v, (int, float)) for v in value):
        return np.asarray(value, dtype=float)
    return str(value)


def set_attrs(obj, attrs: Mapping[str, Any]) -> None:
    for key, value in attrs.items():
        obj.attrs[key] = _attr(value)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success move it into place.

    On failure the temporary file is removed and the old ``path`` (if any) is untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + PARTIAL)
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_series(
    path: str | Path,
    series: Mapping[str, Any],
    attrs: Mapping[str, Any] | None = None,
    groups: Mapping[str, Mapping[str, Any]] | None = None,
) -> Path:
    """Write 1-D datasets (and optional attribute groups) to an HDF5 file, atomically.

    Call on one rank only. ``groups`` maps a group name to its attributes (e.g. the
    parameters, the protocol); versions and a timestamp are added to the root.
    """
    import h5py

    path = Path(path)
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            for name, data in series.items():
                f.create_dataset(name, data=np.asarray(data))
            for gname, gattrs in (groups or {}).items():
                set_attrs(f.require_group(gname), gattrs)
            set_attrs(f, attrs or {})
            set_attrs(f, {f"version_{k}": v for k, v in versions().items()})
            f.attrs["created"] = datetime.datetime.now(datetime.UTC).isoformat()
            f.attrs["complete"] = True
    return path


def is_complete(path: str | Path) -> bool:
    """True if ``path`` is an HDF5 file whose writer finished."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return bool(f.attrs.get("complete", False))
    except (OSError, KeyError):
        return False


def read_series(path: str | Path) -> dict[str, np.ndarray]:
    """All root datasets of a complete series file; a partial file is an error."""
    import h5py

    if not is_complete(path):
        raise OSError(f"{path}: missing or incomplete (no 'complete' mark)")
    with h5py.File(path, "r") as f:
        return {k: f[k][()] for k in f if isinstance(f[k], h5py.Dataset)}


@contextlib.contextmanager
def atomic_xdmf(comm, path: str | Path) -> Iterator[Any]:
    """An open dolfinx XDMFFile that appears at ``path`` (with its .h5) only when closed.

    The pair is written into a ``<name>.partial/`` folder, so the .xdmf keeps the
    relative reference to its .h5, and moved into place: the .h5 first, the .xdmf last,
    so a visible .xdmf always has its data. Collective over ``comm``.
    """
    from dolfinx.io import XDMFFile

    path = Path(path)
    stage = path.with_name(path.name + PARTIAL)
    if comm.rank == 0:
        shutil.rmtree(stage, ignore_errors=True)
        stage.mkdir(parents=True)
    comm.barrier()
    ok = False
    try:
        with XDMFFile(comm, str(stage / path.name), "w") as xdmf:
            yield xdmf
        ok = True
    finally:
        comm.barrier()
        if comm.rank == 0:
            if ok:
                h5 = path.with_suffix(".h5")
                os.replace(stage / h5.name, h5)
                os.replace(stage / path.name, path)
            shutil.rmtree(stage, ignore_errors=True)
        comm.barrier()


# what --output may not end in: the name of another kind of file, taken for a folder by mistake
OTHER_SUFFIXES = (".hdf5", ".xdmf", ".png", ".csv", ".json", ".toml", ".txt", ".npy")


def result_paths(out: Path, stems: list[str]) -> list[Path]:
    """The result files of an --output: ``out`` itself (an .h5 file, one run) or STEM.h5
    per run in the folder ``out``; InputError, before anything is written, where neither fits."""
    single_file = out.suffix == ".h5"
    if single_file and len(stems) > 1:
        raise InputError(f"--output {out}: several protocols need a folder, not an .h5 file")
    if out.suffix.lower() in OTHER_SUFFIXES:
        raise InputError(f"--output {out}: expected an .h5 file or a folder, got a {out.suffix} file")
    if not single_file and out.exists() and not out.is_dir():
        raise InputError(f"--output {out}: exists and is not a folder")
    if single_file and out.is_dir():
        raise InputError(f"--output {out}: is a folder; give the result file a name that ends in .h5")
    for parent in (out if not single_file else out.parent, *out.parents):
        if parent.exists() and not parent.is_dir():
            raise InputError(f"--output {out}: {parent} is a file, not a folder")
    return [out] if single_file else [out / f"{stem}.h5" for stem in stems]
