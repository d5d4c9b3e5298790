"""The driver of one coupled run: what it is, where it writes, and how it survives.

A `RunSpec` describes a run: the geometry (a built-in one or a user's `MeshFile`), the
protocol, the signaling parameters (uniform, or per cell from a heterogeneity model
and a seed), the growth settings and the PETSc options; its SHA-256 `digest` names the
result, and a checkpoint is resumed only by the run with the same digest. `Outputs`
derives the files of a run from its result path:

    RESULT.h5             the time series (hyper.core.io.write_series), written when done
    RESULT_fields.xdmf    snapshots of u, det Ḡ and a0 (and N with per-cell signaling) every
                          --snapshot-every simulated hours and at the end: one temporal
                          series of grids, each with every field (hyper.core.io.one_grid)
    RESULT.ckpt.h5        the whole state, every --checkpoint-every growth steps, at the
                          first step boundary after a SIGTERM and when a step fails
    RESULT.status.json    why an unfinished run stopped, and how to resume it (hyper.runs.status)
    RESULT.h5.lock        held while a run writes (hyper.runs.locks.hold)

`execute` runs the model (`hyper.fem.coupled.CoupledModel.run`, which writes no files)
and records it: `Series` keeps the time series, `Snapshots` the XDMF fields, both
carried by the checkpoint so that a resumed run writes what an uninterrupted one
would (the same bits on one rank; on several, within the round-off by which two
parallel runs already differ). grow, cohort, ensemble and the
benches all run through here.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import signal
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from mpi4py import MPI

from hyper.core import io, term
from hyper.core.collective import on_rank0
from hyper.core.log import PROGRESS_EVERY, Progress, info
from hyper.core.params import InputError, as_attributes
from hyper.fem import fiberread as fr
from hyper.model import signaling
from hyper.model.failure import GrowthFailure
from hyper.runs import checkpoint as ckpt
from hyper.runs import fidelity, presets, provenance
from hyper.runs.runspec import MESH_FIBERS_STOKES, MeshFile, Outputs, RunSpec
from hyper.runs.status import write_status

# growth steps. A checkpoint with the Newton state of BFLH_VHF_Left (8512 cells) takes longer
# to write than a step takes to solve: `python -m hyper.bench speed` put the I/O of its kept run
# at 1.46 s of 18.3 s with a checkpoint every 10 steps, 0.72 s of 16.8 s every 25.
CHECKPOINT_EVERY = 25
SNAPSHOT_EVERY = 24.0  # h of simulated time: a 9-week run writes 64 snapshots
SERIES = ("t", "csa_ratio", "volume_ratio", "kM", *signaling.STATES, "newton_iterations", "halvings", "wall_s")
# the regional CSA: (time, section) CSA/CSA0 at the fractions of the length the result's
# attribute section_fractions lists (hyper.fem.section.section_fractions)
SECTIONS_SERIES = "csa_ratio_sections"



class Unsaved(RuntimeError):
    """A checkpoint could not be written (a full disk, a quota): the run stops, the previous
    checkpoint stays as it was."""


class Interrupted(RuntimeError):
    """The run stopped at a step boundary on request (SIGTERM); its checkpoint is saved."""

    def __init__(self, message: str, *, step: int, t: float, checkpoint: Path | None):
        super().__init__(message)
        self.step = step
        self.t = t
        self.checkpoint = checkpoint


# ------------------------------------------------------------------------- stopping


class StopOnTerm:
    """SIGTERM sets a flag that the run reads at its step boundaries (main thread only).

    With ``comm``, entering is collective: every rank has taken over SIGTERM before any
    goes on, so a TERM (mpirun hands it to every rank) stops them all at the same step
    boundary, or else finds one still under `term.stop_at_once`, whose abort ends them all
    with 143 before any has computed a step. (A TERM inside MUMPS's factorisation, which
    ended a rank by SIGSEGV, was METIS's to take: see hyper.core.term.)
    """

    def __init__(self, comm=None):
        self.received = False
        self._previous = None
        self._comm = comm

    def _handler(self, signum, frame):
        self.received = True

    def __enter__(self):
        # PETSc installs a SIGTERM handler that aborts when it starts, which would replace
        # ours if a job started it later (the farm's first DOLFINx import did, once). The
        # entry points (term.install) have PETSc start without it; a caller that did not
        # come through them gets the same here. PETSc is still started now, before ours,
        # as it was: on every rank at once, and ours replaces a handler it already has.
        term.keep_petsc_off_signals()
        with contextlib.suppress(ImportError):  # a job without PETSc (signaling only)
            import dolfinx_solver  # noqa: F401  (must precede petsc4py)
            from petsc4py import PETSc  # noqa: F401
        with contextlib.suppress(ValueError):  # not the main thread: no handler, no stop
            self._previous = signal.signal(signal.SIGTERM, self._handler)
        if self._comm is not None:
            self._comm.Barrier()
        return self

    def __exit__(self, *exc):
        if self._previous is not None:
            signal.signal(signal.SIGTERM, self._previous)

    def __call__(self) -> bool:
        return self.received


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


# ------------------------------------------------------------------------- recording


class Series:
    """The time series of a run: one row per growth step, `SERIES`, the model's
    ``measures`` (names of `StepReport.extra`: both CSA measures of an anatomical mesh)
    and any extra columns.

    ``extra`` is (names, function): the function of the model gives the values of all the
    extra columns at once (so a reduction over the communicator serves them all); every
    rank calls it. ``sections``: the number of regional sections (`SECTIONS_SERIES`, a row
    of that many per step; 0: no such column).
    """

    def __init__(self, extra: tuple[tuple[str, ...], Callable] | None = None, measures: tuple[str, ...] = (),
                 sections: int = 0):
        self.extra_names, self.extra = extra if extra is not None else ((), None)
        self.measures = tuple(measures)
        self.sections = sections
        self.columns = (*SERIES, *self.measures, *((SECTIONS_SERIES,) if sections else ()), *self.extra_names)
        self.rows = {name: [] for name in self.columns}

    def append(self, report, model, wall_s: float) -> None:
        for name, value in zip(signaling.STATES, report.states):
            self.rows[name].append(value)
        self.rows["t"].append(report.t)
        self.rows["csa_ratio"].append(report.csa_ratio)
        self.rows["volume_ratio"].append(report.volume_ratio)
        self.rows["kM"].append(report.kM)
        self.rows["newton_iterations"].append(report.newton_iterations)
        self.rows["halvings"].append(report.halvings)
        self.rows["wall_s"].append(wall_s)
        for name in self.measures:
            self.rows[name].append(report.extra[name])
        if self.sections:
            self.rows[SECTIONS_SERIES].append(np.array(report.sections, dtype=float))
        if self.extra is not None:
            for name, value in zip(self.extra_names, self.extra(model), strict=True):
                self.rows[name].append(value)

    def arrays(self) -> dict[str, np.ndarray]:
        out = {k: np.asarray(v) for k, v in self.rows.items()}
        if self.sections and not self.rows[SECTIONS_SERIES]:
            out[SECTIONS_SERIES] = np.empty((0, self.sections))
        return out

    def restore(self, saved: dict) -> None:
        # a checkpoint from before both CSA measures (or the regional sections) were kept
        # lacks them: unknown there
        n = len(saved["t"])
        missing = {name: [float("nan")] * n for name in self.measures}
        if self.sections:
            missing[SECTIONS_SERIES] = [np.full(self.sections, np.nan)] * n
        self.rows = {name: list(saved[name]) if name in saved or name not in missing else list(missing[name])
                     for name in self.columns}

    @property
    def wall_s(self) -> float:
        return float(self.rows["wall_s"][-1]) if self.rows["wall_s"] else 0.0


def snapshot_due(kept: list[float], t: float, every: float) -> bool:
    """A snapshot is due at ``t`` (h) after those ``kept``: none yet, or ``t`` reaches the
    first multiple of ``every`` hours after the last one."""
    if not kept:
        return True
    slack = 1e-9 * every  # step times are sums of step lengths: 3 × 8 h may fall short of 24 h
    return t >= (math.floor((kept[-1] + slack) / every) + 1) * every - slack


class Snapshots:
    """Output fields of a run on spaces XDMF stores (P1 and DG0), updated in place:
    u, det Ḡ, a0, and N where each cell has its own signaling; with local mechanosensing the
    stimulus factor of each cell, one field per session intensity (they never change: with the
    first snapshot, as a0).

    Each snapshot is also kept per owned cell so that a checkpoint carries them and a
    resumed run writes them again.
    """

    def __init__(self, model, a0):
        from dolfinx import fem

        mesh = model.geometry.mesh
        self.model = model
        p1 = fem.functionspace(mesh, ("Lagrange", 1, (3,)))
        dg0 = fem.functionspace(mesh, ("DG", 0))
        self.u = fem.Function(p1, name="u")
        self.det = fem.Function(dg0, name="detGbar")
        self.a0 = fem.Function(p1, name="a0")
        self.a0.interpolate(a0)
        self.N = fem.Function(dg0, name="N") if np.ndim(model.y) == 2 else None
        cells = model.growth.cells
        # one field per session intensity: stimulus_factor, or stimulus_factor_I for several
        self.stimulus = []
        factors = model.stimulus_factors or {}
        for intensity, values in factors.items():
            f = fem.Function(dg0, name="stimulus_factor" if len(factors) == 1 else f"stimulus_factor_{intensity:g}")
            f.x.array[dg0.dofmap.list[cells][:, 0]] = values
            f.x.scatter_forward()
            self.stimulus.append(f)
        nlocal = len(cells) + mesh.topology.index_map(mesh.topology.dim).num_ghosts
        self._cells = cells
        self._local = np.arange(nlocal, dtype=np.int32)
        self._dg0_dofs = dg0.dofmap.list[cells][:, 0]
        self.times: list[float] = []
        self.kept: dict[str, list[np.ndarray]] = {name: [] for name in self._names()}

    def _names(self) -> tuple[str, ...]:
        return ("u", "det") + (("N",) if self.N is not None else ())

    def fields(self) -> tuple:
        """The fields of the snapshot just kept; the fibres, which never change, with the first only."""
        first = len(self.times) == 1
        return (self.u, self.det) + ((self.a0, *self.stimulus) if first else ()) + \
            ((self.N,) if self.N is not None else ())

    def update(self, t: float) -> tuple:
        self.u.interpolate(self.model.problem.u)
        self.det.x.array[self._dg0_dofs] = self.model.growth.cell_det()
        self.det.x.scatter_forward()
        if self.N is not None:
            self.N.x.array[self._dg0_dofs] = self.model.y[signaling.STATES.index("N")]
            self.N.x.scatter_forward()
        self._keep(t)
        return self.fields()

    def _keep(self, t: float) -> None:
        self.times.append(t)
        udofs = self.u.function_space.dofmap.list[self._cells]
        self.kept["u"].append(self.u.x.array.reshape(-1, 3)[udofs])
        self.kept["det"].append(self.det.x.array[self._dg0_dofs].copy())
        if self.N is not None:
            self.kept["N"].append(self.N.x.array[self._dg0_dofs].copy())

    def state(self) -> tuple[dict, dict]:
        """(per-cell arrays, global values) of the snapshots so far, for a checkpoint."""
        n = len(self._cells)
        empty = {"u": (n, 0, 4, 3), "det": (n, 0), "N": (n, 0)}
        per_cell = {f"snapshot_{name}": np.stack(rows, axis=1) if rows else np.empty(empty[name])
                    for name, rows in self.kept.items()}
        return per_cell, {"snapshot_t": np.asarray(self.times, dtype=float)}

    def restore(self, saved: ckpt.Checkpoint):
        """Yield (t, fields) for each saved snapshot, set on this partition, and keep them."""
        u_rows, det_rows = saved.rows("snapshot_u"), saved.rows("snapshot_det")
        n_rows = saved.rows("snapshot_N") if self.N is not None else None
        udofs = self.u.function_space.dofmap.list[self._local]
        ddofs = self.det.function_space.dofmap.list[self._local][:, 0]
        for i, t in enumerate(np.asarray(saved.glob["snapshot_t"], dtype=float)):
            self.u.x.array.reshape(-1, 3)[udofs] = u_rows[:, i]
            self.u.x.scatter_forward()
            self.det.x.array[ddofs] = det_rows[:, i]
            self.det.x.scatter_forward()
            if self.N is not None:
                self.N.x.array[ddofs] = n_rows[:, i]
                self.N.x.scatter_forward()
            self._keep(float(t))
            yield float(t), self.fields()


# ------------------------------------------------------------------------- the run


@dataclasses.dataclass
class Result:
    """A finished run: its series, the attributes of its result, and the model at the end."""

    series: dict[str, np.ndarray]
    meta: dict
    model: object
    choice: fidelity.Choice | None = None  # the spec's, with the linear solver where it was chosen


def load_geometry(comm, spec: RunSpec):
    """The geometry of ``spec``: a user's mesh file, or a built-in one with its
    quadrature degree and end tags; either refined ``spec.refine`` times."""
    from hyper.fem import geometry as geo  # DOLFINx (see `build`)

    if spec.mesh is not None:
        if spec.quadrature_degree is not None or spec.ends != "disks":
            raise InputError("quadrature degree and ends apply to the built-in geometries only")
        if spec.fibers not in (*presets.MESH_FIBERS, presets.DATA):
            raise InputError(f"--fibers {spec.fibers}: a mesh file's fibres are one of "
                             f"{', '.join(presets.MESH_FIBERS)}")
        geometry = spec.mesh.load(comm)
    else:
        kwargs = {} if spec.quadrature_degree is None else {"quadrature_degree": spec.quadrature_degree}
        geometry = geo.load(spec.geometry, comm, ends=spec.ends, estimated_surface_degree=not spec.unit_fibres,
                            **kwargs)
    for _ in range(spec.refine):
        geometry = geo.refine(geometry)
    return geometry


def mesh_stokes_fibres(comm, mesh: MeshFile, geometry=None, asked: str = "auto") -> tuple:
    """The fibres of a mesh file on its loaded (unrefined) ``geometry`` (loaded here if
    None): (a0, the fibre file read or written or None, how they were had).

    The fibre file beside the mesh (`MeshFile.fibre_file`: its own, whatever kind; with
    ``asked`` stokes its Stokes fibres) if it has one; else Stokes fibres computed, and kept
    beside the mesh where `MeshFile.fibre_cache` allows it (else computed by every run).
    Collective."""
    from hyper.fem import fibers  # DOLFINx (see `build`)

    geometry = mesh.load(comm) if geometry is None else geometry
    path = on_rank0(comm, lambda: mesh.fibre_file(asked))
    if on_rank0(comm, lambda: io.is_complete(path)):
        kind, _ = on_rank0(comm, lambda: fr.stored_fibres(path))
        info(comm, f"{mesh.path}: its {'Stokes' if kind == 'stokes' else kind} fibres read from {path}")
        return fibers.load(geometry, path), path, f"read from {path}"
    cache, why = mesh.fibre_cache(asked)
    info(comm, f"{mesh.path}: no fibre file beside it; computing its Stokes fibres"
               + (f", kept in {cache}" if cache is not None else f" (not kept: {why})"))
    a0, speed = fibers.compute(geometry)
    if cache is None:
        return a0, None, f"computed for this run (not kept: {why})"
    fibers.store(cache, geometry, a0, speed, mesh=str(mesh.path), mesh_sha256=mesh.identity()["mesh_sha256"])
    return a0, cache, f"computed and kept in {cache}"


def prepare_fibres(comm, meshes, asked: str = "auto") -> None:
    """Before runs on the mesh files ``meshes`` with their fibres (``asked``: auto or stokes,
    `MeshFile.fibre_file`): compute (once) and keep the Stokes fibres of those without that
    fibre file where `MeshFile.fibre_cache` allows, so that the runs read them and their
    digests name the file (a rerun finds its result current). `execute` does it for its
    run, a farm's caller for all its runs at once. Collective."""
    for mesh in meshes:
        if (not on_rank0(comm, lambda m=mesh: io.is_complete(m.fibre_file(asked)))
                and mesh.fibre_cache(asked)[0] is not None):
            mesh_stokes_fibres(comm, mesh, asked=asked)


def stokes_file(geometry: str, mesh: MeshFile | None = None) -> Path | None:
    """Where the Stokes fibres of a built-in ``geometry`` or a ``mesh`` file are kept, if it
    can have them: what fibres from data are compared with."""
    from hyper.fem import fibers  # DOLFINx (see `build`)
    from hyper.fem import geometry as geo

    if mesh is not None:
        return mesh.fibre_file("stokes")
    return fibers.fiber_path(geometry, kind="stokes") if geometry in geo.ANATOMICAL + geo.MESHED else None


def data_fibres(geometry, source, stokes: Path | None, label: str) -> tuple:
    """Fibres from the data file ``source`` (`hyper.fem.fiberdata`) on ``geometry``: made on
    the loaded mesh, carried onto a refinement; (a0, their record as `fiber_field`'s),
    compared with the Stokes fibres in ``stokes`` where that file holds them. Collective."""
    from hyper.fem import fiberdata, fibers  # DOLFINx (see `build`)

    comm = geometry.comm
    a0, field = fiberdata.make(geometry.base, source, *fiberdata.stokes_beside(geometry.base, stokes))
    info(comm, f"{label}: fibres from {source.path}: {fiberdata.summary(field)}")
    method = fiberdata.method(source, field)
    if geometry.refinements:
        a0 = fibers.carried(a0, geometry)
        method += fibers.CARRIED_METHOD.format(n=geometry.refinements)
    sha = on_rank0(comm, lambda: ckpt.file_digest(source.path))
    return a0, {"fibers": presets.DATA, "fibers_method": method, "fibers_sha256": sha}


def laplace_fibres(geometry) -> tuple:
    """The Laplace fibres (`hyper.fem.laplace`) made on ``geometry``'s loaded mesh, carried
    onto its refinements, and their record. Collective."""
    from hyper.fem import fibers, laplace  # DOLFINx (see `build`)

    params = laplace.LaplaceParams()
    a0, _ = laplace.compute(geometry.base, params)
    method = laplace.method(params) + "; made on the mesh run"
    info(geometry.comm, f"{geometry.name}: Laplace fibres made on the mesh run")
    if geometry.refinements:
        a0 = fibers.carried(a0, geometry)
        method += fibers.CARRIED_METHOD.format(n=geometry.refinements)
    return a0, {"fibers": laplace.KIND, "fibers_method": method, "fibers_sha256": ""}


def stored_laplace(geometry) -> bool:
    """Whether a built-in ``geometry`` keeps Laplace fibres in its fibre file (the shipped
    meshes do), read there rather than made on the run. Collective."""
    from hyper.fem import fibers  # DOLFINx (see `build`)
    from hyper.fem import geometry as geo

    if geometry.name not in geo.ANATOMICAL + geo.MESHED:
        return False
    return on_rank0(geometry.comm, lambda: fibers.stored_kind(fibers.fiber_path(geometry.name))) == presets.LAPLACE


def fiber_field(spec: RunSpec, geometry) -> tuple:
    """The fibres of ``spec`` on ``geometry`` and their record: ``fibers`` the kind used
    (never auto; "data" for a data file; a mesh file's fibre file may hold another kind
    than Stokes, "pennate" or "data", and says so), ``fibers_method`` how they were made,
    ``fibers_sha256`` the SHA-256 of the fibre file they come from ("" for a field made from a formula). Collective."""
    from hyper.fem import fibers  # DOLFINx (see `build`)

    if spec.fiber_data is not None:
        return data_fibres(geometry, spec.fiber_data, stokes_file(spec.geometry, spec.mesh), spec.label)
    # a mesh file's own fibres: the file beside it (of whatever kind), else computed Stokes
    kind = "stokes" if spec.mesh is not None and spec.fibers == "auto" else fibers.resolved(geometry, spec.fibers)
    if kind == presets.LAPLACE and not (spec.mesh is None and stored_laplace(geometry)):
        return laplace_fibres(geometry)
    base = geometry.base
    if spec.mesh is not None and kind == "stokes":
        a0, path, how = mesh_stokes_fibres(geometry.comm, spec.mesh, base, spec.fibers)
        if geometry.refinements:
            a0 = fibers.carried(a0, geometry)
        method = fibers.method(geometry, kind) + f"; {how}"
        stored, made = on_rank0(geometry.comm, lambda: fr.stored_fibres(path)) if path is not None else ("stokes", "")
        if stored != "stokes":  # a fibre file of another kind beside the mesh (hyper fibers --method pennate)
            carried_over = fibers.CARRIED_METHOD.format(n=geometry.refinements) if geometry.refinements else ""
            kind, method = stored, f"{made}{carried_over}; {how}"
    else:
        return built_in_fibres(geometry, spec.geometry, kind)
    sha = on_rank0(geometry.comm, lambda: ckpt.file_digest(path)) if path is not None else ""
    return a0, {"fibers": kind, "fibers_method": method, "fibers_sha256": sha}


def built_in_fibres(geometry, name: str, kind: str) -> tuple:
    """The fibres of ``kind`` (resolved: not auto) of the built-in geometry ``name`` on
    ``geometry`` (it or a refinement of it) and their record; a fibre file's (Stokes, the
    shipped Laplace) as the file says it made them. Collective."""
    from hyper.fem import fibers  # DOLFINx (see `build`)

    a0 = fibers.fiber_field(geometry, kind)
    if kind not in ("stokes", presets.LAPLACE):
        return a0, {"fibers": kind, "fibers_method": fibers.method(geometry, kind), "fibers_sha256": ""}
    path = fibers.fiber_path(name, kind=kind)
    made = fibers.method(geometry, kind)
    if kind == presets.LAPLACE:  # its parameters are the file's
        carried_over = fibers.CARRIED_METHOD.format(n=geometry.refinements) if geometry.refinements else ""
        made = on_rank0(geometry.comm, lambda: fr.stored_fibres(path)[1]) + carried_over
    info(geometry.comm, f"{name}: its {'Stokes' if kind == 'stokes' else 'Laplace'} fibres read from {path}")
    return a0, {"fibers": kind, "fibers_method": f"{made}; read from {path}",
                "fibers_sha256": on_rank0(geometry.comm, lambda: ckpt.file_digest(path))}


def cell_params(spec: RunSpec, geometry):
    """The signaling parameters of ``spec`` on this rank's cells."""
    if spec.heterogeneity is None:
        return spec.params
    from hyper.model import heterogeneity  # SciPy's FFT, for per-cell fields only

    return heterogeneity.cell_params(geometry.mesh, spec.heterogeneity, spec.seed, spec.params)


def build(comm, spec: RunSpec, *, monitor=None, integrator=None):
    """The coupled model of ``spec``, its fibre field, the linear solver's and the fibres'
    attributes (`fiber_field`'s record) and
    the fidelity choice completed with it (``auto``: by `fidelity.linear_solver` from the
    unknowns and the memory available). ``monitor`` and ``integrator`` go to the model
    (`hyper.fem.coupled.build_model`): a timing monitor, another ODE integrator."""
    # the finite elements load DOLFINx: not at the driver's import, which the signaling-only jobs share
    from hyper.fem.coupled import build_model
    from hyper.fem.mechanics import taylor_hood_unknowns

    geometry = load_geometry(comm, spec)
    a0, fibres = fiber_field(spec, geometry)
    choice = spec.choice
    solver, reason = spec.linear_solver, "asked for (--linear-solver)"
    if solver == "auto":
        unknowns, memory = taylor_hood_unknowns(geometry.mesh), available_memory_mb(comm)
        if choice is None:
            solver, reason = fidelity.linear_solver(unknowns, memory)
        else:
            choice = choice.with_linear_solver(unknowns, memory)
            solver, reason = choice.linear_solver, choice.linear_solver_reason
        info(comm, f"fidelity: {reason}")
    kwargs = {name: value for name, value in (("monitor", monitor), ("integrator", integrator)) if value is not None}
    model = build_model(geometry, a0, spec.protocol, params=cell_params(spec, geometry), material=spec.material,
                        settings=spec.settings, petsc_options=dict(spec.petsc_options), linear_solver=solver,
                        normalize_fibres=spec.unit_fibres, **kwargs)
    return model, a0, {"linear_solver": solver, "linear_solver_reason": reason, **fibres}, choice


def execute(comm, spec: RunSpec, outputs: Outputs, *, snapshot_every: float = SNAPSHOT_EVERY,
            checkpoint_every: int = CHECKPOINT_EVERY, stop: Callable[[], bool] | None = None,
            extra_series: tuple[tuple[str, ...], Callable] | None = None, checkpoints: bool = True,
            progress_every: float = PROGRESS_EVERY, monitor=None) -> Result:
    """Run ``spec``, writing its snapshots to ``outputs.fields`` (the first state, then every
    ``snapshot_every`` simulated hours and the last); return its `Result`. Progress
    lines come at most every ``progress_every`` seconds of wall time.

    With ``checkpoints``, the run resumes from ``outputs.checkpoint`` if it exists (it
    must belong to this run: InputError otherwise), saves its state there every
    ``checkpoint_every`` growth steps (0: never on schedule), when ``stop()`` turns true
    on some rank (then raises `Interrupted`) and before a `GrowthFailure` propagates
    (whose ``checkpoint`` attribute names the file); either way ``outputs.status`` says
    what happened. The caller stores the result (`Outputs.store`), which drops the
    checkpoint. The status file of a failed run records the command (`hyper.core.io.command`).
    Collective over ``comm``.
    """
    if spec.mesh is not None and spec.fibers in MESH_FIBERS_STOKES:
        prepare_fibres(comm, [spec.mesh], spec.fibers)  # before the digest, which names the fibre file
    run_digest = spec.digest()
    model, a0, solver, choice = build(comm, spec, monitor=monitor)
    snaps = Snapshots(model, a0)
    sections = 0 if model.regional is None else len(model.regional.fractions)
    series = Series(extra_series, model.measures, sections)
    segments = 1
    saved = None
    path = outputs.checkpoint
    if checkpoints:
        # a checkpoint write killed halfway leaves its temporary file: never read, remove it
        on_rank0(comm, lambda: Path(str(path) + io.PARTIAL).unlink(missing_ok=True))
        if on_rank0(comm, path.is_file):
            saved = ckpt.read(comm, path, run_digest, model.local_original_cells())
            model.restore(saved)
            series.restore(saved.series)
            segments = int(saved.attrs["segments"]) + 1
            info(comm, f"{spec.label}: resuming from {path} at step {model.step} (t = {model.t:g} h), "
                       f"written on {saved.attrs['ranks']} rank(s)")
    wall0 = series.wall_s

    def save(status: str) -> None:
        state = model.state()
        snap_cells, snap_glob = snaps.state()
        try:
            ckpt.write(comm, path, state.original, {**state.per_cell, **snap_cells}, {**state.glob, **snap_glob},
                       series.arrays(),
                       {"run_digest": run_digest, "step": model.step, "t": model.t, "segments": segments,
                        "status": status, "geometry": spec.geometry, "protocol": spec.protocol.name})
        except OSError as err:  # raised on every rank alike
            kept = "the previous checkpoint is kept" if on_rank0(comm, path.is_file) else "no checkpoint yet"
            with contextlib.suppress(OSError):  # a disk too full for the checkpoint may take no status either
                stopped("failed", reason=str(err), step=model.step, t_h=model.t, checkpoint=kept,
                        resume="make room, then run the same command again")
            raise Unsaved(f"{err}; {kept}") from None

    def stopped(state: str, **status) -> None:
        on_rank0(comm, lambda: write_status(outputs.status, {"state": state, **status}))

    end = spec.protocol.end
    progress = Progress(comm, end, spec.label, every=progress_every)
    start = time.perf_counter()
    last_saved = model.step
    with io.atomic_xdmf(comm, outputs.fields) as xdmf:
        xdmf.write_mesh(model.geometry.mesh)
        if saved is not None:
            for t, fields in snaps.restore(saved):
                for f in fields:
                    xdmf.write_function(f, t)
        try:
            for report in model.run():
                series.append(report, model, wall0 + time.perf_counter() - start)
                last = report.t >= end
                if snapshot_due(snaps.times, report.t, snapshot_every) or last:
                    for f in snaps.update(report.t):
                        xdmf.write_function(f, report.t)
                progress.update(report.t, f"day {report.t / 24:5.1f}, CSA/CSA0 {report.csa_ratio:.5f}, "
                                          f"V/V0 {report.volume_ratio:.5f}", force=last)
                if last or not checkpoints:
                    continue
                if stop is not None and comm.allreduce(bool(stop()), op=MPI.LOR):
                    save("interrupted")
                    stopped("interrupted", reason="SIGTERM", step=model.step, t_h=model.t, checkpoint=path,
                            resume="run the same command again")
                    raise Interrupted(f"stopped on request at step {model.step} (t = {model.t:g} h); "
                                      f"state saved in {path}", step=model.step, t=model.t, checkpoint=path)
                if checkpoint_every and model.step - last_saved >= checkpoint_every:
                    save("running")
                    last_saved = model.step
        except GrowthFailure as err:
            err.checkpoint = None
            if checkpoints:
                save("failed")
                err.checkpoint = path
                stopped("failed", reason=str(err), failed_step=err.step, from_h=err.t0, to_h=err.t1,
                        checkpoint=path, geometry=spec.geometry, protocol=spec.protocol.to_attributes(),
                        params=as_attributes(spec.params), settings=dataclasses.asdict(spec.settings),
                        petsc_options=dict(spec.petsc_options), ranks=comm.size, command=io.command(),
                        resume="run the command again, e.g. with a larger --max-halvings")
                err.args = (f"{err}; state after step {err.step - 1} saved in {path}, details in {outputs.status}",)
            raise
    meta = {
        "geometry": spec.geometry,
        "mesh_sha256": on_rank0(comm, lambda: ckpt.file_digest(*spec.mesh_files())),
        "quadrature_degree": model.geometry.quadrature_degree,
        "ends": spec.ends,
        "refine": spec.refine,
        "surface_quadrature_degree": "estimated" if model.geometry.estimated_surface_degree
        else model.geometry.quadrature_degree,
        "csa0_m2": model.csa0,
        **{f"csa0_{name}_m2": area for name, area in model.csa0_by_method.items()},
        "volume0_m3": model.volume0,
        **({} if model.regional is None else {"section_fractions": model.regional.fractions,
                                              "csa0_sections_m2": model.regional.areas0}),
        "ranks": comm.size,
        "growth_steps": model.step,
        "wall_s": wall0 + time.perf_counter() - start,
        "segments": segments,
        "run_digest": run_digest,
        "unknowns": model.problem.num_dofs,
        **model.stimulus_record,
        "study": provenance.study_text(spec),
        **solver,
    }
    return Result(series.arrays(), meta, model, choice)
