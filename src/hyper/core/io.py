"""Results on disk: HDF5 time series with provenance, XDMF fields, atomic writes.

A file appears under its final name only once it is whole: writers fill a temporary
name and rename it (an atomic operation on POSIX file systems), and HDF5 files carry
a ``complete`` attribute written last. A killed job leaves at most a ``*.partial``
file behind, which no reader mistakes for a result.
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import functools
import json
import os
import platform
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Mapping
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

import hyper
from hyper.core import resources, term
from hyper.core.params import InputError, input_file, read_text

PARTIAL = ".partial"


# Where results never go: the kernel's and the devices' pseudo file systems.
SYSTEM_TREES = (Path("/proc"), Path("/sys"), Path("/dev"))


def unwritable(path: Path, *, folder: bool | None, inputs=(), replaces: bool = False) -> str | None:
    """Why ``path`` cannot be written as a file (``folder`` False), a folder (True) or
    either (None); None where it can. Looks only, creates nothing.

    An existing folder must itself be writable (the job writes into it), not only its
    parent. ``inputs`` are the files the job reads: the output may not be one of them, nor,
    where the job ``replaces`` the folder whole (mesh --force), hold one of them.
    """
    absolute = Path(os.path.abspath(path))
    for tree in SYSTEM_TREES:
        if absolute == tree or tree in absolute.parents:
            return f"{path}: under {tree}, not a place for results"
    real = Path(os.path.realpath(absolute))
    for source in inputs:
        if not os.path.exists(source):  # nothing to destroy; the job says it is missing
            continue
        read = Path(os.path.realpath(source))
        if read == real:
            return f"{path}: is an input of this job ({source}); writing it would destroy it"
        if replaces and real in read.parents:
            return f"{path}: holds an input of this job ({source}); replacing the folder would delete it"
    if absolute.exists():
        if folder is True and not absolute.is_dir():
            return f"{path}: exists and is not a folder"
        if folder is False and absolute.is_dir():
            return f"{path}: is a folder, not a file"
        if folder is False and not absolute.is_file():
            return f"{path}: exists and is not a regular file"
        if absolute.is_dir() and not os.access(absolute, os.W_OK | os.X_OK):
            return f"{path}: the folder is not writable"
    ancestor = absolute.parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        return f"{path}: {ancestor} is a file, not a folder"
    if not os.access(ancestor, os.W_OK | os.X_OK):
        return f"{path}: {ancestor} is not writable"
    return None


# The command this process runs, as the user typed it: `hyper.commands.cli.entry` records
# it, and whatever records a run reads it here (`write_series`, a failed run's status file).
_command: list[str] = []


def record_command(words: list[str]) -> None:
    _command[:] = [str(w) for w in words]


def command() -> list[str]:
    """The words of the recorded command (none if no command was recorded)."""
    return list(_command)


@functools.cache
def git_commit() -> str:
    """The checkout's commit (+ "-dirty" with uncommitted changes); "" outside a checkout."""

    root = resources.checkout()
    if root is None or not (root / ".git").exists():
        return ""
    try:
        with term.spawning():
            head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                                  timeout=10, check=True).stdout.strip()
            dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                                   capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""
    return head + ("-dirty" if dirty else "")


