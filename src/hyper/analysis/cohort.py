"""python -m hyper.cohort: the anatomical cohort of the paper's Fig. 6 on an MPI job farm.

    mpirun -n 2 python -m hyper.cohort                      # 12 meshes × mwf, every3days, weekly
    mpirun -n 4 python -m hyper.cohort --ranks-per-job 2    # 2 groups of 2 ranks
    python -m hyper.cohort --geometries BFLH_VHF_Left --protocols mwf my_protocol.toml

Every (geometry, protocol) pair is one job of `hyper.runs.farm` (longest first, by the
estimate mesh cells × growth steps), run by `hyper.runs.driver.execute` on its group's
communicator. Per run, under OUTPUT/runs/:

    GEOMETRY_PROTOCOL.h5            the time series (as hyper.grow writes it) with the
                                    attributes geometry, muscle, subject, side, protocol,
                                    csa0_m2, volume0_m3, wall_s, ranks, run_digest and
                                    the groups signaling, material, protocol, settings
                                    and the equivalent study file (hyper.runs.provenance)
    GEOMETRY_PROTOCOL_fields.xdmf   snapshots of u, det Ḡ and a0 every --snapshot-every
                                    simulated hours (ParaView, meshio's TimeSeriesReader)
    GEOMETRY_PROTOCOL.log           the run's own progress lines

and for the cohort, written by rank 0 from the complete .h5 files (so a rerun that had
nothing left to do writes the same summary):

    summary.csv     geometry,muscle,subject,side,protocol,csa0_cm2,volume0_cm3,
                    final_csa_ratio,final_csa_ratio_cut,final_csa_ratio_box,
                    final_volume_ratio,wall_s,data_rmse_pp,data_last_difference_pp,
                    status (final_csa_ratio is the one --csa-method feeds back; cut
                    and box are blank on meshes with a tagged mid-section; data_*:
                    against --data, or the protocol's own data set, in percentage
                    points; blank without)
    failures.txt    the error of every failed run (only when some failed)
    ratios.png      final CSA and volume change by muscle and protocol, mean ± standard
                    error over the four members of each muscle (Fig. 6C–D analog)
    shape.png       the grown --plot-geometry geometry (BFLH_VHF_Left, or the first) per protocol,
                    displacement amplified 10× (Fig. 6A analog)
    table.md        the results against the paper (MODEL.md §8)

Rerunning the same command skips every run whose .h5 is complete and was computed with
the same geometry, protocol, signaling parameters and settings (hyper.runs.driver's
`RunSpec.digest`); the others run again. Each run saves a checkpoint every
hyper.runs.driver.CHECKPOINT_EVERY growth steps (runs/GEOMETRY_PROTOCOL.ckpt.h5, deleted when
its series is stored), so after a kill (Ctrl-C, a Slurm time limit) the same command
resumes the interrupted runs where they were; a run that failed keeps its checkpoint
and resumes from it. Files appear only when whole (hyper.core.io). One cohort at a time
writes an output folder (the lock OUTPUT.lock). On SIGTERM (what Slurm sends before a
time limit) the running runs stop at their next growth step with a checkpoint, the
others are not started, and the summary marks them `interrupted`. Exit status: 0 all
runs done, 1 some failed (see failures.txt), 2 bad options (nothing written), 4 the
output is locked, 143 stopped by SIGTERM (run the same command again to continue).
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import math
import sys
import threading
import time
import traceback
from collections.abc import Mapping
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
import numpy as np
from mpi4py import MPI

from hyper.commands import cli
from hyper.core import io
from hyper.core.collective import on_rank0
from hyper.core.log import PROGRESS_EVERY, hms, info
from hyper.core.params import InputError
from hyper.fem import geometry as geo
from hyper.fem.coupled import CSA_METHODS, GrowthSettings
from hyper.model import material, protocols, signaling
from hyper.model.growth import step_times
from hyper.model.protocols import Protocol
from hyper.runs import checkpoint as ckpt
from hyper.runs import driver as run
from hyper.runs import farm, locks, measured, plot, presets, runspec

COLUMNS = ("geometry", "muscle", "subject", "side", "protocol", "csa0_cm2", "volume0_cm3",
           "final_csa_ratio", "final_csa_ratio_cut", "final_csa_ratio_box", "final_volume_ratio", "wall_s",
           "data_rmse_pp", "data_last_difference_pp", "status")
# the summary's numbers: CSA by the feedback's method and by each method, and against
# measured CSA (blank without them)
NUMBERS = ("csa0_cm2", "volume0_cm3", "final_csa_ratio", "final_csa_ratio_cut", "final_csa_ratio_box",
           "final_volume_ratio", "wall_s", "data_rmse_pp", "data_last_difference_pp")
PAPER_PROTOCOLS = protocols.PAPER  # in the paper's order of growth: mwf > every3days > weekly
# MODEL.md §8, anatomical cohort under mwf: increases in percent (low, high)
PAPER_MWF_INCREASE = {"volume": (8.0, 9.0), "csa": (3.0, 6.0)}
PICTURE_SCALE = 10.0  # displacement amplification of the shape picture (the paper's Fig. 6A)
SHAPE_GEOMETRY = "BFLH_VHF_Left"  # the paper's Fig. 6A


@dataclasses.dataclass(frozen=True)
class Run:
    geometry: str  # a built-in geometry id, or the stem of ``mesh``
    protocol: Protocol
    mesh: runspec.MeshFile | None = None  # a user's mesh file (hyper study); None: the built-in geometry

    @property
    def key(self) -> str:
        return f"{self.geometry}_{self.protocol.name}"


def plan(geometries, protocol_list, meshes: Mapping[str, runspec.MeshFile] | None = None) -> list[Run]:
    """Every geometry with every protocol; names must make unique run keys. ``meshes``
    maps the geometries that are a user's mesh file to it."""
    meshes = meshes or {}
    runs = [Run(g, p, meshes.get(g)) for g in geometries for p in protocol_list]
    keys = [r.key for r in runs]
    repeated = sorted({k for k in keys if keys.count(k) > 1})
    if repeated:
        raise InputError(f"runs must be unique (check --geometries and the protocol names); repeated: "
                         f"{', '.join(repeated)}")
    return runs


