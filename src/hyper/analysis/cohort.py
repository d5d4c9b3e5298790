"""The anatomical cohort's runs (the paper's Fig. 6): every geometry with every protocol,
each one job of `hyper.runs.farm` (longest first, by the estimate mesh cells × growth
steps), run by `hyper.runs.driver.execute` on its group's communicator, with
checkpoints, its own log and a skip of what is done (`hyper cohort`, `hyper study`).

Per run, under OUTPUT/runs/: GEOMETRY_PROTOCOL.h5 (the series with the run's
provenance), GEOMETRY_PROTOCOL_fields.xdmf (snapshots) and GEOMETRY_PROTOCOL.log (its
progress lines). The summary, table and figures are `hyper.analysis.cohortsummary`'s.
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
import threading
import time
from collections.abc import Mapping
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
from mpi4py import MPI

from hyper.core.collective import on_rank0
from hyper.core.log import PROGRESS_EVERY
from hyper.core.params import InputError
from hyper.fem import geometry as geo
from hyper.fem.coupled import GrowthSettings
from hyper.model import protocols, signaling
from hyper.model.growth import step_times
from hyper.model.protocols import Protocol
from hyper.runs import checkpoint as ckpt
from hyper.runs import driver, farm, locks, measured, presets, runspec

PAPER_PROTOCOLS = protocols.PAPER  # in the paper's order of growth: mwf > every3days > weekly


@dataclasses.dataclass(frozen=True)
class Run:
    geometry: str  # a built-in geometry id, or the stem of ``mesh``
    protocol: Protocol
    mesh: runspec.MeshFile | None = None  # a user's mesh file (hyper study); None: the built-in geometry
    fibres: object = None  # fibres from data (hyper.fem.fiberread.Source); None: the geometry's kind

    @property
    def key(self) -> str:
        return f"{self.geometry}_{self.protocol.name}"


def plan(geometries, protocol_list, meshes: Mapping[str, runspec.MeshFile] | None = None,
         fibres: Mapping | None = None) -> list[Run]:
    """Every geometry with every protocol; names must make unique run keys. ``meshes``
    maps the geometries that are a user's mesh file to it, ``fibres`` those with fibres
    from data to their file (`hyper.fem.fiberread.Source`)."""
    meshes, fibres = meshes or {}, fibres or {}
    runs = [Run(g, p, meshes.get(g), fibres.get(g)) for g in geometries for p in protocol_list]
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


def data_fields(source) -> dict:
    """The `RunSpec` fields of fibres from data ``source`` (none for None)."""
    return {} if source is None else {"fibers": presets.DATA, "fiber_data": source}


def spec(entry: Run, params, settings: GrowthSettings, options: Mapping | None = None) -> runspec.RunSpec:
    """The run of ``entry``; ``options`` more `RunSpec` fields (heterogeneity, seed,
    linear_solver, choice, quadrature_degree: what a study file sets); the entry's fibres
    from data win over a fibre kind there."""
    return runspec.RunSpec(entry.geometry, entry.protocol, params, settings, mesh=entry.mesh,
                           **{**(options or {}), **data_fields(entry.fibres)})


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


class RunLog:
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
               snapshot_every: float = driver.SNAPSHOT_EVERY, ranks_per_job: int = 1, stop=None,
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
        # the run's own lock, as `hyper grow` takes it: the folder's lock alone let a grow on
        # runs/KEY.h5 and this run share the checkpoint
        with locks.hold(subcomm, [out.h5]):
            on_rank0(subcomm, lambda: drop_stale_checkpoint(out.checkpoint, digests[entry.key]))
            try:
                with RunLog(out.h5.with_suffix(".log")) if subcomm.rank == 0 else contextlib.nullcontext():
                    done = driver.execute(subcomm, specs[entry.key], out, snapshot_every=snapshot_every, stop=stop,
                                          progress_every=progress_every)
            except driver.Interrupted:
                return interrupted
            if subcomm.rank != 0:
                return None
            groups = runspec.result_groups(specs[entry.key], done.choice)
            against = data if data is not None else measured.of_protocol(entry.protocol, entry.geometry)
            if against is not None:
                groups["data"] = measured.compare(against, done.series["t"], done.series["csa_ratio"],
                                                  measured.run_sections(done.series, done.meta)).attributes()
            out.store(done.series, {**done.meta, **member(entry.geometry), "protocol": entry.protocol.name}, groups)
            return {"csa_ratio": float(done.series["csa_ratio"][-1]),
                    "volume_ratio": float(done.series["volume_ratio"][-1])}

    return farm.run(comm, jobs, work, ranks_per_job=ranks_per_job, is_done=is_done, label="cohort",
                    progress_every=progress_every)


def idle_barrier(comm) -> None:
    """A barrier at which waiting ranks sleep, instead of spinning in MPI and taking a core
    from rank 0 while it writes the summary and figures."""
    request = comm.Ibarrier()
    while not request.Test():
        time.sleep(0.05)