@functools.cache
def _installed_versions() -> dict[str, str]:
    """The versions of the packages a result depends on, read once per process: the
    package metadata cost a checkpoint 15 ms, and importing scipy for its version 50 ms."""
    import h5py

    out = {
        "hyper": hyper.__version__,
        "git_commit": git_commit(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "h5py": h5py.__version__,
    }
    for package in ("scipy", "SALib", "mpi4py"):
        try:
            out[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            pass
    return out


def versions() -> dict[str, str]:
    """The versions of everything a result depends on."""
    out = dict(_installed_versions())
    mpi = sys.modules.get("mpi4py.MPI")
    if mpi is not None:
        out["mpi_library"] = mpi.Get_library_version().splitlines()[0].strip()
    # Importing dolfinx or petsc4py starts PETSc, which is collective: never here, on one rank.
    dolfinx = sys.modules.get("dolfinx")
    if dolfinx is not None:
        out["dolfinx"] = dolfinx.__version__
    petsc = sys.modules.get("petsc4py.PETSc")
    if petsc is not None:
        out["petsc4py"] = sys.modules["petsc4py"].__version__
        out["petsc"] = ".".join(str(v) for v in petsc.Sys.getVersion())
    return out


# The unit of each series a run writes; a state's spread has the state's unit.
UNITS = {
    "t": "h", "csa_ratio": "1", "volume_ratio": "1", "kM": "1/h", "newton_iterations": "count",
    "halvings": "count", "wall_s": "s", "igf1": "1", "akt": "1", "foxo": "1", "mtor": "1", "N": "1",
    "csa_ratio_sections": "1", "detraining": "h",
    "final_x": "m", "final_u": "m", "final_N": "1", "final_detGbar": "1",
}


def unit(name: str) -> str:
    """The unit of a series by its name (the signaling states are normalized: 1)."""
    return UNITS.get(name.removesuffix("_std"), "unspecified")


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


# What a write meets when the disk, not the job, is at fault: full, over quota, failing.
DISK_FAULTS = (errno.ENOSPC, errno.EDQUOT, errno.EIO)


class WriteFailed(OSError):
    """A file could not be written for want of room or a failing disk: one line that names
    the file (`hyper.commands.cli.entry` reports it as one ``error:`` line, exit status 3).
    An OSError, so that what handles a failed write (the checkpoint's status) still does."""

    def __str__(self) -> str:  # the message alone, without OSError's "[Errno 28]"
        return str(self.strerror if self.strerror is not None else super().__str__())


def write_failed(path: str | Path, err: BaseException) -> WriteFailed | None:
    """``err`` as a `WriteFailed` on ``path`` where it is a disk fault (h5py's OSError for
    one carries the errno too), None where it is anything else. HDF5's own text, which
    spans lines, is left out: the errno says what happened."""
    if isinstance(err, WriteFailed):
        return err
    if not isinstance(err, OSError) or err.errno not in DISK_FAULTS:
        return None
    return WriteFailed(err.errno, f"{path}: cannot write: {os.strerror(err.errno)}; nothing was written there, "
                                  "make room and run the same command again")


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success move it into place.

    On failure the temporary file is removed and the old ``path`` (if any) is untouched;
    a full or failing disk raises `WriteFailed`. Every file a job writes passes here.
    """
    path = Path(path)
    tmp = path.with_name(path.name + PARTIAL)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as err:
        tmp.unlink(missing_ok=True)
        fault = write_failed(path, err)
        if fault is not None:
            raise fault from None
        raise


def write_json(path: str | Path, data: Any, *, indent: int | None = 2) -> Path:
    """A JSON file, written atomically (`atomic_path`); numpy scalars as floats."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=indent, default=float) + "\n")
    return Path(path)


def write_series(
    path: str | Path,
    series: Mapping[str, Any],
    attrs: Mapping[str, Any] | None = None,
    groups: Mapping[str, Mapping[str, Any]] | None = None,
    units: Mapping[str, str] | None = None,
) -> Path:
    """Write 1-D datasets (and optional attribute groups) to an HDF5 file, atomically.

    Call on one rank only. ``groups`` maps a group name to its attributes (e.g. the
    parameters, the protocol); versions, the command and a timestamp are added to the
    root, and each dataset gets a ``units`` attribute (``units``, else `UNITS`).
    """
    import h5py

    path = Path(path)
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            for name, data in series.items():
                f.create_dataset(name, data=np.asarray(data)).attrs["units"] = (units or {}).get(name, unit(name))
            for gname, gattrs in (groups or {}).items():
                set_attrs(f.require_group(gname), gattrs)
            set_attrs(f, attrs or {})
            set_attrs(f, {f"version_{k}": v for k, v in versions().items()})
            if _command:
                f.attrs["command"] = " ".join(_command)
            f.attrs["created"] = datetime.datetime.now(datetime.UTC).isoformat()
            f.attrs["complete"] = True
    return path


# What h5py raises on a file that is not whole: OSError (no HDF5 signature, a bad object
# header), RuntimeError (a damaged B-tree or heap), KeyError (an object its links name is
# not there) and ValueError (a datatype or dataspace it cannot make sense of).
HDF5_ERRORS = (OSError, RuntimeError, KeyError, ValueError)


def _reason(err: Exception) -> str:
    """An h5py error in words (a KeyError's str() is its message in quotes)."""
    return str(err.args[0]) if isinstance(err, KeyError) and err.args else str(err) or type(err).__name__


@contextlib.contextmanager
def reading_h5(path: str | Path, what: str = "HDF5 result file") -> Iterator[Any]:
    """The open h5py.File of a file a job reads back (a result, a checkpoint, the data of
    an XDMF file). Any HDF5 error in opening it or in the block, which should only read
    it, is one InputError naming the file and what HDF5 found: a damaged or truncated
    file is bad input, not a traceback."""
    import h5py

    path = input_file(path, f"an {what}")
    try:
        with h5py.File(path, "r") as f:
            yield f
    except InputError:
        raise
    except HDF5_ERRORS as err:
        raise InputError(f"{path}: not a readable {what} ({_reason(err)})") from None


def is_complete(path: str | Path) -> bool:
    """True if ``path`` is an HDF5 file whose writer finished (a damaged one: False)."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return bool(f.attrs.get("complete", False))
    except HDF5_ERRORS:
        return False


def read_series(path: str | Path) -> dict[str, np.ndarray]:
    """All root datasets of a complete series file; a partial file is an error (OSError),
    a damaged one an InputError (`reading_h5`)."""
    import h5py

    if not is_complete(path):
        raise OSError(f"{path}: missing or incomplete (no 'complete' mark)")
    with reading_h5(path) as f:
        return {k: f[k][()] for k in f if isinstance(f[k], h5py.Dataset)}


def read_xml(path: str | Path, what: str = "XDMF file") -> ET.Element:
    """The root element of an XML input (`read_text`: UTF-8 only); InputError naming the
    file and the line where it is not well-formed."""
    try:
        return ET.fromstring(read_text(path, what))
    except ET.ParseError as err:
        raise InputError(f"{path}: not a well-formed {what} ({err})") from None


def xml_child(element: ET.Element, tag: str, path: str | Path) -> ET.Element:
    """``element.find(tag)``, an InputError naming the file where it is not there."""
    found = element.find(tag)
    if found is None:
        raise InputError(f"{path}: a <{element.tag}> without <{tag}>")
    return found


def xml_attribute(element: ET.Element, name: str, path: str | Path) -> str:
    """``element.get(name)``, an InputError naming the file where it is not there."""
    value = element.get(name)
    if value is None:
        raise InputError(f"{path}: a <{element.tag}> without its {name} attribute")
    return value


def one_grid(xml: str) -> str:
    """DOLFINx's XDMF of functions written over time, as one temporal collection of grids
    that each carry every function.

    DOLFINx writes the mesh as a grid of its own and each function as its own temporal
    collection: ParaView's Xdmf3 reader opens that as blocks to merge, meshio's time-series
    reader sees the last collection only and `meshio.read` none. Here each time at which
    any function was written is one grid: the mesh (the same HDF5 datasets, referenced
    again) and every function, a function written less often (the fibres, once) with the
    value it was last written with. The HDF5 file is untouched.
    """

    domain = ET.fromstring(xml).find("Domain")
    grids = list(domain)
    mesh = next(g for g in grids if g.get("GridType") == "Uniform")
    shape = [mesh.find("Topology"), mesh.find("Geometry")]
    written: dict[str, list[tuple[float, str, ET.Element]]] = {}
    for collection in grids:
        if collection.get("GridType") != "Collection":
            continue
        for grid in collection.findall("Grid"):
            attribute, value = grid.find("Attribute"), grid.find("Time").get("Value")
            written.setdefault(attribute.get("Name"), []).append((float(value), value, attribute))
    times = sorted({(t, text) for rows in written.values() for t, text, _ in rows})
    root = ET.Element("Xdmf", Version="3.0")
    series = ET.SubElement(ET.SubElement(root, "Domain"), "Grid", Name="fields", GridType="Collection",
                           CollectionType="Temporal")
    for t, text in times:
        grid = ET.SubElement(series, "Grid", Name="fields", GridType="Uniform")
        grid.extend(shape)
        ET.SubElement(grid, "Time", Value=text)
        for rows in written.values():
            held = [attribute for when, _, attribute in rows if when <= t]
            if held:
                grid.append(held[-1])
    ET.indent(root)
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


# DOLFINx's HDF5 cannot fail a write cleanly: on a full disk it prints pages of HDF5-DIAG,
# its close raises, and HDF5 then aborts the process (exit 134). So every write to an XDMF
# file first checks that the disk has room for it, and a want of room is a `WriteFailed`
# before HDF5 sees any of it. The room asked for is the arrays' bytes (on every rank) times
# ROOM_FACTOR, for HDF5's chunks and metadata and the XML, plus ROOM_SLACK.
ROOM_FACTOR = 2.0
ROOM_SLACK = 64 * 1024  # bytes


class RoomCheckedXDMF:
    """A dolfinx XDMFFile whose writes each check, collectively, that the disk holding
    ``path`` has room for them (`ROOM_FACTOR`); anything else is the file's own."""

    def __init__(self, xdmf, comm, path: Path, shown: Path | None = None):
        self._xdmf, self._comm, self._path = xdmf, comm, path
        self._shown = path if shown is None else shown  # the name a refusal gives

    def _room_for(self, nbytes: int) -> None:
        needed = ROOM_FACTOR * self._comm.allreduce(int(nbytes)) + ROOM_SLACK
        free = shutil.disk_usage(self._path.parent).free if self._comm.rank == 0 else None
        if self._comm.bcast(free, root=0) < needed:
            raise write_failed(self._shown, OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)))

    def write_mesh(self, mesh, *args, **kwargs):
        self._room_for(mesh.geometry.x.nbytes + 8 * mesh.topology.index_map(mesh.topology.dim).size_local
                       * mesh.geometry.dofmaps[0].shape[1])
        return self._xdmf.write_mesh(mesh, *args, **kwargs)

    def write_meshtags(self, tags, *args, **kwargs):
        self._room_for(tags.values.nbytes + tags.indices.nbytes * 4)
        return self._xdmf.write_meshtags(tags, *args, **kwargs)

    def write_function(self, function, *args, **kwargs):
        # a higher-degree field is written at the mesh's nodes: its own dofs are the most
        self._room_for(function.x.array.nbytes + function.function_space.mesh.geometry.x.nbytes)
        return self._xdmf.write_function(function, *args, **kwargs)

    def __getattr__(self, name):
        return getattr(self._xdmf, name)


