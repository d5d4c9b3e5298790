"""Checkpoints of a coupled run, run digests, output locks and status files.

Checkpoint file (HDF5, one per run, ``{result stem}.ckpt.h5``). Rank 0 gathers the
state and writes it through `hyper.core.io.atomic_path` (temporary name, fsync, rename):
a kill during the write leaves the previous checkpoint in place, never half a file.

    attrs       kind, format, run_digest (the run it belongs to), step, t, segments,
                ranks (that wrote it), created, versions, complete (written last)
    cells/original      (n,) original cell indices (the mesh file's), ascending
    cells/<name>        (n, ...) one row per cell in that order: the model's per-cell
                        state (see `model_state`) and the snapshots
    global/<name>       scalars and small arrays (CSA/V ratios, time, step, protocol
                        position, multipliers, Jacobian count, uniform signaling state,
                        growth amounts and multipliers of the predictor's solutions,
                        multiplier parts of the Newton secant pairs)
    series/<name>       the time series so far

Keyed by the original cell index, the file is read back on any number of ranks: rank
0 reads it and sends each rank the rows of its own cells (owned and ghost).

A run digest is the SHA-256 of a canonical JSON description of everything that
defines a run's result (geometry, protocol, parameters, settings, solver options); a
checkpoint is resumed only by a run with the same digest.
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import json
import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hyper.core import io
from hyper.core.params import InputError

if TYPE_CHECKING:
    from hyper.fem.coupled import CoupledModel

KIND = "hyper.grow checkpoint"
FORMAT = 1


# ----------------------------------------------------------------------------- digests


def _plain(value: Any):
    """JSON-able form of attribute values: arrays as lists, floats exact (repr)."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in sorted(value.items(), key=lambda kv: str(kv[0]))}
    if isinstance(value, np.ndarray):
        return [_plain(v) for v in value.tolist()]
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
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
    text = json.dumps(_plain(description), sort_keys=True, separators=(",", ":"))
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
        except Exception as err:  # noqa: BLE001 - every rank raises below
            error = f"{path}: cannot write the checkpoint: {err}"
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
    import h5py

    what = "remove it or pass --restart to start the run again"
    try:
        with h5py.File(path, "r") as f:
            attrs = dict(f.attrs)
    except OSError as err:
        raise InputError(f"{path}: cannot read the checkpoint ({err}); {what}") from None
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
    import h5py

    wanted = comm.gather(np.asarray(local_original, dtype=np.int64), root=0)
    payload = None
    if comm.rank == 0:
        try:
            attrs = inspect(path, run_digest)
            with h5py.File(path, "r") as f:
                index = f["cells/original"][()]
                cells = {k: f["cells"][k][()] for k in f["cells"] if k != "original"}
                glob = {k: f["global"][k][()] for k in f["global"]}
                series = {k: f["series"][k][()] for k in f["series"]}
            parts = []
            for want in wanted:
                pos = np.searchsorted(index, want)
                if np.any(pos >= len(index)) or np.any(index[np.minimum(pos, len(index) - 1)] != want):
                    raise InputError(f"{path}: the checkpoint's cells do not match this mesh; "
                                     "remove it or pass --restart")
                parts.append({k: v[pos] for k, v in cells.items()})
            payload = [(glob, series, attrs, part) for part in parts]
        except (InputError, OSError, KeyError) as err:
            payload = [str(err) if isinstance(err, InputError) else
                       f"{path}: cannot read the checkpoint ({err}); remove it or pass --restart"] * comm.size
    mine = comm.scatter(payload, root=0)
    if isinstance(mine, str):
        raise InputError(mine)
    return Checkpoint(*mine)


# ------------------------------------------------------------------- the model's state


def local_original_cells(mesh) -> np.ndarray:
    """The original (mesh file) index of each local cell, owned then ghost."""
    imap = mesh.topology.index_map(mesh.topology.dim)
    return np.asarray(mesh.topology.original_cell_index, dtype=np.int64)[: imap.size_local + imap.num_ghosts]