def member(geometry: str) -> dict[str, str]:
    """muscle, subject and side of an anatomical geometry (or a meshed one named M_S_side); blank for the others."""
    if geometry in geo.ANATOMICAL or (geometry in geo.MESHED and geometry.count("_") == 2):
        return dict(zip(("muscle", "subject", "side"), geo.split_id(geometry)))
    return {"muscle": "", "subject": "", "side": ""}


def mesh_cells(geometry: str, path: Path | None = None) -> int:
    """The number of cells of a project mesh (or of the mesh file ``path``), read from its
    file header (no mesh built)."""
    import h5py

    path = geo.MESHES_DIR / geo.GEOMETRIES[geometry] if path is None else Path(path)
    data = path.with_suffix(".h5") if path.suffix == ".xdmf" else path
    if path.suffix == ".xdmf":
        with h5py.File(data, "r") as f:
            if "Mesh/Grid/topology" in f:
                return int(f["Mesh/Grid/topology"].shape[0])
    # The Gmsh meshes are small, and a user's mesh may name its datasets otherwise: the
    # file size (about 100 bytes a cell) suffices to order the jobs.
    return max(1, data.stat().st_size // 100)


def growth_steps(protocol: Protocol, growth_dt: float) -> int:
    return sum(len(step_times(t0, t1, growth_dt)) - 1 for t0, t1, _ in protocol.periods())


def spec(entry: Run, params, settings: GrowthSettings, options: Mapping | None = None) -> runspec.RunSpec:
    """The run of ``entry``; ``options`` more `RunSpec` fields (heterogeneity, seed,
    linear_solver, choice, quadrature_degree: what a study file sets)."""
    return runspec.RunSpec(entry.geometry, entry.protocol, params, settings, mesh=entry.mesh, **(options or {}))


def series_path(output: Path, entry: Run) -> Path:
    return Path(output) / "runs" / f"{entry.key}.h5"


def drop_stale_checkpoint(path: Path, digest: str) -> None:
    """Remove a checkpoint that another run (other settings) left, or a broken one: the
    cohort starts that run afresh rather than failing on it."""
    if path.is_file():
        try:
            ckpt.inspect(path, digest)
        except InputError:
            path.unlink()


class _RunLog:
    """While a run computes, what the calling thread prints (the run's own progress) goes
    to the run's log file; other threads still print to the terminal. On rank 0 the farm's
    server thread prints the other groups' progress while rank 0 computes a run of its own."""

    def __init__(self, path: Path):
        self.path = path

    def __enter__(self):
        self.file = open(self.path, "a")  # a resumed run adds to its log
        self.thread = threading.get_ident()
        self.terminal = sys.stdout
        sys.stdout = self
        return self

    def write(self, text: str) -> int:
        return (self.file if threading.get_ident() == self.thread else self.terminal).write(text)

    def flush(self) -> None:
        self.file.flush()
        self.terminal.flush()

    def __exit__(self, *exc):
        sys.stdout = self.terminal
        self.file.close()


def run_cohort(comm, runs: list[Run], output: Path, *, params=None, settings: GrowthSettings | None = None,
               snapshot_every: float = run.SNAPSHOT_EVERY, ranks_per_job: int = 1, stop=None,
               options: Mapping | None = None, data: measured.Measured | None = None,
               progress_every: float = PROGRESS_EVERY) -> list[farm.JobResult]:
    """Run every run not done before on the farm; collective over ``comm``.

    Each run checkpoints every run.CHECKPOINT_EVERY growth steps (runs/KEY.ckpt.h5) and
    resumes from its checkpoint, so a killed cohort loses at most that much per run.
    ``stop()`` turning true (run.StopOnTerm: SIGTERM) stops the running runs at their
    next step boundary with a checkpoint, and the runs not started yet at once; their
    results are ``{"interrupted": True}``. ``options``: more `RunSpec` fields for every run (`spec`).
    Each run is compared with ``data`` (None: its protocol's own data set, if any; `hyper.runs.measured`),
    its error stored in its result's ``data`` group. Progress lines come at most every
    ``progress_every`` s, the farm's on the terminal and each run's in its log.
    """
    params = signaling.SignalingParams() if params is None else params
    settings = GrowthSettings() if settings is None else settings
    output = Path(output)
    specs = {r.key: spec(r, params, settings, options) for r in runs}
    digests = {key: s.digest() for key, s in specs.items()}
    jobs = [farm.Job(r.key, cost=float(mesh_cells(r.geometry, r.mesh and r.mesh.path)
                                       * growth_steps(r.protocol, settings.growth_dt)), payload=r) for r in runs]
    if comm.rank == 0:
        (output / "runs").mkdir(parents=True, exist_ok=True)

    def is_done(job):
        return runspec.Outputs(series_path(output, job.payload)).is_current(digests[job.key])

    def work(subcomm, job):
        entry: Run = job.payload
        interrupted = {"interrupted": True} if subcomm.rank == 0 else None
        if subcomm.allreduce(bool(stop is not None and stop()), op=MPI.LOR):
            return interrupted
        out = runspec.Outputs(series_path(output, entry))
        on_rank0(subcomm, lambda: drop_stale_checkpoint(out.checkpoint, digests[entry.key]))
        try:
            with _RunLog(out.h5.with_suffix(".log")) if subcomm.rank == 0 else contextlib.nullcontext():
                done = run.execute(subcomm, specs[entry.key], out, snapshot_every=snapshot_every, stop=stop,
                                   progress_every=progress_every)
        except run.Interrupted:
            return interrupted
        if subcomm.rank != 0:
            return None
        groups = runspec.result_groups(specs[entry.key], done.choice)
        against = data if data is not None else measured.of_protocol(entry.protocol)
        if against is not None:
            groups["data"] = measured.compare(against, done.series["t"], done.series["csa_ratio"]).attributes()
        out.store(done.series, {**done.meta, **member(entry.geometry), "protocol": entry.protocol.name}, groups)
        return {"csa_ratio": float(done.series["csa_ratio"][-1]),
                "volume_ratio": float(done.series["volume_ratio"][-1])}

    return farm.run(comm, jobs, work, ranks_per_job=ranks_per_job, is_done=is_done, label="cohort",
                    progress_every=progress_every)


# --------------------------------------------------------------------------------------
# Summary and statistics (rank 0, plain numbers)


def summary_row(path: Path) -> dict:
    """The summary row of a complete series file."""
    import h5py

    with h5py.File(path, "r") as f:
        a = f.attrs
        return {
            "geometry": str(a["geometry"]), "muscle": str(a["muscle"]), "subject": str(a["subject"]),
            "side": str(a["side"]), "protocol": str(a["protocol"]),
            "csa0_cm2": float(a["csa0_m2"]) * 1e4, "volume0_cm3": float(a["volume0_m3"]) * 1e6,
            "final_csa_ratio": float(f["csa_ratio"][-1]),
            **{f"final_csa_ratio_{m}": float(f[f"csa_ratio_{m}"][-1]) if f"csa_ratio_{m}" in f else float("nan")
               for m in CSA_METHODS},
            "final_volume_ratio": float(f["volume_ratio"][-1]), "wall_s": float(a["wall_s"]),
            # against measured CSA (hyper.runs.measured), where the run was compared with some
            "data_rmse_pp": float(f["data"].attrs["rmse_pp"]) if "data" in f else float("nan"),
            "data_last_difference_pp": float(f["data"].attrs["last_difference_pp"]) if "data" in f else float("nan"),
            "status": "done",
        }


def summarize(output: Path, runs: list[Run], failed: dict[str, str], interrupted=()) -> list[dict]:
    """One row per run, in the order of ``runs``: read back from its complete file, or
    marked failed (``failed``: run key -> error), interrupted or missing, with blank numbers."""
    rows = []
    for entry in runs:
        path = series_path(output, entry)
        if entry.key not in failed and io.is_complete(path):
            rows.append(summary_row(path))
            continue
        row = dict.fromkeys(COLUMNS, float("nan"))
        row.update(geometry=entry.geometry, protocol=entry.protocol.name, **member(entry.geometry),
                   status="failed" if entry.key in failed else "interrupted" if entry.key in interrupted else "missing")
        rows.append(row)
    return rows


def write_csv(rows: list[dict], path: Path) -> None:
    with io.atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: ("" if isinstance(v, float) and math.isnan(v) else
                                 repr(v) if isinstance(v, float) else v) for k, v in row.items()})


