"""Checkpoints of a coupled run, and run digests: the file format, not what is in it.

Checkpoint file (HDF5, one per run, ``{result stem}.ckpt.h5``). Rank 0 gathers the
state and writes it through `hyper.core.io.atomic_path` (temporary name, fsync, rename):
a kill during the write leaves the previous checkpoint in place, never half a file.

    attrs       kind, format, run_digest (the run it belongs to), step, t, segments,
                ranks (that wrote it), created, versions, complete (written last)
    cells/original      (n,) original cell indices (the mesh file's), ascending
    cells/<name>        (n, ...) one row per cell in that order: the model's per-cell
                        state (`hyper.fem.coupled.CoupledModel.state`) and the snapshots
    global/<name>       scalars and small arrays (CSA/V ratios, time, step, protocol
                        position, multipliers, Jacobian count, uniform signaling state,
                        growth amounts and multipliers of the predictor's solutions,
                        multiplier parts of the Newton secant pairs)
    series/<name>       the time series so far

Keyed by the original cell index, the file is read back on any number of ranks: rank
0 reads it and sends each rank the rows of its own cells (owned and ghost), which the
model takes over (`hyper.fem.coupled.CoupledModel.restore`).

A run digest is the SHA-256 of a canonical JSON description of everything that
defines a run's result (geometry, protocol, parameters, settings, solver options); a
checkpoint is resumed only by a run with the same digest.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from hyper.core import io
from hyper.core.params import InputError

KIND = "hyper.grow checkpoint"
FORMAT = 1


# ----------------------------------------------------------------------------- digests


def plain(value: Any):
    """JSON-able form of attribute values: arrays as lists, floats exact (repr)."""
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in sorted(value.items(), key=lambda kv: str(kv[0]))}
    if isinstance(value, np.ndarray):
        return [plain(v) for v in value.tolist()]
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return repr(value) if not math.isfinite(value) else value
    if isinstance(value, Path):
        return str(value)
    return value if value is None or isinstance(value, str) else repr(value)


def digest(description: Mapping[str, Any]) -> str:
    """SHA-256 (hex) of the canonical JSON of ``description``."""
    text = json.dumps(plain(description), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def file_digest(*paths: Path) -> str:
    """SHA-256 of the bytes of the given files, in order."""
    h = hashlib.sha256()
    for path in paths:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


# ------------------------------------------------------------------------- checkpoints


def write(comm, path: Path, original: np.ndarray, per_cell: Mapping[str, np.ndarray],
          glob: Mapping[str, Any], series: Mapping[str, Any], attrs: Mapping[str, Any]) -> None:
    """Write a checkpoint atomically; collective (rank 0 writes).

    ``original``: the original index of each owned cell of this rank; ``per_cell``:
    arrays with one row per owned cell; ``glob``: values equal on every rank.
    """
    names = sorted(per_cell)
    mine = (np.asarray(original, dtype=np.int64), [np.asarray(per_cell[k]) for k in names])
    # one rank: no gather, whose pickling was half of a checkpoint's CPU (0.1 s of 30 MB)
    parts = [mine] if comm.size == 1 else comm.gather(mine, root=0)
    error = None
    if comm.rank == 0:
        try:
            _write(path, parts, names, glob, series, {**attrs, "ranks": comm.size})
        except io.WriteFailed as err:  # a full disk: its one line, which names the file
            error = str(err)
        except Exception as err:  # noqa: BLE001 - every rank raises below
            error = f"{path}: cannot write the checkpoint: {' '.join(str(err).split())}"  # HDF5's text spans lines
    error = comm.bcast(error, root=0)
    if error is not None:
        raise OSError(error)


def _write(path, parts, names, glob, series, attrs) -> None:
    import h5py

    index = np.concatenate([p[0] for p in parts])
    order = np.argsort(index, kind="stable")
    with io.atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            cells = f.create_group("cells")
            cells.create_dataset("original", data=index[order])
            for i, name in enumerate(names):
                cells.create_dataset(name, data=np.concatenate([p[1][i] for p in parts])[order])
            g = f.create_group("global")
            for name, value in glob.items():
                g.create_dataset(name, data=np.asarray(value))
            s = f.create_group("series")
            for name, value in series.items():
                s.create_dataset(name, data=np.asarray(value))
            io.set_attrs(f, {**attrs, "kind": KIND, "format": FORMAT,
                             "created": datetime.datetime.now(datetime.UTC).isoformat()})
            io.set_attrs(f, {f"version_{k}": v for k, v in io.versions().items()})
            f.attrs["complete"] = True


def inspect(path: Path, run_digest: str) -> dict:
    """The attributes of a complete checkpoint that belongs to the run ``run_digest``;
    InputError (naming the file and what to do) otherwise. Cheap: reads attributes only."""
    what = "remove it or pass --restart to start the run again"
    try:
        with io.reading_h5(path, "checkpoint") as f:
            attrs = dict(f.attrs)
    except InputError as err:
        raise InputError(f"{err}; {what}") from None
    if attrs.get("kind") != KIND or not attrs.get("complete", False):
        raise InputError(f"{path}: not a complete hyper.grow checkpoint; {what}")
    if attrs.get("format") != FORMAT:
        raise InputError(f"{path}: checkpoint format {attrs.get('format')}, this version reads {FORMAT}; {what}")
    if attrs.get("run_digest") != run_digest:
        raise InputError(
            f"{path}: the checkpoint belongs to another run (geometry, protocol, parameters, "
            f"settings or solver options differ: run digest {str(attrs.get('run_digest'))[:12]}…, "
            f"this run {run_digest[:12]}…); {what}"
        )
    return attrs


class Checkpoint:
    """A checkpoint read back on some partition: global values, series, attributes and
    ``rows(name)``: a per-cell array for this rank's local cells (or None)."""

    def __init__(self, glob: dict, series: dict, attrs: dict, rows: dict):
        self.glob = glob
        self.series = series
        self.attrs = attrs
        self._rows = rows

    def rows(self, name: str) -> np.ndarray | None:
        return self._rows.get(name)


def read(comm, path: Path, run_digest: str, local_original: np.ndarray) -> Checkpoint:
    """Read a checkpoint of run ``run_digest``; collective. ``local_original``: the
    original index of each local cell (owned then ghost) of this rank."""
    wanted = comm.gather(np.asarray(local_original, dtype=np.int64), root=0)
    payload = None
    if comm.rank == 0:
        try:
            attrs = inspect(path, run_digest)
            try:
                with io.reading_h5(path, "checkpoint") as f:
                    index = f["cells/original"][()]
                    cells = {k: f["cells"][k][()] for k in f["cells"] if k != "original"}
                    glob = {k: f["global"][k][()] for k in f["global"]}
                    series = {k: f["series"][k][()] for k in f["series"]}
            except InputError as err:  # whatever HDF5 raised, damage inside the file too
                raise InputError(f"{err}; remove it or pass --restart") from None
            parts = []
            for want in wanted:
                pos = np.searchsorted(index, want)
                if np.any(pos >= len(index)) or np.any(index[np.minimum(pos, len(index) - 1)] != want):
                    raise InputError(f"{path}: the checkpoint's cells do not match this mesh; "
                                     "remove it or pass --restart")
                parts.append({k: v[pos] for k, v in cells.items()})
            payload = [(glob, series, attrs, part) for part in parts]
        except InputError as err:
            payload = [str(err)] * comm.size
    mine = comm.scatter(payload, root=0)
    if isinstance(mine, str):
        raise InputError(mine)
    return Checkpoint(*mine)