def model_state(model: CoupledModel) -> tuple[np.ndarray, dict, dict]:
    """(original index of each owned cell, per-cell arrays, global values) of a model.

    Per-cell arrays have one row per owned cell. The mixed solution is stored as
    each cell's own dof values in the element's order: that order follows the cell's
    vertices as the mesh file lists them, so it is the same on any partition (P2 has
    one dof per edge, so no dof transformation enters). Ḡ is per quadrature point of
    the cell, whose points are placed by the same vertex order; what the next growth
    increment needs besides (`hyper.fem.growthfield.GrowthField.directions`) follows from w.
    """
    problem, growth, jacobian = model.problem, model.growth, model.jacobian
    cells = growth.cells
    original = local_original_cells(model.geometry.mesh)[cells]
    wdofs = problem.W.dofmap.list[cells]
    per_cell = {
        "w": problem.w.x.array[wdofs],
        "Gbar": growth.Gbar,
    }
    glob = {
        "multipliers": np.asarray(problem.multipliers, dtype=float),
        "csa_ratio": model.csa_ratio,
        "volume_ratio": model.volume_ratio,
        "t": model.t,
        "step": model.step,
        "period": model.period,
        "period_step": model.period_step,
        "jacobian_count": jacobian.count,
        "csa0": model.csa0,
        "volume0": model.volume0,
        **{name: value for name, value in zip(model.measures, model.csa_ratios.values())},
    }
    if jacobian.point is not None:
        w_j, g_j = jacobian.point
        per_cell["jacobian_w"] = w_j[wdofs]
        per_cell["jacobian_Gbar"] = g_j.reshape(-1, 9)[growth.dofs]
    history = getattr(jacobian, "history", [])  # the solutions kept for a predictor
    if history:
        glob["predictor_amounts"] = np.array([s for s, _, _ in history])
        glob["predictor_multipliers"] = np.array([m for _, _, m in history], dtype=float)
        per_cell["predictor_w"] = np.stack([w_k[wdofs] for _, w_k, _ in history], axis=1)
    if hasattr(jacobian, "secant_state"):
        arrays, multipliers = jacobian.secant_state()
        if arrays:
            per_cell["secant_w"] = np.stack([a[wdofs] for a in arrays], axis=1)
            glob["secant_multipliers"] = multipliers
    per_cell_y = model.y.ndim == 2
    (per_cell if per_cell_y else glob)["y"] = model.y.T if per_cell_y else model.y
    if np.ndim(model.kM):
        per_cell["kM"] = np.asarray(model.kM)
    else:
        glob["kM"] = float(model.kM)
    if model.period_states is not None:
        glob["period_times"] = model.period_times
        if np.ndim(model.period_kM):
            per_cell["period_kM"] = np.asarray(model.period_kM)
        else:
            glob["period_kM"] = float(model.period_kM)
        ys = model.period_states
        if per_cell_y:
            per_cell["period_states"] = np.moveaxis(ys, 2, 0)  # (cell, time, species)
        else:
            glob["period_states"] = ys
    for f in dataclasses.fields(model.params):
        value = getattr(model.params, f.name)
        if isinstance(value, np.ndarray):
            per_cell[f"params.{f.name}"] = value
    return original, per_cell, glob