def read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    for row in rows:
        for key in NUMBERS:
            row[key] = float(row[key]) if row.get(key) else float("nan")
    return rows


def standard_error(values) -> float:
    """Standard error of the mean, s/√n with the sample standard deviation; NaN for n < 2."""
    values = np.asarray(values, dtype=float)
    if values.size < 2:
        return float("nan")
    return float(values.std(ddof=1) / np.sqrt(values.size))


def group(row: dict) -> str:
    """The group a run belongs to in the statistics: its muscle, or its geometry if it has none."""
    return row["muscle"] or row["geometry"]


def ratio_column(quantity: str) -> str:
    """The summary column of ``quantity``: 'csa', 'volume', or 'csa_cut', 'csa_box' (one CSA measure)."""
    name, _, method = quantity.partition("_")
    return f"final_{name}_ratio" + (f"_{method}" if method else "")


def percent(row: dict, quantity: str) -> float:
    """The final relative increase of ``quantity`` (`ratio_column`) in percent."""
    return 100.0 * (row[ratio_column(quantity)] - 1.0)


def group_statistics(rows: list[dict], quantity: str) -> dict[tuple[str, str], dict]:
    """(group, protocol) -> n, mean and standard error of the increase (%) over the done runs."""
    out: dict[tuple[str, str], list[float]] = {}
    for row in rows:
        if row["status"] == "done":
            out.setdefault((group(row), row["protocol"]), []).append(percent(row, quantity))
    return {key: {"n": len(v), "mean": float(np.mean(v)), "se": standard_error(v)} for key, v in out.items()}


