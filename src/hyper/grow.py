"""python -m hyper.grow: the coupled growth model on one geometry for one or more protocols.

    python -m hyper.grow --geometry idealized --protocol mwf --output results/grow/idealized_mwf.h5
    python -m hyper.grow --geometry idealized --protocol all --output results/grow
    python -m hyper.grow --mesh my_muscle.xdmf --mesh-unit mm --protocol mwf --output results/mine
    python -m hyper.grow --geometry idealized --protocol mwf --accuracy 1e-3
    python -m hyper.grow --ask signaling --protocol mwf --accuracy 1e-3 --output results/signaling/mwf.h5

Writes per run an HDF5 time series (t, csa_ratio, volume_ratio, kM, the signaling
states, Newton iterations, step cuts) with parameters, protocol, settings and versions
as attributes, and an XDMF file of snapshots (growth displacement, det Ḡ, fibres) for
ParaView; with several protocols, the paper's Fig. 4C–E analog.

Fidelity (hyper.fidelity). --accuracy A runs the cheapest model and the longest growth
and RK4 steps whose error, from the tables measured by python -m hyper.bench growth and
signaling, stays within A of the growth (half for each step); it prints the choice and
stores it as the result's `fidelity` attributes. --ask signaling answers a question
about N alone: only the signaling ODEs run (no mesh is built, DOLFINx is not imported),
and each protocol's series is written as python -m hyper.signaling writes it, with A a
fraction of N (exit status 3 if the ODEs fail).

Linear solver. --linear-solver lu (the default) factorises the Newton matrix with MUMPS;
iterative runs GMRES preconditioned by MUMPS's block low-rank factorisation (0.6x the
memory at 578k unknowns, the same answer to the Newton tolerance); auto, the default
with --accuracy, takes LU while its memory, predicted from the unknowns by the law
python -m hyper.bench solvers measured, fits in the memory available on the run's
nodes. The choice and its reason are printed and stored as attributes (linear_solver,
linear_solver_reason).

Restart. Every --checkpoint-every growth steps, and at the first step boundary after
a SIGTERM (what Slurm sends before a time limit), the run saves its whole state in
RESULT.ckpt.h5 next to its result RESULT.h5 (atomically: a kill leaves the previous
checkpoint). Running the same command again resumes from it and gives the result of
an uninterrupted run: the same bits on the same number of ranks, within round-off on
another. A finished run deletes its checkpoint. --restart ignores and deletes it.

Failures. A growth step whose Newton solve fails is cut in halves (up to
--max-halvings times); if it still fails, the run stops, saves the state after its
last completed step in the checkpoint and writes RESULT.status.json (what failed, at
which step and time, with which settings). It can be resumed with a larger
--max-halvings, the one setting that may change on resume.

Outputs appear only when complete (HDF5 with a `complete` mark, the XDMF pair and the
figure by rename). On resume the XDMF file is written again from the snapshots kept in
the checkpoint, so it always holds every snapshot. A run holds RESULT.h5.lock
(fcntl.flock) while it works; a second run on the same result stops at once.

Exit status: 0 done; 2 bad input (nothing written; the message names the file or
option, the field and the expected form); 3 a growth step failed for good (checkpoint
and status file written); 4 another run holds the output; 143 stopped by SIGTERM
(checkpoint written: run the command again to resume).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import re
import signal
import sys
import time
from pathlib import Path
from typing import Callable

import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)

import numpy as np
from mpi4py import MPI

# The DOLFINx side (geometry, growth, coupled) is imported in the functions that build a
# mesh: a signaling question (--ask signaling) runs without it.
from hyper import checkpoint as ckpt
from hyper import fidelity, io, protocols, signaling
from hyper.log import Progress, hms, info
from hyper.params import InputError, as_attributes

PAPER_PROTOCOLS = ("mwf", "every3days", "weekly")
SERIES = ("t", "csa_ratio", "volume_ratio", "kM", *signaling.STATES, "newton_iterations", "halvings", "wall_s")
CHECKPOINT_EVERY = 10  # growth steps; writing one took 0.3 s on BFLH_VHF_Left (8512 cells, 30 MB), a step 7 s
SIGNALING_SAMPLE_EVERY = 0.5  # h, the series of --ask signaling, as python -m hyper.signaling samples it

EXIT_OK = 0
EXIT_INPUT = 2
EXIT_FAILED = 3
EXIT_BUSY = 4
EXIT_TERMINATED = 128 + signal.SIGTERM  # 143, what a shell reports for a TERM-killed job

MESH_UNITS = {"m": 1.0, "mm": 1.0e-3}
# A muscle's longest side: the paper's are 0.1-0.45 m. Outside this, the declared unit
# is wrong (a file in millimetres read as metres is ~1000x too long).
MUSCLE_LENGTH_M = (0.01, 1.0)


class Interrupted(RuntimeError):
    """The run stopped at a step boundary on request (SIGTERM); its checkpoint is saved."""

    def __init__(self, message: str, *, step: int, t: float, checkpoint: Path | None):
        super().__init__(message)
        self.step = step
        self.t = t
        self.checkpoint = checkpoint


# ---------------------------------------------------------------------------------- paths


def checkpoint_path(h5: Path) -> Path:
    return h5.with_name(h5.stem + ".ckpt.h5")


def status_path(h5: Path) -> Path:
    return h5.with_name(h5.stem + ".status.json")


def fields_path(h5: Path) -> Path:
    return h5.with_name(h5.stem + "_fields.xdmf")


# ----------------------------------------------------------------------------- user meshes


@dataclasses.dataclass(frozen=True)
class MeshFile:
    """A user's tetrahedral XDMF mesh with facet tags ``tags``: 1 and 2 the ends, 3 the
    lateral surface (the anatomical meshes' convention); lengths in ``unit``."""

    path: Path
    unit: str = "m"
    tags: str = "ft_small"

    def load(self, comm) -> geo.Geometry:
        from hyper import geometry as geo

        if self.unit not in MESH_UNITS:
            raise InputError(f"--mesh-unit: expected one of {', '.join(MESH_UNITS)}, got {self.unit!r}")
        if self.path.suffix != ".xdmf":
            raise InputError(f"{self.path}: expected an XDMF mesh file (.xdmf with its .h5), got {self.path.suffix!r}")
        geometry = geo.load_file(self.path, comm, name=self.path.stem, tags=self.tags, ends=(1, 2), lateral=3,
                                 scale=MESH_UNITS[self.unit])
        x = geometry.mesh.geometry.x
        lo, hi = np.empty(3), np.empty(3)
        comm.Allreduce(x.min(axis=0) if len(x) else np.full(3, np.inf), lo, op=MPI.MIN)
        comm.Allreduce(x.max(axis=0) if len(x) else np.full(3, -np.inf), hi, op=MPI.MAX)
        length = float(np.max(hi - lo))
        low, high = MUSCLE_LENGTH_M
        if not low <= length <= high:
            in_file = length / MESH_UNITS[self.unit]
            raise InputError(
                f"{self.path}: the mesh is {in_file:g} {self.unit} long (longest side of its bounding box), "
                f"i.e. {length:g} m, outside the {low:g}-{high:g} m of a muscle: its length unit is not "
                f"{self.unit!r}; declare the file's unit with --mesh-unit ({' or '.join(MESH_UNITS)})"
            )
        return geometry

    def identity(self) -> dict:
        data = self.path.with_suffix(".h5")
        files = [self.path] + ([data] if data.is_file() else [])
        return {"mesh_sha256": ckpt.file_digest(*files), "unit": self.unit, "tags": self.tags}


def describe(geometry_name: str, protocol, params, settings: GrowthSettings, petsc_options=None,
             mesh: MeshFile | None = None) -> dict:
    """Everything that defines a run's result: the run digest is its hash."""
    # Per-cell parameter arrays are in a rank's own cell order; the checkpoint carries
    # them keyed by cell, so the description only says that they are per cell.
    described = {k: ("per cell" if isinstance(v, np.ndarray) else v) for k, v in as_attributes(params).items()}
    return {
        "geometry": geometry_name if mesh is None else mesh.identity(),
        "protocol": protocol.to_attributes(),
        "params": described,
        "settings": settings.model_attributes(),
        "petsc_options": dict(petsc_options or {}),
    }


# ------------------------------------------------------------------------------- the run


class Snapshots:
    """Output fields of a run on spaces XDMF can store (P1 and DG0), updated in place.

    Each snapshot is also kept per owned cell (the cell's own P1 values of u, and det Ḡ)
    so that a checkpoint can carry them and a resumed run can write them again.
    """

    def __init__(self, model: CoupledModel, a0):
        from dolfinx import fem

        mesh = model.geometry.mesh
        self.model = model
        self.u = fem.Function(fem.functionspace(mesh, ("Lagrange", 1, (3,))), name="u")
        self.det = fem.Function(fem.functionspace(mesh, ("DG", 0)), name="detGbar")
        self.a0 = fem.Function(fem.functionspace(mesh, ("Lagrange", 1, (3,))), name="a0")
        self.a0.interpolate(a0)
        cells = model.growth.cells
        nlocal = len(cells) + mesh.topology.index_map(mesh.topology.dim).num_ghosts
        self._cells = cells
        self._local = np.arange(nlocal, dtype=np.int32)
        self._det_dofs = self.det.function_space.dofmap.list[cells][:, 0]
        self.times: list[float] = []
        self.u_cells: list[np.ndarray] = []  # (owned cells, 4, 3) each
        self.det_cells: list[np.ndarray] = []  # (owned cells,) each

    def update(self, t: float):
        self.u.interpolate(self.model.problem.u)
        self.det.x.array[self._det_dofs] = self.model.growth.cell_det()
        self.det.x.scatter_forward()
        self._keep(t)
        return self.u, self.det, self.a0

    def _keep(self, t: float) -> None:
        dofs = self.u.function_space.dofmap.list[self._cells]
        self.times.append(t)
        self.u_cells.append(self.u.x.array.reshape(-1, 3)[dofs])
        self.det_cells.append(self.det.x.array[self._det_dofs].copy())

    def state(self) -> tuple[dict, dict]:
        """(per-cell arrays, global values) of the snapshots so far, for a checkpoint."""
        n = len(self._cells)
        per_cell = {
            "snapshot_u": np.stack(self.u_cells, axis=1) if self.u_cells else np.empty((n, 0, 4, 3)),
            "snapshot_det": np.stack(self.det_cells, axis=1) if self.det_cells else np.empty((n, 0)),
        }
        return per_cell, {"snapshot_t": np.asarray(self.times, dtype=float)}

    def restore(self, saved: ckpt.Checkpoint):
        """Yield (t, fields) for each saved snapshot, set on this partition, and keep them."""
        u_rows, det_rows = saved.rows("snapshot_u"), saved.rows("snapshot_det")
        udofs = self.u.function_space.dofmap.list[self._local]
        ddofs = self.det.function_space.dofmap.list[self._local][:, 0]
        for i, t in enumerate(np.asarray(saved.glob["snapshot_t"], dtype=float)):
            self.u.x.array.reshape(-1, 3)[udofs] = u_rows[:, i]
            self.u.x.scatter_forward()
            self.det.x.array[ddofs] = det_rows[:, i]
            self.det.x.scatter_forward()
            self._keep(float(t))
            yield float(t), (self.u, self.det, self.a0)


def available_memory_mb(comm) -> float:
    """MemAvailable of every node the ranks of ``comm`` run on, summed (MB). Collective."""
    node = comm.Split_type(MPI.COMM_TYPE_SHARED)
    try:
        mine = 0.0
        if node.rank == 0:
            meminfo = Path("/proc/meminfo").read_text().splitlines()
            line = next(text for text in meminfo if text.startswith("MemAvailable:"))
            mine = float(line.split()[1]) / 1024.0
        return comm.allreduce(mine, op=MPI.SUM)
    finally:
        node.Free()


def run_one(comm, geometry_name: str, protocol, params, settings, *, snapshot_every: int, xdmf_path,
            checkpoint: Path | None = None, checkpoint_every: int = CHECKPOINT_EVERY,
            stop: Callable[[], bool] | None = None, petsc_options: dict | None = None,
            mesh: MeshFile | None = None, linear_solver: str = "lu"):
    """Run one coupled simulation; return the series and the model's metadata.

    With ``checkpoint`` (a path), the run resumes from that file if it exists (it must
    belong to this run: InputError otherwise), saves its state there every
    ``checkpoint_every`` growth steps (0: never on schedule), when ``stop()`` turns true
    on some rank (then raises `Interrupted`) and before a `GrowthFailure` propagates
    (whose ``checkpoint`` attribute names the file). The caller deletes the checkpoint
    once the results are stored. ``linear_solver`` is "lu", "iterative" or "auto" (chosen
    by `fidelity.linear_solver` from the unknowns and the memory available). Collective
    over ``comm``.
    """
    from hyper import geometry as geo
    from hyper.coupled import CoupledModel, GrowthFailure
    from hyper.mechanics import taylor_hood_unknowns

    run_digest = ckpt.digest(describe(geometry_name, protocol, params, settings, petsc_options, mesh))
    geometry = mesh.load(comm) if mesh is not None else geo.load(geometry_name, comm)
    a0 = geo.fiber_field(geometry, "principal" if mesh is not None else "auto")
    solver_reason = "asked for (--linear-solver)"
    if linear_solver == "auto":
        unknowns = taylor_hood_unknowns(geometry.mesh)
        linear_solver, solver_reason = fidelity.linear_solver(unknowns, available_memory_mb(comm))
        info(comm, f"fidelity: {solver_reason}")
    model = CoupledModel(geometry, a0, protocol, params=params, settings=settings, petsc_options=petsc_options,
                         linear_solver=linear_solver)
    snaps = Snapshots(model, a0)
    series = {name: [] for name in SERIES}
    segments, wall0 = 1, 0.0
    saved = None
    if checkpoint is not None:
        # a checkpoint write killed halfway leaves its temporary file: never read, remove it
        ckpt.on_rank0(comm, lambda: Path(str(checkpoint) + io.PARTIAL).unlink(missing_ok=True))
    if checkpoint is not None and ckpt.on_rank0(comm, Path(checkpoint).is_file):
        saved = ckpt.read(comm, Path(checkpoint), run_digest, ckpt.local_original_cells(model.geometry.mesh))
        ckpt.restore_model(model, saved.rows, saved.glob)
        series = {name: list(saved.series[name]) for name in SERIES}
        segments = int(saved.attrs["segments"]) + 1
        wall0 = float(series["wall_s"][-1])
        info(comm, f"{geometry_name}/{protocol.name}: resuming from {checkpoint} at step {model.step} "
                   f"(t = {model.t:g} h), written on {saved.attrs['ranks']} rank(s)")

    def save(status: str) -> None:
        original, per_cell, glob = ckpt.model_state(model)
        snap_cells, snap_glob = snaps.state()
        ckpt.write(comm, Path(checkpoint), original, {**per_cell, **snap_cells}, {**glob, **snap_glob},
                   {k: np.asarray(v) for k, v in series.items()},
                   {"run_digest": run_digest, "step": model.step, "t": model.t, "segments": segments,
                    "status": status, "geometry": geometry_name, "protocol": protocol.name})

    progress = Progress(comm, protocol.end, f"{geometry_name}/{protocol.name}")
    start = time.perf_counter()
    last_saved = model.step
    with io.atomic_xdmf(comm, xdmf_path) as xdmf:
        xdmf.write_mesh(geometry.mesh)
        if saved is not None:
            for t, fields in snaps.restore(saved):
                for f in fields:
                    xdmf.write_function(f, t)
        try:
            for report in model.run():
                for name, value in zip(signaling.STATES, report.states):
                    series[name].append(value)
                series["t"].append(report.t)
                series["csa_ratio"].append(report.csa_ratio)
                series["volume_ratio"].append(report.volume_ratio)
                series["kM"].append(report.kM)
                series["newton_iterations"].append(report.newton_iterations)
                series["halvings"].append(report.halvings)
                series["wall_s"].append(wall0 + time.perf_counter() - start)
                last = report.t >= protocol.end
                if report.step % snapshot_every == 0 or last:
                    for f in snaps.update(report.t):
                        xdmf.write_function(f, report.t)
                progress.update(
                    report.t,
                    f"day {report.t / 24:5.1f}, CSA/CSA0 {report.csa_ratio:.5f}, V/V0 {report.volume_ratio:.5f}",
                    force=last,
                )
                if last or checkpoint is None:
                    continue
                if stop is not None and comm.allreduce(bool(stop()), op=MPI.LOR):
                    save("interrupted")
                    raise Interrupted(f"stopped on request at step {model.step} (t = {model.t:g} h); "
                                      f"state saved in {checkpoint}", step=model.step, t=model.t,
                                      checkpoint=Path(checkpoint))
                if checkpoint_every and model.step - last_saved >= checkpoint_every:
                    save("running")
                    last_saved = model.step
        except GrowthFailure as err:
            err.checkpoint = None
            if checkpoint is not None:
                save("failed")
                err.checkpoint = Path(checkpoint)
            raise
    meta = {
        "geometry": geometry_name,
        "csa0_m2": model.csa0,
        "volume0_m3": model.volume0,
        "ranks": comm.size,
        "growth_steps": model.step,
        "wall_s": wall0 + time.perf_counter() - start,
        "segments": segments,
        "run_digest": run_digest,
        "unknowns": model.problem.num_dofs,
        "linear_solver": linear_solver,
        "linear_solver_reason": solver_reason,
    }
    return {k: np.asarray(v) for k, v in series.items()}, meta


# ------------------------------------------------------------------------------- figure


def figure(results: dict[str, dict], path: Path, data_dir: Path | None = None) -> None:
    """CSA, volume and kM against time for several protocols (the paper's Fig. 4C–E)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8), constrained_layout=True)
    for name, s in results.items():
        weeks = s["t"] / 168.0
        axes[0].plot(weeks, 100 * (s["csa_ratio"] - 1), label=name)
        axes[1].plot(weeks, 100 * (s["volume_ratio"] - 1), label=name)
        axes[2].plot(weeks, s["kM"], label=name)
    if data_dir is not None and (data_dir / "defreitas.csv").is_file():
        data = np.genfromtxt(data_dir / "defreitas.csv", delimiter=",", names=True)
        axes[0].plot(data["week"], 100 * (data["csa"] / data["csa"][0] - 1), "ko", ms=4,
                     label="DeFreitas 2011 (mwf)")
    axes[0].set_ylabel("CSA change (%)")
    axes[1].set_ylabel("volume change (%)")
    axes[2].set_ylabel("kM (1/h)")
    for ax in axes:
        ax.set_xlabel("time (weeks)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    with io.atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=150, format="png")
    plt.close(fig)


# ---------------------------------------------------------------------------------- CLI


class _Parser(argparse.ArgumentParser):
    """argparse whose errors are InputErrors: one message, on rank 0, exit status 2."""

    def error(self, message):
        raise InputError(message)


def _petsc_option(text: str) -> tuple[str, str]:
    key, sep, value = text.partition("=")
    if not sep or not re.fullmatch(r"[a-z][a-z0-9_]*", key) or not value or re.search(r"\s", value):
        raise InputError(f"--petsc-option {text!r}: expected KEY=VALUE with a PETSc option name without "
                         "its dash and prefix, e.g. snes_max_it=50")
    return key, value


def _scene_options(p) -> None:
    """The options a signaling question shares with a growth run."""
    p.add_argument("--ask", choices=fidelity.ASKS, default="growth",
                   help="what the run answers: 'growth' (default; CSA and volume, the coupled model on a mesh) or "
                        "'signaling' (N and the signaling states: the ODEs alone, no mesh, no DOLFINx; takes "
                        "--protocol, --protocol-file, --params, --output, --signaling-dt and --accuracy)")
    p.add_argument("--accuracy", type=float, nargs="?", const=fidelity.DEFAULT_ACCURACY, metavar="A",
                   help="run the cheapest model and the longest steps whose error, from the error tables that "
                        "python -m hyper.bench growth and signaling measured, stays within A: a fraction of the "
                        "growth (of x - 1 for x = CSA/CSA0 or V/V0) or, for --ask signaling, of N; A in "
                        f"(0, 0.5), {fidelity.DEFAULT_ACCURACY:g} when A is left out. Prints the choice "
                        "(fidelity: …) and stores it in the result's 'fidelity' attributes; an explicit "
                        "--growth-dt or --signaling-dt wins over it. Without --accuracy the fixed default steps "
                        "run, as before: the choice for 0.001 takes a longer RK4 step, so it is another run "
                        "(its own results and checkpoints)")
    p.add_argument("--protocol",
                   help=f"named protocol ({', '.join(protocols.NAMES)}; default mwf) or 'all' for "
                        f"{', '.join(PAPER_PROTOCOLS)}")
    p.add_argument("--protocol-file", type=Path, help="TOML protocol file (replaces --protocol)")
    p.add_argument("--params", type=Path, help="TOML file overriding signaling parameters")
    p.add_argument("--signaling-dt", type=float,
                   help=f"RK4 step (h; default {fidelity.SIGNALING_DT0:g}, or chosen by --accuracy)")


def parse_args(argv):
    from hyper import growth
    from hyper.coupled import GrowthSettings

    p = _Parser(prog="python -m hyper.grow", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--geometry", help="geometry id (idealized, cylinder, BFLH_VHF_Left, …; default idealized)")
    p.add_argument("--mesh", type=Path,
                   help="a tetrahedral XDMF mesh of your own instead of --geometry (facet tags 'ft_small': 1, 2 "
                        "the ends, 3 the lateral surface; fibres along its principal axis)")
    p.add_argument("--mesh-unit", help="length unit of --mesh: m or mm (default m)")
    _scene_options(p)
    p.add_argument("--output", type=Path, default=Path("results/grow"),
                   help="an .h5 file (one protocol) or a folder (default results/grow; results/signaling for "
                        "--ask signaling)")
    p.add_argument("--growth-dt", type=float,
                   help=f"growth step Δtg (h; default {GrowthSettings.growth_dt:g}, or chosen by --accuracy)")
    p.add_argument("--feedback", choices=growth.FEEDBACK_LAWS, default="hill")
    p.add_argument("--skip-sessions", action="store_true",
                   help="no growth during sessions (the original code's choice)")
    p.add_argument("--fe-stress", action="store_true",
                   help="use P = Fe S (the original code) instead of the consistent det(Fg) Fe S Fg⁻ᵀ")
    p.add_argument("--max-halvings", type=int, default=GrowthSettings.max_halvings,
                   help="cuts of a growth step whose Newton solve fails before the run stops (default %(default)s)")
    p.add_argument("--linear-solver", choices=("lu", "iterative", "auto"),
                   help="the Newton step's linear solver: 'lu' (MUMPS; the default without --accuracy), "
                        "'iterative' (GMRES with MUMPS's block low-rank factorisation as preconditioner: less "
                        "memory, same answer to the Newton tolerance) or 'auto' (the default with --accuracy: LU "
                        "while its memory, predicted from the unknowns, fits in the memory available)")
    p.add_argument("--petsc-option", action="append", default=[], metavar="KEY=VALUE",
                   help="a PETSc option of the mechanics solver, e.g. snes_max_it=50 (repeatable)")
    p.add_argument("--snapshot-every", type=int, default=10, help="XDMF snapshot every K growth steps")
    p.add_argument("--checkpoint-every", type=int, default=CHECKPOINT_EVERY,
                   help="checkpoint every K growth steps (0: only on SIGTERM and failures; default %(default)s)")
    p.add_argument("--restart", action="store_true", help="ignore and delete an existing checkpoint")
    p.add_argument("--plot", type=Path, help="figure path, .png (default: next to the output)")
    return p.parse_args(argv)


def parse_signaling_args(argv):
    """The options of --ask signaling; any other is an error that names it."""
    p = _Parser(prog="python -m hyper.grow --ask signaling",
                description="A signaling question: the signaling ODEs alone for each protocol (no mesh, no "
                            "DOLFINx), written as python -m hyper.signaling writes them, with the fidelity choice "
                            "as attributes.")
    _scene_options(p)
    p.add_argument("--output", type=Path, default=Path("results/signaling"),
                   help="an .h5 file (one protocol) or a folder (default results/signaling)")
    args, rest = p.parse_known_args(argv)
    if rest:
        raise InputError(f"--ask signaling builds no mesh and grows nothing: {' '.join(rest)} does not apply")
    return args


def _ask(argv) -> str:
    """--ask, read before the other options: a signaling question needs neither a mesh nor DOLFINx."""
    p = _Parser(add_help=False, allow_abbrev=False)
    p.add_argument("--ask", choices=fidelity.ASKS, default="growth")
    return p.parse_known_args(argv)[0].ask


@dataclasses.dataclass
class Plan:
    """The validated command: what to run and where the results go."""

    geometry: str
    mesh: MeshFile | None
    runs: list
    params: signaling.SignalingParams
    settings: GrowthSettings
    petsc_options: dict
    outputs: list[Path]
    plot: Path
    snapshot_every: int
    checkpoint_every: int
    restart: bool
    choice: fidelity.Choice | None  # from --accuracy; None: the fixed steps
    linear_solver: str = "lu"  # lu, iterative, or auto (chosen once the mesh is loaded)


_FILE_SUFFIXES = (".hdf5", ".xdmf", ".png", ".csv", ".json", ".toml", ".txt", ".npy")


def _protocols(args) -> list:
    if args.protocol_file is not None and args.protocol is not None:
        raise InputError("--protocol and --protocol-file exclude each other: give one of them")
    if args.protocol_file is not None:
        return [protocols.load(args.protocol_file)]
    if args.protocol == "all":
        return [protocols.named(n) for n in PAPER_PROTOCOLS]
    try:
        return [protocols.named(args.protocol or "mwf")]
    except InputError as err:
        raise InputError(f"--protocol: {err}, or 'all'; or give a TOML file with --protocol-file") from None


def _check_steps(growth_dt: float | None, signaling_dt: float | None) -> None:
    for name, value in (("--growth-dt", growth_dt), ("--signaling-dt", signaling_dt)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise InputError(f"{name}: expected a finite number of hours > 0, got {value:g}")


def _choose(scene: fidelity.Scene, accuracy: float, growth_dt: float | None,
            signaling_dt: float | None) -> fidelity.Choice:
    try:
        return fidelity.choose(scene, accuracy, growth_dt=growth_dt, signaling_dt=signaling_dt)
    except InputError as err:
        raise InputError(f"--accuracy {accuracy:g}: {err}") from None


def _outputs(out: Path, stems: list[str]) -> list[Path]:
    """The result files: ``out`` itself (an .h5 file, one run) or STEM.h5 per run in the folder ``out``."""
    single_file = out.suffix == ".h5"
    if single_file and len(stems) > 1:
        raise InputError(f"--output {out}: several protocols need a folder, not an .h5 file")
    if out.suffix.lower() in _FILE_SUFFIXES:
        raise InputError(f"--output {out}: expected an .h5 file or a folder, got a {out.suffix} file")
    if not single_file and out.exists() and not out.is_dir():
        raise InputError(f"--output {out}: exists and is not a folder")
    if single_file and out.is_dir():
        raise InputError(f"--output {out}: is a folder; give the result file a name that ends in .h5")
    for parent in (out if not single_file else out.parent, *out.parents):
        if parent.exists() and not parent.is_dir():
            raise InputError(f"--output {out}: {parent} is a file, not a folder")
    return [out] if single_file else [out / f"{stem}.h5" for stem in stems]


def plan(comm, argv) -> Plan:
    """Parse and check every input; raises InputError before anything is written."""
    from hyper import geometry as geo
    from hyper.coupled import LAG_OPTION, GrowthSettings, jacobian_lag

    args = parse_args(argv)
    mesh = None
    if args.mesh is not None and args.geometry is not None:
        raise InputError("--geometry and --mesh exclude each other: give one of them")
    if args.mesh_unit is not None and args.mesh is None:
        raise InputError("--mesh-unit declares the length unit of a --mesh file; there is none")
    if args.mesh is not None:
        mesh = MeshFile(args.mesh, args.mesh_unit or "m")
        geometry = args.mesh.stem
    else:
        args.geometry = args.geometry or "idealized"
        if args.geometry not in geo.GEOMETRIES:
            raise InputError(f"--geometry: unknown geometry {args.geometry!r}; known: {', '.join(geo.GEOMETRIES)}")
        geometry = args.geometry
        path = geo.MESHES_DIR / geo.GEOMETRIES[geometry]
        if not path.is_file():
            raise InputError(f"--geometry {geometry}: {path}: no such mesh file")
        if geometry in geo.ANATOMICAL:
            from hyper import fibers

            fpath = fibers.fiber_path(geometry)
            if not ckpt.on_rank0(comm, lambda: io.is_complete(fpath)):
                raise InputError(f"--geometry {geometry}: {fpath}: no complete fibre file; compute it with "
                                 f"`python -m hyper.fibers --geometries {geometry}`")
    runs = _protocols(args)
    params = signaling.load_params(args.params) if args.params else signaling.SignalingParams()
    _check_steps(args.growth_dt, args.signaling_dt)
    growth_dt = GrowthSettings.growth_dt if args.growth_dt is None else args.growth_dt
    signaling_dt = GrowthSettings.signaling_dt if args.signaling_dt is None else args.signaling_dt
    choice = None
    if args.accuracy is not None:
        # hyper.grow takes uniform parameters only (per-cell ones are hyper.ensemble's)
        scene = fidelity.Scene(geometry, ",".join(p.name for p in runs), heterogeneous=False, ask="growth")
        choice = _choose(scene, args.accuracy, args.growth_dt, args.signaling_dt)
        growth_dt, signaling_dt = choice.growth_dt, choice.signaling_dt
    try:
        settings = GrowthSettings(
            growth_dt=growth_dt,
            signaling_dt=signaling_dt,
            feedback=args.feedback,
            grow_during_sessions=not args.skip_sessions,
            consistent_stress=not args.fe_stress,
            max_halvings=args.max_halvings,
        )
    except InputError as err:
        raise InputError(f"--{str(err).replace('_', '-')}") from None
    petsc_options = dict(_petsc_option(text) for text in args.petsc_option)
    if LAG_OPTION in petsc_options:
        jacobian_lag(petsc_options[LAG_OPTION])
    for name in ("snapshot_every", "checkpoint_every"):
        value, least = getattr(args, name), 1 if name == "snapshot_every" else 0
        if value < least:
            raise InputError(f"--{name.replace('_', '-')}: expected an integer >= {least} (growth steps), got {value}")

    out = args.output
    outputs = _outputs(out, [f"{geometry}_{p.name}" for p in runs])
    plot = args.plot or (out.with_suffix(".png") if out.suffix == ".h5" else out / f"{geometry}_growth.png")
    if plot.suffix != ".png":
        raise InputError(f"--plot {plot}: expected a .png file")
    if mesh is not None:
        mesh.load(comm)  # units and tags, before anything is written
    if not args.restart:
        for h5, protocol in zip(outputs, runs):
            path = checkpoint_path(h5)
            digest = ckpt.digest(describe(geometry, protocol, params, settings, petsc_options, mesh))
            ckpt.on_rank0(comm, lambda: path.is_file() and ckpt.inspect(path, digest))
    linear_solver = args.linear_solver or ("auto" if args.accuracy is not None else "lu")
    return Plan(geometry, mesh, runs, params, settings, petsc_options, outputs, plot,
                args.snapshot_every, args.checkpoint_every, args.restart, choice, linear_solver)


class StopOnTerm:
    """SIGTERM sets a flag that the run reads at its step boundaries (main thread only)."""

    def __init__(self):
        self.received = False
        self._previous = None

    def _handler(self, signum, frame):
        self.received = True

    def __enter__(self):
        with contextlib.suppress(ValueError):  # not the main thread: no handler, no stop
            self._previous = signal.signal(signal.SIGTERM, self._handler)
        return self

    def __exit__(self, *exc):
        if self._previous is not None:
            signal.signal(signal.SIGTERM, self._previous)

    def __call__(self) -> bool:
        return self.received


def _error(comm, message: str) -> None:
    if comm.rank == 0:
        print(f"error: {message}", file=sys.stderr, flush=True)


def answer_signaling(comm, argv) -> int:
    """--ask signaling: the signaling ODEs alone for each protocol, on rank 0; no mesh."""
    try:
        args = parse_signaling_args(argv)
        runs = _protocols(args)
        params = signaling.load_params(args.params) if args.params else signaling.SignalingParams()
        _check_steps(None, args.signaling_dt)
        scene = fidelity.Scene(None, ",".join(p.name for p in runs), heterogeneous=False, ask="signaling")
        if args.accuracy is not None:
            choice = _choose(scene, args.accuracy, None, args.signaling_dt)
        else:
            choice = fidelity.assess(scene, None, fidelity.SIGNALING_DT0 if args.signaling_dt is None
                                     else args.signaling_dt)
        outputs = _outputs(args.output, [p.name for p in runs])
    except InputError as err:
        _error(comm, str(err))
        return EXIT_INPUT
    info(comm, f"fidelity: {choice.describe()}")

    def answer():
        for protocol, h5 in zip(runs, outputs):
            series = signaling.run(params, protocol, choice.signaling_dt, SIGNALING_SAMPLE_EVERY)
            io.write_series(
                h5, series,
                attrs={"model": "signaling (MODEL.md §1)", "integrator": "RK4", "dt": choice.signaling_dt,
                       "sample_every": SIGNALING_SAMPLE_EVERY, "N_final": float(series["N"][-1])},
                groups={"parameters": as_attributes(params), "protocol": protocol.to_attributes(),
                        "fidelity": choice.as_attributes()},
            )
            print(f"{protocol.name}: N({protocol.end:g} h) = {series['N'][-1]:.6f}; no mesh built -> {h5}",
                  flush=True)

    try:
        ckpt.on_rank0(comm, answer)
    except signaling.SignalingError as err:
        _error(comm, str(err))
        return EXIT_FAILED
    return EXIT_OK


def main(argv=None) -> int:
    comm = MPI.COMM_WORLD
    command = sys.argv[1:] if argv is None else argv
    try:
        ask = _ask(command)
    except InputError as err:
        _error(comm, str(err))
        return EXIT_INPUT
    if ask == "signaling":
        return answer_signaling(comm, command)
    # PETSc installs its own SIGTERM handler (which aborts) when it starts: start it
    # before ours, so that ours is the one in place.
    import dolfinx_solver  # noqa: F401
    from petsc4py import PETSc  # noqa: F401
    with StopOnTerm() as stop:
        try:
            work = plan(comm, command)
        except InputError as err:
            _error(comm, str(err))
            return EXIT_INPUT
        with contextlib.ExitStack() as held:
            busy = None
            if comm.rank == 0:
                try:
                    unlocked = held.enter_context(ckpt.locked(work.outputs))
                except ckpt.Busy as err:
                    busy = str(err)
                else:
                    for path in unlocked:
                        print(f"warning: {path}: the file system takes no locks; nothing keeps another run "
                              "from writing the same output", file=sys.stderr, flush=True)
            busy = comm.bcast(busy, root=0)
            if busy is not None:
                _error(comm, busy)
                return EXIT_BUSY
            return _run(comm, work, stop, argv)


def _run(comm, work: Plan, stop, argv) -> int:
    from hyper.coupled import GrowthFailure

    if work.choice is not None:
        info(comm, f"fidelity: {work.choice.describe()}")
    results = {}
    for protocol, h5 in zip(work.runs, work.outputs):
        xdmf, saved, status = fields_path(h5), checkpoint_path(h5), status_path(h5)
        if work.restart:
            ckpt.on_rank0(comm, lambda: saved.unlink(missing_ok=True))
        try:
            series, meta = run_one(comm, work.geometry, protocol, work.params, work.settings,
                                   snapshot_every=work.snapshot_every, xdmf_path=xdmf, checkpoint=saved,
                                   checkpoint_every=work.checkpoint_every, stop=stop,
                                   petsc_options=work.petsc_options, mesh=work.mesh,
                                   linear_solver=work.linear_solver)
        except InputError as err:
            _error(comm, str(err))
            return EXIT_INPUT
        except Interrupted as err:
            ckpt.on_rank0(comm, lambda: ckpt.write_status(status, {
                "state": "interrupted", "reason": "SIGTERM", "step": err.step, "t_h": err.t,
                "checkpoint": saved, "resume": "run the same command again"}))
            info(comm, f"{protocol.name}: {err}; exit status {EXIT_TERMINATED}")
            return EXIT_TERMINATED
        except GrowthFailure as err:
            ckpt.on_rank0(comm, lambda: ckpt.write_status(status, {
                "state": "failed", "reason": str(err), "failed_step": err.step, "from_h": err.t0, "to_h": err.t1,
                "checkpoint": err.checkpoint, "geometry": work.geometry, "protocol": protocol.to_attributes(),
                "params": as_attributes(work.params), "settings": dataclasses.asdict(work.settings),
                "petsc_options": work.petsc_options, "ranks": comm.size,
                "command": ["python", "-m", "hyper.grow", *(sys.argv[1:] if argv is None else argv)],
                "resume": "run the command again, e.g. with a larger --max-halvings"}))
            _error(comm, f"{work.geometry}/{protocol.name}: {err}; state after step {err.step - 1} saved in "
                         f"{err.checkpoint}, details in {status}")
            return EXIT_FAILED

        def store():
            groups = {"signaling": as_attributes(work.params), "protocol": protocol.to_attributes(),
                      "settings": dataclasses.asdict(work.settings)}
            if work.choice is not None:
                groups["fidelity"] = work.choice.as_attributes()
            io.write_series(h5, series, attrs=meta, groups=groups)
            saved.unlink(missing_ok=True)
            status.unlink(missing_ok=True)

        ckpt.on_rank0(comm, store)
        info(comm, f"{protocol.name}: CSA/CSA0 {series['csa_ratio'][-1]:.5f}, V/V0 "
                   f"{series['volume_ratio'][-1]:.5f} in {hms(meta['wall_s'])}; wrote {h5} and {xdmf}")
        results[protocol.name] = series
    if comm.rank == 0:
        data_dir = Path(__file__).resolve().parents[2] / "data"
        figure(results, work.plot, data_dir if data_dir.is_dir() else None)
        print(f"figure: {work.plot}")
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