def restore_model(model: CoupledModel, rows: Callable[[str], np.ndarray | None], glob: Mapping[str, Any]) -> None:
    """Take over a state saved by `model_state` (on any partition).

    ``rows(name)`` gives a per-cell array for this rank's cells, owned then ghost (the
    local cell numbering), or None where the state has no such array.
    """
    import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
    from dolfinx import fem

    problem, growth = model.problem, model.growth
    nowned = len(growth.cells)
    mesh = model.geometry.mesh
    nlocal = nowned + mesh.topology.index_map(mesh.topology.dim).num_ghosts
    local = np.arange(nlocal, dtype=np.int32)
    wdofs = problem.W.dofmap.list[local]
    w = problem.w
    w.x.array[wdofs] = rows("w")
    w.x.scatter_forward()
    problem.multipliers = np.array(glob["multipliers"], dtype=float)
    growth.set(np.array(rows("Gbar")[:nowned]))  # after w: the fibre directions come from it

    # per-cell parameters (random fields) come from the state: they are part of it
    names = [f"params.{f.name}" for f in dataclasses.fields(model.params)]
    params = {name.split(".", 1)[1]: rows(name)[:nowned] for name in names if rows(name) is not None}
    if params:
        model.params = dataclasses.replace(model.params, **params)
        model.kM0 = model.params.kM
    y = rows("y")
    model.y = np.ascontiguousarray(y[:nowned].T) if y is not None else np.array(glob["y"], dtype=float)
    kM = rows("kM")
    model.kM = np.array(kM[:nowned]) if kM is not None else float(glob["kM"])
    model.csa_ratio = float(glob["csa_ratio"])
    model.volume_ratio = float(glob["volume_ratio"])
    # a checkpoint from before both CSA measures were kept has neither: unknown until measured
    model.csa_ratios = {method: float(glob[name]) if name in glob else float("nan")
                        for method, name in zip(model.csa_ratios, model.measures)}
    model.t = float(glob["t"])
    model.step = int(glob["step"])
    model.period = int(glob["period"])
    model.period_step = int(glob["period_step"])
    if "period_times" in glob:
        model.period_times = np.array(glob["period_times"], dtype=float)
        ys = rows("period_states")
        model.period_states = (np.ascontiguousarray(np.moveaxis(ys[:nowned], 0, 2)) if ys is not None
                               else np.array(glob["period_states"], dtype=float))
        kM = rows("period_kM")
        if kM is not None:
            model.period_kM = np.array(kM[:nowned])
        else:  # uniform; or a checkpoint from before it was kept (only the left-point increment reads it)
            model.period_kM = float(glob["period_kM"]) if "period_kM" in glob else model.kM
    else:
        model.period_times = model.period_states = None

    point = None
    jw = rows("jacobian_w")
    if jw is not None:
        pw = np.zeros_like(w.x.array)
        pw[wdofs] = jw
        g = fem.Function(growth.space)
        g.x.array.reshape(-1, 9)[growth.dofs.ravel()] = rows("jacobian_Gbar")[:nowned].reshape(-1, 9)
        g.x.scatter_forward()
        point = (pw, g.x.array.copy())
    model.jacobian.rebuild(int(glob["jacobian_count"]), point)
    kept = rows("predictor_w")
    if kept is not None and hasattr(model.jacobian, "history"):
        history = []
        for i, amount in enumerate(np.asarray(glob["predictor_amounts"], dtype=float)):
            w_k = np.zeros_like(w.x.array)
            w_k[wdofs] = kept[:, i]
            history.append((float(amount), w_k, np.array(glob["predictor_multipliers"][i], dtype=float)))
        model.jacobian.history = history
    pairs = rows("secant_w")
    if pairs is not None and hasattr(model.jacobian, "restore_secants"):
        arrays = []
        for i in range(pairs.shape[1]):
            a = np.zeros_like(w.x.array)
            a[wdofs] = pairs[:, i]
            arrays.append(a)
        model.jacobian.restore_secants(arrays, np.asarray(glob["secant_multipliers"], dtype=float))
    model.resumed = True


# ------------------------------------------------------------------------ status files


def write_status(path: Path, status: Mapping[str, Any]) -> None:
    """A JSON status file, written atomically (call on one rank)."""
    text = json.dumps(_plain({**status, "written": datetime.datetime.now(datetime.UTC).isoformat()}), indent=2)
    with io.atomic_path(path) as tmp:
        tmp.write_text(text + "\n")


def read_status(path: Path) -> dict:
    return json.loads(Path(path).read_text())


def on_rank0(comm, action: Callable[[], Any]) -> Any:
    """Run ``action`` on rank 0 and raise its error on every rank (collective)."""
    result = error = None
    if comm.rank == 0:
        try:
            result = action()
        except Exception as err:  # noqa: BLE001 - re-raised on every rank below
            error = err
    error = comm.bcast(error, root=0)
    if error is not None:
        raise error
    return comm.bcast(result, root=0)