def increases(rows: list[dict], geometry: str, quantity: str) -> dict[str, float]:
    """protocol -> increase (%) of one geometry's done runs."""
    return {r["protocol"]: percent(r, quantity) for r in rows if r["geometry"] == geometry and r["status"] == "done"}


def ordered(values: dict[str, float], order=PAPER_PROTOCOLS) -> bool | None:
    """Whether the values strictly decrease along ``order``; None if one is missing."""
    if not all(p in values for p in order):
        return None
    return all(values[a] > values[b] for a, b in zip(order, order[1:]))


def mwf_statistics(rows: list[dict], quantity: str) -> dict | None:
    """Mean, min and max over the geometries of the mwf increase (%), or None without mwf runs."""
    values = [percent(r, quantity) for r in rows if r["protocol"] == "mwf" and r["status"] == "done"]
    if not values:
        return None
    return {"n": len(values), "mean": float(np.mean(values)), "min": float(np.min(values)),
            "max": float(np.max(values))}


def _yes(flag: bool | None) -> str:
    return "–" if flag is None else ("yes" if flag else "**no**")


def markdown(rows: list[dict], settings: GrowthSettings) -> str:
    """The cohort's results against the paper (MODEL.md §8), as markdown."""
    geometries = list(dict.fromkeys(r["geometry"] for r in rows))
    names = list(dict.fromkeys(r["protocol"] for r in rows))
    lines = [f"Final increase after {'/'.join(names)} (growth step {settings.growth_dt:g} h), per geometry:", ""]
    head = ["geometry", *(f"CSA {p}" for p in names), *(f"volume {p}" for p in names)]
    if all(p in names for p in PAPER_PROTOCOLS):
        head.append("mwf > every3days > weekly")
    if "mwf" in names:
        head.append("ΔV > ΔCSA (mwf)")
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    order_ok = vol_ok = 0
    for g in geometries:
        csa, vol = increases(rows, g, "csa"), increases(rows, g, "volume")
        cells = [g, *(f"{csa[p]:+.2f} %" if p in csa else "failed" for p in names),
                 *(f"{vol[p]:+.2f} %" if p in vol else "failed" for p in names)]
        if all(p in names for p in PAPER_PROTOCOLS):
            flag = ordered(csa) and ordered(vol) if ordered(csa) is not None and ordered(vol) is not None else None
            order_ok += bool(flag)
            cells.append(_yes(flag))
        if "mwf" in names:
            flag = vol["mwf"] > csa["mwf"] if "mwf" in csa and "mwf" in vol else None
            vol_ok += bool(flag)
            cells.append(_yes(flag))
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    if all(p in names for p in PAPER_PROTOCOLS):
        lines.append(f"- mwf > every3days > weekly in both CSA and volume: {order_ok} of {len(geometries)} geometries.")
    if "mwf" in names:
        lines.append(f"- relative volume increase > relative CSA increase under mwf: {vol_ok} of {len(geometries)}.")
        lines += ["", "mwf across the geometries against the paper:", "",
                  "| quantity | mean | min | max | paper |", "|---|---|---|---|---|"]
        done = [r for r in rows if r["status"] == "done"]
        measured = [(f"csa_{m}", f"mid-belly CSA increase, {m}") for m in CSA_METHODS
                    if done and all(math.isfinite(r.get(ratio_column(f"csa_{m}"), math.nan)) for r in done)]
        for quantity, label in (("volume", "volume increase"), ("csa", "mid-belly CSA increase"), *measured):
            s = mwf_statistics(rows, quantity)
            lo, hi = PAPER_MWF_INCREASE[quantity.split("_")[0]]
            if s is not None:
                lines.append(f"| {label} (n = {s['n']}) | {s['mean']:+.2f} % | {s['min']:+.2f} % | "
                             f"{s['max']:+.2f} % | +{lo:g}–{hi:g} % |")
    failed = [f"{r['geometry']}/{r['protocol']}" for r in rows if r["status"] != "done"]
    if failed:
        lines += ["", f"Not done: {', '.join(failed)}."]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------