@contextlib.contextmanager
def room_checked_xdmf(comm, path: str | Path, shown: Path | None = None) -> Iterator[RoomCheckedXDMF]:
    """A new dolfinx XDMFFile at ``path`` for writing, its writes room-checked (a refusal
    names ``shown``, where the file is bound for, if given)."""
    from dolfinx.io import XDMFFile

    with XDMFFile(comm, str(path), "w") as xdmf:
        yield RoomCheckedXDMF(xdmf, comm, Path(path), shown)


@contextlib.contextmanager
def atomic_xdmf(comm, path: str | Path) -> Iterator[Any]:
    """An open dolfinx XDMFFile that appears at ``path`` (with its .h5) only when closed,
    its XML made one temporal series of grids that carry every function (`one_grid`).

    The pair is written into a ``<name>.partial/`` folder, so the .xdmf keeps the
    relative reference to its .h5, and moved into place: the .h5 first, the .xdmf last,
    so a visible .xdmf always has its data. Every write is room-checked
    (`RoomCheckedXDMF`): a full disk is a `WriteFailed` and leaves nothing. Collective
    over ``comm``.
    """
    path = Path(path)
    stage = path.with_name(path.name + PARTIAL)
    if comm.rank == 0:
        shutil.rmtree(stage, ignore_errors=True)
        stage.mkdir(parents=True)
    comm.barrier()
    ok = False
    try:
        with room_checked_xdmf(comm, stage / path.name, shown=path) as xdmf:
            yield xdmf
        ok = True
    finally:
        comm.barrier()
        fault = None
        if comm.rank == 0:
            if ok:
                try:
                    staged = stage / path.name
                    staged.write_text(one_grid(staged.read_text()))
                    h5 = path.with_suffix(".h5")
                    os.replace(stage / h5.name, h5)
                    os.replace(stage / path.name, path)
                except OSError as err:
                    fault = write_failed(path, err)
                    if fault is None:
                        raise
            shutil.rmtree(stage, ignore_errors=True)
        fault = comm.bcast(fault, root=0)
        if fault is not None:
            raise fault


