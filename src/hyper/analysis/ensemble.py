"""python -m hyper.ensemble: heterogeneous signaling ensembles (MODEL.md §6, the paper's Fig. 7).

    python -m hyper.ensemble --geometry BFLH_VHF_Left --protocol mwf --samples 5 --epsilon 0.01
    mpirun -n 2 python -m hyper.ensemble ... --model matern --length 0.03

Runs the uniform case (the homogeneous model: one ODE for the body) and N samples of
per-cell signaling parameters p = p0 (1 + ε ξ) (`hyper.model.heterogeneity`; sample i uses
seed first_seed + i), one coupled run each, farmed over the ranks with `hyper.runs.farm`
(--ranks-per-job ranks per run). Per run it writes an HDF5 series (t, CSA and volume
ratios, kM, the cell mean of each signaling state and its standard deviation across
cells `<state>_std`, Newton iterations), the final cell fields gathered in input-cell
order (`final_x` midpoints, `final_N`, `final_detGbar`, `final_u` = |u| at the
midpoints) and their roughness, and an XDMF file of snapshots (N and det Ḡ as DG0, the
growth displacement u as P1). Files:

    OUTPUT/GEOMETRY_PROTOCOL/uniform.h5                 (shared by every model and ε)
    OUTPUT/GEOMETRY_PROTOCOL/LABEL/seedI.h5, seedI_fields.xdmf/.h5
    OUTPUT/GEOMETRY_PROTOCOL/LABEL/summary.json, fig7a_states.png, fig7b_growth.png, fig7c_maps.png

with LABEL e.g. uniform-noise_eps0.01. A run whose complete .h5 exists for the same run
(hyper.runs.driver's digest: geometry, protocol, heterogeneity, seed, settings) is skipped, so a
rerun only redoes what is missing (and the figures). Runs checkpoint and resume as
hyper grow's do (RESULT.ckpt.h5 every run.CHECKPOINT_EVERY growth steps and at the first step boundary
after a SIGTERM; exit status 143, and the same command continues them).

Roughness of a cell field f: R(f) = sqrt(mean over interior facets of
((f_a − f_b)/|x_a − x_b|)²) / std(f), with a, b the facet's two cells and x their
midpoints; an inverse length (1/m). Independent cell noise has R ≈ √2/(cell spacing),
a field varying over the body's size R ≈ 1/size.

The states are sampled at the ends of the growth steps (Δtg, default 24 h, and the
session boundaries), so the IGF1/AKT spikes between them are not resolved in Fig. 7A.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
import numpy as np
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh
from mpi4py import MPI

from hyper.commands import cli
from hyper.core import io
from hyper.core.log import PROGRESS_EVERY, hms, info
from hyper.core.params import InputError, build
from hyper.fem.coupled import GrowthSettings
from hyper.model import heterogeneity, protocols, signaling
from hyper.runs import driver as run
from hyper.runs import farm, locks, plot, runspec

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
    done = run.execute(comm, spec, sample.outputs, snapshot_every=snapshot_every, stop=stop,
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
    import h5py

    data = io.read_series(path)
    with h5py.File(path, "r") as f:
        data.update({k: f.attrs[k] for k in f.attrs if k.startswith("roughness_")})
    return data


def figures(uniform: dict, samples: dict[str, dict], folder: Path, title: str) -> list[Path]:
    """Fig. 7A (states), 7B (CSA, volume, kM) and 7C (maps of N, det Ḡ, |u|)."""
    plt = plot.pyplot()
    paths = [folder / "fig7a_states.png", folder / "fig7b_growth.png", folder / "fig7c_maps.png"]
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    names = {"igf1": "IGF1", "akt": "AKT", "foxo": "FOXO", "mtor": "mTOR", "N": "N"}

    fig, axes = plt.subplots(1, 5, figsize=(18, 3.6), constrained_layout=True)
    for ax, state in zip(axes, signaling.STATES):
        for i, (key, s) in enumerate(samples.items()):
            w = s["t"] / 168.0
            ax.fill_between(w, s[state] - s[f"{state}_std"], s[state] + s[f"{state}_std"],
                            color=colors[i % len(colors)], alpha=0.25, lw=0)
            ax.plot(w, s[state], color=colors[i % len(colors)], lw=0.8, label=key)
        ax.plot(uniform["t"] / 168.0, uniform[state], "k--", lw=1.0, label="uniform")
        ax.set_title(names[state])
        ax.set_xlabel("time (weeks)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"{title}: cell mean ± std across cells")
    plot.save(fig, paths[0], dpi=130)

    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8), constrained_layout=True)
    for key, label, scale in (("csa_ratio", "CSA change (%)", 100), ("volume_ratio", "volume change (%)", 100),
                              ("kM", "kM (1/h)", None)):
        ax = axes[["csa_ratio", "volume_ratio", "kM"].index(key)]
        for i, (name, s) in enumerate(samples.items()):
            y = scale * (s[key] - 1) if scale else s[key]
            ax.plot(s["t"] / 168.0, y, color=colors[i % len(colors)], lw=0.8, label=name)
        mean = np.mean([s[key] for s in samples.values()], axis=0)
        t = next(iter(samples.values()))["t"] / 168.0
        ax.plot(t, scale * (mean - 1) if scale else mean, color="C3", lw=2, alpha=0.6, label="ensemble mean")
        ax.plot(uniform["t"] / 168.0, scale * (uniform[key] - 1) if scale else uniform[key], "k--", lw=1.2,
                label="uniform")
        ax.set_ylabel(label)
        ax.set_xlabel("time (weeks)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(title)
    plot.save(fig, paths[1], dpi=130)

    first = next(iter(samples.values()))
    x = first["final_x"]
    centred = x - x.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    q = centred @ vt.T  # principal coordinates: long axis first
    spacing = (np.ptp(x, axis=0).prod() / len(x)) ** (1 / 3)
    slab = np.abs(q[:, 2]) < spacing
    fig, axes = plt.subplots(1, 3, figsize=(15, 5), constrained_layout=True)
    for ax, (key, label) in zip(axes, (("final_N", "N"), ("final_detGbar", "det Ḡ"), ("final_u", "|u| (mm)"))):
        v = first[key] * (1e3 if key == "final_u" else 1.0)
        sc = ax.scatter(1e3 * q[slab, 0], 1e3 * q[slab, 1], c=v[slab], s=12, cmap="viridis")
        fig.colorbar(sc, ax=ax, shrink=0.8)
        ax.set_title(f"{label}, {next(iter(samples))}")
        ax.set_aspect("equal")
        ax.set_xlabel("first principal axis (mm)")
    axes[0].set_ylabel("second principal axis (mm)")
    fig.suptitle(f"{title}: cells within {1e3 * spacing:.1f} mm of the principal plane, t = {first['t'][-1]:g} h")
    plot.save(fig, paths[2], dpi=130)
    return paths


# ---------------------------------------------------------------------------------- CLI


def parser() -> cli.Parser:
    p = cli.Parser("ensemble", __doc__)
    p.add_argument("--geometry", default="BFLH_VHF_Left", help="geometry id (idealized, BFLH_VHF_Left, …)")
    p.add_argument("--protocol", default="mwf", metavar="NAME|FILE",
                   help=f"a named protocol ({', '.join(protocols.NAMES)}) or a TOML protocol file")
    p.add_argument("--samples", type=cli.integer(1), default=5, help="heterogeneous samples besides the uniform case")
    p.add_argument("--first-seed", type=cli.integer(0, 2**32 - 1), default=1,
                   help="seed of the first sample (then +1 each)")
    p.add_argument("--epsilon", type=float, default=0.01, help="relative half-width ε of the perturbation")
    p.add_argument("--model", choices=heterogeneity.MODELS, default="uniform-noise", help="heterogeneity model")
    p.add_argument("--length", type=float, default=heterogeneity.Heterogeneity.length,
                   help="Matérn correlation range ℓ (m; matern only)")
    p.add_argument("--nu", type=float, default=heterogeneity.Heterogeneity.nu, help="Matérn smoothness ν (matern only)")
    p.add_argument("--growth-dt", type=float, default=GrowthSettings.growth_dt, help="growth step Δtg (h)")
    p.add_argument("--signaling-dt", type=float, default=GrowthSettings.signaling_dt, help="RK4 step (h)")
    p.add_argument("--ranks-per-job", type=cli.integer(1), default=1, help="MPI ranks per coupled run")
    p.add_argument("--snapshot-every", type=cli.positive("hours"), default=run.SNAPSHOT_EVERY, metavar="HOURS",
                   help="fields snapshot every HOURS of simulated time, besides the first and the last state")
    p.add_argument("--output", type=cli.output(folder=True), default="results/ensemble", help="results folder")
    cli.progress_option(p)
    return p


def plan(comm, args) -> tuple[list[farm.Job], heterogeneity.Heterogeneity, Path]:
    """Jobs, heterogeneity and the sample folder; InputError on bad input."""
    runspec.check_geometry(comm, args.geometry)
    (protocol,) = protocols.from_option(args.protocol) if args.protocol != "all" else (None,)
    if protocol is None:
        raise InputError("--protocol: an ensemble runs one protocol, not 'all'")
    het = heterogeneity.Heterogeneity(model=args.model, epsilon=args.epsilon, length=args.length, nu=args.nu)
    settings = build(GrowthSettings, {"growth_dt": "--growth-dt", "signaling_dt": "--signaling-dt"},
                     growth_dt=args.growth_dt, signaling_dt=args.signaling_dt)
    base = args.output / f"{args.geometry}_{protocol.name}"
    folder = base / het.label()

    def job(key, het, seed, h5):
        spec = runspec.RunSpec(args.geometry, protocol, settings=settings, heterogeneity=het, seed=seed)
        return farm.Job(key, 1.0, Sample(spec, h5))

    jobs = [job("uniform", None, None, base / "uniform.h5")]
    for i in range(args.samples):
        seed = args.first_seed + i
        jobs.append(job(f"seed{seed}", het, seed, folder / f"seed{seed}.h5"))
    return jobs, het, folder


def ensemble(comm, args) -> int:
    jobs, het, folder = plan(comm, args)
    if args.ranks_per_job < 1 or comm.size % args.ranks_per_job:
        raise InputError(f"--ranks-per-job must be >= 1 and divide the number of ranks ({comm.size}), "
                         f"got {args.ranks_per_job}")
    protocol = jobs[0].payload.spec.protocol.name
    digests = {job.key: job.payload.spec.digest() for job in jobs}
    start = time.perf_counter()

    def work(sub, job, stop):
        # after a SIGTERM the runs not started yet are not started at all
        if sub.allreduce(bool(stop()), op=MPI.LOR):
            return {"interrupted": True}
        try:
            return run_sample(sub, job.payload, snapshot_every=args.snapshot_every, stop=stop,
                              progress_every=args.progress_every)
        except run.Interrupted:
            return {"interrupted": True}

    with locks.hold(comm, [folder]), run.StopOnTerm() as stop:
        results = farm.run(
            comm, jobs, lambda sub, job: work(sub, job, stop), ranks_per_job=args.ranks_per_job,
            is_done=lambda job: job.payload.outputs.is_current(digests[job.key]),
            label=f"ensemble {args.geometry}/{protocol}/{het.label()}", progress_every=args.progress_every,
        )
    info(comm, farm.summary_line(results) + f" in {hms(time.perf_counter() - start)}")
    for r in results:
        if r.status == "failed":
            info(comm, f"{r.key} failed:\n{r.error}")
    failed = any(r.status == "failed" for r in results)
    interrupted = comm.allreduce(stop(), op=MPI.LOR)
    if interrupted:
        info(comm, "stopped by SIGTERM: run the same command again to continue from the checkpoints")
        return cli.EXIT_TERMINATED
    if comm.rank != 0 or failed:
        return cli.EXIT_SOME_FAILED if failed else cli.EXIT_OK
    uniform = read(jobs[0].payload.h5)
    samples = {job.key: read(job.payload.h5) for job in jobs[1:]}
    numbers = summary(uniform, samples)
    numbers["heterogeneity"] = het.attributes()
    numbers["settings"] = dataclasses.asdict(jobs[0].payload.spec.settings)
    numbers["wall_s"] = {r.key: r.wall_s for r in results}
    folder.mkdir(parents=True, exist_ok=True)
    with io.atomic_path(folder / "summary.json") as tmp:
        tmp.write_text(json.dumps(numbers, indent=2))
    title = f"{args.geometry}, {protocol}, {het.label()}"
    paths = figures(uniform, samples, folder, title)
    c, v = numbers["csa_ratio"], numbers["volume_ratio"]
    info(comm, f"uniform: CSA/CSA0 {numbers['uniform']['csa_ratio']:.5f}, V/V0 "
               f"{numbers['uniform']['volume_ratio']:.5f}; ensemble mean CSA/CSA0 {c['mean']:.5f} (std "
               f"{c['std']:.2e}), V/V0 {v['mean']:.5f} (std {v['std']:.2e}); roughness det Ḡ / |u| = "
               f"{numbers['roughness_ratio_detGbar_over_u']:.1f}")
    info(comm, f"wrote {folder / 'summary.json'}, " + ", ".join(map(str, paths)))
    return cli.EXIT_OK


main = cli.entry(parser, ensemble)

if __name__ == "__main__":
    sys.exit(main())