# Figures (rank 0)



def ratio_figure(rows: list[dict], path: Path) -> None:
    """Final CSA and volume change per muscle and protocol: mean ± standard error over the
    members (bars), each member (dots), and the paper's mwf range (grey band)."""
    plt = plot.pyplot()
    groups = list(dict.fromkeys(group(r) for r in rows))
    names = list(dict.fromkeys(r["protocol"] for r in rows))
    width = 0.8 / len(names)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), layout="constrained")
    for ax, quantity, title in ((axes[0], "csa", "mid-belly CSA"), (axes[1], "volume", "volume")):
        stats = group_statistics(rows, quantity)
        if "mwf" in names:
            lo, hi = PAPER_MWF_INCREASE[quantity]
            ax.axhspan(lo, hi, color="0.85", zorder=0, label="paper, mwf")
        for j, name in enumerate(names):
            x = np.arange(len(groups)) + (j - (len(names) - 1) / 2) * width
            cells = [stats.get((g, name), {"mean": np.nan, "se": np.nan}) for g in groups]
            ax.bar(x, [c["mean"] for c in cells], width * 0.9, yerr=[np.nan_to_num(c["se"]) for c in cells],
                   capsize=3, label=name, zorder=2, color=plot.protocol_colour(name))
            for xi, g in zip(x, groups):
                values = [percent(r, quantity) for r in rows
                          if group(r) == g and r["protocol"] == name and r["status"] == "done"]
                ax.plot([xi] * len(values), values, "k.", ms=3, zorder=3)
        ax.set_xticks(range(len(groups)), groups)
        ax.set_ylabel(f"{title} change (%)")
        members = max((sum(group(r) == g and r["protocol"] == n for r in rows) for g in groups for n in names),
                      default=0)
        ax.set_title(f"final {title}: mean ± standard error, dots: members" if members > 1
                     else f"final {title} (one member per bar: no spread)")
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=8)
    plot.save(fig, path, dpi=140)
    plt.close(fig)