def read_point_field(path: str | Path, name: str) -> tuple[np.ndarray, list[tuple[float, np.ndarray]]]:
    """The mesh's nodes (n, 3) and each snapshot (t, values (n, k)) of the nodal field
    ``name`` in an XDMF file `atomic_xdmf` wrote (one grid per time), in time order.
    InputError where the file or the field is not there."""

    path = Path(path)
    domain = read_xml(path, "XDMF file").find("Domain")
    grids = [] if domain is None else domain.findall("Grid/Grid")

    def data(item) -> np.ndarray:
        text = (item.text or "").strip()
        file, sep, dataset = text.partition(":")
        if not sep:
            raise InputError(f"{path}: a <DataItem> that names no FILE.h5:DATASET ({text!r})")
        try:
            with reading_h5(path.parent / file, "HDF5 data file") as f:
                return f[dataset][()]
        except InputError as err:
            raise InputError(f"{path}: cannot read {text}: {err}") from None

    def time(grid) -> float:
        value = xml_attribute(xml_child(grid, "Time", path), "Value", path)
        try:
            return float(value)
        except ValueError:
            raise InputError(f"{path}: a <Time> whose Value is not a number ({value!r})") from None

    snapshots = []
    for grid in grids:
        for attribute in grid.findall("Attribute"):
            if attribute.get("Name") == name and attribute.get("Center") == "Node":
                snapshots.append((time(grid), data(xml_child(attribute, "DataItem", path))))
    if not snapshots:
        raise InputError(f"{path}: no snapshot of a nodal field {name!r}")
    return data(xml_child(grids[0], "Geometry/DataItem", path)), sorted(snapshots, key=lambda s: s[0])


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
