"""Heterogeneous signaling ensembles (MODEL.md §6, the paper's Fig. 7): the uniform case
and samples of per-cell signaling parameters (`hyper.model.heterogeneity`), one coupled
run each (`run_sample`), with the spread of each signaling state across cells in the
series, the final cell fields gathered in input-cell order and their roughness; the
ensemble's summary.json and figures (`write_results`, `hyper.analysis.ensembleplot`).

Roughness of a cell field f: R(f) = sqrt(mean over interior facets of
((f_a − f_b)/|x_a − x_b|)²) / std(f), with a, b the facet's two cells and x their
midpoints; an inverse length (1/m). Independent cell noise has R ≈ √2/(cell spacing),
a field varying over the body's size R ≈ 1/size.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
import numpy as np
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh
from mpi4py import MPI

from hyper.analysis.ensembleplot import figures
from hyper.core import io
from hyper.core.log import PROGRESS_EVERY
from hyper.model import heterogeneity, signaling
from hyper.runs import driver, farm, runspec

STD = tuple(f"{s}_std" for s in signaling.STATES)
FIELDS = ("N", "detGbar", "u")


@dataclasses.dataclass(frozen=True)
class Sample:
    """One run of an ensemble: the uniform case (no heterogeneity) or a heterogeneous sample."""

    spec: runspec.RunSpec
    h5: Path

    @property
    def outputs(self) -> runspec.Outputs:
        return runspec.Outputs(self.h5)


class FinalFields:
    """N, det Ḡ and |u| per cell (DG0, ghosts included) at the end of a run."""

    def __init__(self, model):
        mesh = model.geometry.mesh
        self.mesh = mesh
        dg0 = fem.functionspace(mesh, ("DG", 0))
        self._dofs = dg0.dofmap.list[model.growth.cells][:, 0]
        self.fields = {name: fem.Function(dg0, name=name) for name in FIELDS}
        self.fields["N"].x.array[self._dofs] = model.y[signaling.STATES.index("N")]
        self.fields["detGbar"].x.array[self._dofs] = model.growth.cell_det()
        u = model.problem.u
        self.fields["u"].interpolate(fem.Expression(ufl.sqrt(ufl.dot(u, u)), dg0.element.interpolation_points))
        for f in self.fields.values():
            f.x.scatter_forward()

    def cell_values(self) -> dict[str, np.ndarray]:
        """The fields of FIELDS at the owned cells (|u| at the midpoints)."""
        return {name: f.x.array[self._dofs].copy() for name, f in self.fields.items()}

    def roughness(self) -> dict[str, float]:
        """R(f) of the module docstring for each field (NaN for a constant field)."""
        mesh = self.mesh
        tdim = mesh.topology.dim
        mesh.topology.create_connectivity(tdim - 1, tdim)
        f2c = mesh.topology.connectivity(tdim - 1, tdim)
        nfacets = mesh.topology.index_map(tdim - 1).size_local
        offsets = f2c.offsets[: nfacets + 1]
        interior = np.flatnonzero(np.diff(offsets) == 2)
        a, b = f2c.array[offsets[interior]], f2c.array[offsets[interior] + 1]
        cells = mesh.topology.index_map(tdim)
        nowned, ncells = cells.size_local, cells.size_local + cells.num_ghosts
        mid = mesh.geometry.x[dmesh.entities_to_geometry(mesh, tdim, np.arange(ncells, dtype=np.int32))].mean(axis=1)
        dist = np.linalg.norm(mid[a] - mid[b], axis=1)
        dofs = self.fields["N"].function_space.dofmap.list[:, 0]
        comm = mesh.comm
        count = comm.allreduce(len(interior), op=MPI.SUM)
        out = {}
        for name, f in self.fields.items():
            v = f.x.array[dofs]
            grad2 = comm.allreduce(float(np.sum(((v[a] - v[b]) / dist) ** 2)), op=MPI.SUM) / count
            out[name] = float(np.sqrt(grad2) / global_std(comm, v[:nowned]))
        return out


def global_std(comm, values: np.ndarray) -> float:
    """Standard deviation over all ranks; NaN for a field constant to round-off."""
    n = comm.allreduce(values.size, op=MPI.SUM)
    mean = comm.allreduce(float(values.sum()), op=MPI.SUM) / n
    std = np.sqrt(comm.allreduce(float(((values - mean) ** 2).sum()), op=MPI.SUM) / n)
    return float(std) if std > 1e-12 * abs(mean) else float("nan")


def state_std(comm, y: np.ndarray) -> np.ndarray:
    """Standard deviation across all cells of each signaling state (zeros for one ODE)."""
    if y.ndim == 1:
        return np.zeros(len(y))
    n = comm.allreduce(y.shape[1], op=MPI.SUM)
    mean = comm.allreduce(y.sum(axis=1), op=MPI.SUM) / n
    return np.sqrt(comm.allreduce(((y - mean[:, None]) ** 2).sum(axis=1), op=MPI.SUM) / n)


def gather_cells(comm, mesh, values: dict[str, np.ndarray], points: np.ndarray) -> dict[str, np.ndarray] | None:
    """Owned-cell arrays gathered on rank 0 in input-cell order (None elsewhere)."""
    original, _ = heterogeneity.cell_identity(mesh)
    parts = comm.gather((original, points, values), root=0)
    if comm.rank != 0:
        return None
    order = np.argsort(np.concatenate([p[0] for p in parts]))
    out = {"final_x": np.concatenate([p[1] for p in parts])[order]}
    for name in values:
        out[f"final_{name}"] = np.concatenate([p[2][name] for p in parts])[order]
    return out


def std_columns(comm) -> tuple[tuple[str, ...], Callable]:
    """The series columns of the spread of each state across all cells, one reduction a step."""
    return STD, lambda model: state_std(comm, model.y)


def run_sample(comm, sample: Sample, *, snapshot_every: float, stop=None,
               progress_every: float = PROGRESS_EVERY) -> dict:
    """One coupled run of an ensemble, with checkpoints; writes its series and fields.
    Collective over comm; raises run.Interrupted after a SIGTERM (checkpoint saved)."""
    spec = sample.spec
    done = driver.execute(comm, spec, sample.outputs, snapshot_every=snapshot_every, stop=stop,
                       extra_series=std_columns(comm), progress_every=progress_every)
    final = FinalFields(done.model)
    rough = final.roughness()
    cells = gather_cells(comm, final.mesh, final.cell_values(), heterogeneity.cell_midpoints(final.mesh))
    if comm.rank == 0:
        attrs = {**done.meta, "protocol": spec.protocol.name, "seed": -1 if spec.seed is None else spec.seed}
        attrs |= {f"roughness_{k}": v for k, v in rough.items()}
        groups = runspec.result_groups(spec)
        groups.setdefault("heterogeneity", {"model": "uniform"})
        sample.outputs.store(done.series | cells, attrs, groups)
    return {"csa_ratio": float(done.series["csa_ratio"][-1]), "volume_ratio": float(done.series["volume_ratio"][-1]),
            "wall_s": done.meta["wall_s"]}


# ------------------------------------------------------------------------------ summary


def summary(uniform: dict, samples: dict[str, dict]) -> dict:
    """Final ratios of the ensemble against the uniform case, spread and roughness."""
    out = {"uniform": {k: float(uniform[k][-1]) for k in ("csa_ratio", "volume_ratio", "kM")}}
    for key in ("csa_ratio", "volume_ratio"):
        final = np.array([s[key][-1] for s in samples.values()])
        u = out["uniform"][key]
        out[key] = {
            "samples": final.tolist(),
            "mean": float(final.mean()),
            "std": float(final.std(ddof=1)) if len(final) > 1 else 0.0,
            "mean_minus_uniform": float(final.mean() - u),
            "growth_deficit_percent": float(100 * (u - final.mean()) / (u - 1.0)),
        }
    rough = {f: np.array([s[f"roughness_{f}"] for s in samples.values()]) for f in FIELDS}
    out["roughness_per_m"] = {f: {"mean": float(r.mean()), "samples": r.tolist()} for f, r in rough.items()}
    out["roughness_ratio_detGbar_over_u"] = float(np.mean(rough["detGbar"] / rough["u"]))
    out["roughness_ratio_N_over_u"] = float(np.mean(rough["N"] / rough["u"]))
    return out


def read(path: str) -> dict:
    data = io.read_series(path)
    with io.reading_h5(path) as f:
        data.update({k: f.attrs[k] for k in f.attrs if k.startswith("roughness_")})
    return data


def write_results(jobs: list[farm.Job], het: heterogeneity.Heterogeneity, results: list[farm.JobResult],
                  folder: Path, title: str) -> tuple[dict, list[Path]]:
    """Rank 0, once every run is done: the summary (`summary`, with the heterogeneity,
    the settings and each run's wall time) in folder/summary.json, and the figures.
    ``jobs``: the uniform case first, then the samples (their payloads `Sample`)."""
    uniform = read(jobs[0].payload.h5)
    samples = {job.key: read(job.payload.h5) for job in jobs[1:]}
    numbers = summary(uniform, samples)
    numbers["heterogeneity"] = het.attributes()
    numbers["settings"] = dataclasses.asdict(jobs[0].payload.spec.settings)
    numbers["wall_s"] = {r.key: r.wall_s for r in results}
    folder.mkdir(parents=True, exist_ok=True)
    io.write_json(folder / "summary.json", numbers)
    return numbers, figures(uniform, samples, folder, title)