def final_fields(xdmf: Path) -> dict:
    """Mesh and the last snapshot of u and det Ḡ from a run's XDMF output (its .h5)."""
    import h5py

    def hours(name: str) -> float:
        return float(name.replace("_", "."))  # DOLFINx names a snapshot by its time, "." as "_"

    with h5py.File(Path(xdmf).with_suffix(".h5"), "r") as f:
        mesh = f["Mesh"][next(iter(f["Mesh"]))]  # one mesh, named after the mesh read
        last = max(f["Function/u"], key=hours)
        return {"x": mesh["geometry"][()], "cells": mesh["topology"][()].astype(np.int64),
                "u": f["Function/u"][last][()], "detGbar": f["Function/detGbar"][last][()].ravel(),
                "t": hours(last)}


def boundary_faces(x: np.ndarray, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The faces of a tetrahedral mesh that belong to one cell only, numbered so that
    their normals (b - a) × (c - a) point out of the mesh, and their cells."""
    local = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
    faces = cells[:, local].reshape(-1, 3)
    _, inverse, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True, return_counts=True)
    once = counts[inverse.ravel()] == 1
    faces, owner = faces[once], np.repeat(np.arange(len(cells)), 4)[once]
    opposite = cells.ravel()[np.flatnonzero(once)]  # local face i is opposite local vertex i
    a, b, c = (x[faces[:, i]] for i in range(3))
    inward = np.einsum("ij,ij->i", np.cross(b - a, c - a), x[opposite] - a) > 0
    faces[inward] = faces[inward][:, ::-1]
    return faces, owner


def shape_figure(fields: dict[str, dict], path: Path, title: str) -> None:
    """The grown shape per protocol (``fields``: protocol -> final_fields), displacement
    amplified PICTURE_SCALE×, long axis upright, boundary faces coloured by |u|."""
    from matplotlib import cm, colors
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    plt = plot.pyplot()
    first = next(iter(fields.values()))
    # Upright frame from the reference vertices: the first principal axis vertical.
    x0 = first["x"]
    centre = x0.mean(axis=0)
    _, vectors = np.linalg.eigh(np.cov((x0 - centre).T))
    frame = vectors[:, ::-1][:, [1, 2, 0]]  # (second, third, first) axis -> (x, y, z)
    top = max(float(np.linalg.norm(f["u"], axis=1).max()) for f in fields.values()) * 1e3
    norm = colors.Normalize(0.0, top)
    fig = plt.figure(figsize=(2.4 * len(fields) + 1.2, 6), layout="constrained")
    for k, (name, f) in enumerate(fields.items()):
        faces, _ = boundary_faces(f["x"], f["cells"])
        y = (f["x"] + PICTURE_SCALE * f["u"] - centre) @ frame * 1e2  # cm
        speed = np.linalg.norm(f["u"], axis=1)[faces].mean(axis=1) * 1e3  # mm
        ax = fig.add_subplot(1, len(fields), k + 1, projection="3d")
        ax.add_collection3d(Poly3DCollection(y[faces], facecolors=cm.viridis(norm(speed)), linewidths=0,
                                             shade=True, lightsource=colors.LightSource(azdeg=225, altdeg=45)))
        lo, hi = y.min(axis=0), y.max(axis=0)
        ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), zlim=(lo[2], hi[2]), xticks=[], yticks=[])
        ax.set_box_aspect(hi - lo)  # equal scales on the three axes
        ax.view_init(elev=15, azim=-60)
        ax.set_title(f"{name}, day {f['t'] / 24:.0f}\nmean det Ḡ {f['detGbar'].mean():.4f}", fontsize=10)
    fig.colorbar(cm.ScalarMappable(norm=norm, cmap="viridis"), ax=fig.axes, shrink=0.6, label="|u| (mm)")
    fig.suptitle(f"{title}: grown shape, displacement ×{PICTURE_SCALE:g} (axis: cm along the muscle)")
    plot.save(fig, path, dpi=140)
    plt.close(fig)


# --------------------------------------------------------------------------------------
# CLI


def parser() -> cli.Parser:
    p = cli.Parser("cohort", __doc__)
    p.add_argument("--geometries", nargs="+", metavar="ID", default=list(geo.ANATOMICAL),
                   help="geometry ids (the 12 anatomical meshes by default; idealized and cylinder work too), "
                        f"or a set: {', '.join(f'{k} ({len(v)})' for k, v in geo.SETS.items())}")
    p.add_argument("--protocols", nargs="+", metavar="NAME|FILE", default=list(PAPER_PROTOCOLS),
                   help=f"named protocols ({', '.join(protocols.NAMES)}) or TOML protocol files")
    p.add_argument("--output", type=cli.output(folder=True), default="results/cohort", help="output folder")
    p.add_argument("--ranks-per-job", type=cli.integer(1), default=1,
                   help="MPI ranks per run; must divide the number of ranks")
    p.add_argument("--growth-dt", type=float,
                   help=f"growth step Δtg (h); {GrowthSettings.growth_dt:g} unless --settings sets it")
    p.add_argument("--material", type=Path, metavar="F.toml",
                   help="TOML file overriding the muscle law's parameters (hyper.model.material.MaterialParams)")
    presets.add_options(p)
    p.add_argument("--max-halvings", type=int, default=GrowthSettings.max_halvings,
                   help="cuts of a growth step whose Newton solve fails before the run fails; a failed run "
                        "resumes from its checkpoint with a larger value")
    p.add_argument("--snapshot-every", type=cli.positive("hours"), default=run.SNAPSHOT_EVERY, metavar="HOURS",
                   help="fields snapshot every HOURS of simulated time, besides the first and the last state")
    p.add_argument("--data", type=Path, metavar="CSV",
                   help="measured CSA to compare every run with (as hyper grow --data); by default each "
                        "protocol's own data set, if it has one (mwf: DeFreitas)")
    cli.progress_option(p)
    p.add_argument("--plot-geometry", metavar="ID",
                   help=f"geometry of the shape plot (the paper's Fig. 6A), one of --geometries; {SHAPE_GEOMETRY} "
                        "when it is one of them, else the first")
    return p


def check(args, comm) -> tuple[list[Run], GrowthSettings, material.MaterialParams]:
    args.geometries = list(dict.fromkeys(n for g in args.geometries for n in geo.SETS.get(g, (g,))))
    unknown = [g for g in args.geometries if g not in geo.GEOMETRIES]
    if unknown:
        raise InputError(f"--geometries: unknown {', '.join(unknown)}; known: {', '.join(geo.GEOMETRIES)}")
    if args.ranks_per_job < 1 or comm.size % args.ranks_per_job:
        raise InputError(f"--ranks-per-job must be >= 1 and divide the number of MPI ranks ({comm.size}), "
                         f"got {args.ranks_per_job}")
    for name in args.geometries:
        runspec.check_geometry(comm, name, "--geometries")
    if args.plot_geometry is None:
        args.plot_geometry = SHAPE_GEOMETRY if SHAPE_GEOMETRY in args.geometries else args.geometries[0]
    elif args.plot_geometry not in args.geometries:
        raise InputError(f"--plot-geometry {args.plot_geometry}: not one of --geometries "
                         f"({', '.join(args.geometries)}); its shape could not be drawn")
    args.shape = presets.shape(args, args.geometries)
    chosen = {"growth_dt": args.growth_dt, "max_halvings": args.max_halvings, **presets.chosen(args)}
    settings = presets.settings(GrowthSettings, args.settings, chosen,
                                {"growth_dt": "--growth-dt", "max_halvings": "--max-halvings"})
    runs = plan(args.geometries, [p for text in args.protocols for p in protocols.from_option(text, "--protocols")])
    if args.data is not None:
        data = measured.read(args.data)
        for r in runs:
            measured.check_span(data, r.protocol)
    return runs, settings, material.load(args.material) if args.material else material.MaterialParams()


def idle_barrier(comm) -> None:
    """A barrier at which waiting ranks sleep, instead of spinning in MPI and taking a core
    from rank 0 while it writes the summary and figures."""
    request = comm.Ibarrier()
    while not request.Test():
        time.sleep(0.05)


def finish(output: Path, runs: list[Run], results, settings: GrowthSettings, elapsed: float, *,
           plot_geometry: str, figures: bool = True) -> int:
    """Rank 0: summary, failures, figures (unless ``figures`` is false), table. Returns the exit status."""
    failed = {r.key: r.error for r in results if r.status == "failed"}
    interrupted = {r.key for r in results if r.status == "done" and r.result and r.result.get("interrupted")}
    rows = summarize(output, runs, failed, interrupted)
    write_csv(rows, output / "summary.csv")
    failures = output / "failures.txt"
    if failed:
        with io.atomic_path(failures) as tmp:
            tmp.write_text("".join(f"== {key} ==\n{error.rstrip()}\n\n" for key, error in failed.items()))
    else:
        failures.unlink(missing_ok=True)
    done = [r for r in rows if r["status"] == "done"]
    written = [output / "summary.csv"]
    if done and figures:
        ratio_figure(done, output / "ratios.png")
        written.append(output / "ratios.png")
    pictured = {r.protocol.name: runspec.Outputs(series_path(output, r)).fields for r in runs
                if r.geometry == plot_geometry}
    pictured = {name: p for name, p in pictured.items() if p.is_file()}
    if pictured and figures:
        shape_figure({name: final_fields(p) for name, p in pictured.items()}, output / "shape.png", plot_geometry)
        written.append(output / "shape.png")
    elif figures:
        info(None, f"shape.png not written: {plot_geometry}, its geometry, has no finished run")
    table = markdown(rows, settings)
    with io.atomic_path(output / "table.md") as tmp:
        tmp.write_text(table)
    written.append(output / "table.md")

    info(None, f"\n{'geometry':<16} {'protocol':<11} {'CSA0 cm²':>8} {'V0 cm³':>8} {'CSA/CSA0':>9} "
               f"{'V/V0':>8} {'wall':>8} status")
    for r in rows:
        info(None, f"{r['geometry']:<16} {r['protocol']:<11} {r['csa0_cm2']:>8.3f} {r['volume0_cm3']:>8.2f} "
                   f"{r['final_csa_ratio']:>9.5f} {r['final_volume_ratio']:>8.5f} "
                   f"{hms(r['wall_s']) if r['status'] == 'done' else '-':>8} {r['status']}")
    for r in rows:
        if r["status"] == "done" and not math.isnan(r["data_rmse_pp"]):
            info(None, f"{r['geometry']}/{r['protocol']} against measured CSA: RMSE {r['data_rmse_pp']:.2f} "
                       f"percentage points, model − data at the last measured time "
                       f"{r['data_last_difference_pp']:+.2f} points")
    info(None, "\n" + table)
    info(None, farm.summary_line(results) + f"; cohort wall time {hms(elapsed)} ({elapsed:.0f} s)")
    if failed:
        written.append(failures)
        info(None, f"errors in {failures}; rerun the same command to retry only the failed runs")
    if interrupted:
        info(None, f"stopped by SIGTERM: {len(interrupted)} run(s) not finished ({', '.join(sorted(interrupted))}); "
                   "rerun the same command to continue them from their checkpoints")
    info(None, "wrote " + ", ".join(str(p) for p in written))
    return cli.EXIT_TERMINATED if interrupted else cli.EXIT_SOME_FAILED if failed else cli.EXIT_OK


def cohort(comm, args) -> int:
    start = time.perf_counter()
    runs, settings, muscle = check(args, comm)
    with locks.hold(comm, [args.output]):
        info(comm, f"cohort: {len(runs)} runs ({len(args.geometries)} geometries × {len(args.protocols)} "
                   f"protocols) on {comm.size} rank(s) in groups of {args.ranks_per_job}, growth step "
                   f"{settings.growth_dt:g} h, output {args.output}")
        with run.StopOnTerm() as stop:
            results = run_cohort(comm, runs, args.output, settings=settings, snapshot_every=args.snapshot_every,
                                 ranks_per_job=args.ranks_per_job, stop=stop, progress_every=args.progress_every,
                                 data=None if args.data is None else measured.read(args.data),
                                 options={**args.shape, "material": muscle})
        code = 0
        if comm.rank == 0:
            try:
                code = finish(args.output, runs, results, settings, time.perf_counter() - start,
                              plot_geometry=args.plot_geometry)
            except Exception:  # noqa: BLE001 - the other ranks wait below: report, never leave them hanging
                traceback.print_exc()
                code = cli.EXIT_SOME_FAILED
        idle_barrier(comm)
    return int(comm.bcast(code, root=0))


main = cli.entry(parser, cohort)

if __name__ == "__main__":
    sys.exit(main())
