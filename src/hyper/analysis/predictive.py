"""The posterior predictive on a real muscle: K posterior samples of kM through the coupled model.

K of the kM samples of a posterior (the posterior.h5 of ``hyper calibrate --method bayes``),
drawn at random without replacement with a seed (the samples are independent draws, so any K
of them are a sample of the posterior; `draw`), each one coupled run on an anatomical mesh, a
job of `hyper.runs.farm` (as the cohort's: checkpoints, a rerun skips the runs whose results
match their digest). Reported: the 9-week CSA and volume gains, median and the 95 %
credible interval (percentiles of the K runs), and the ODE growth model's (`hyper.model.surrogate`,
the model the posterior was sampled on, with the section factor of the posterior's geometry)
gains for the same samples with its error against the coupled runs. The job is
`hyper.commands.predict`.

Under OUTPUT: runs/sampleNN.h5 (each coupled run), predictive.h5 (per sample kM, gains of both
models, the posterior's SHA-256, the summary as a group), predictive.json and predictive.png
(the K CSA curves of both models and the coupled band).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import textwrap
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)
import numpy as np

from hyper.analysis import cohort
from hyper.core import io
from hyper.core.collective import on_rank0
from hyper.core.params import InputError
from hyper.fem.coupled import GrowthSettings
from hyper.model import protocols, signaling, surrogate
from hyper.model.protocols import Protocol
from hyper.runs import checkpoint as ckpt
from hyper.runs import driver, farm, locks, plot, runspec

LEVEL = 0.95
DEFAULT_SAMPLES = 8


@dataclasses.dataclass(frozen=True)
class Source:
    """The kM samples of a posterior file and how it was fitted."""

    path: Path
    kM: np.ndarray
    sha256: str
    geometry: str  # of the fit: whose section factor the ODE growth model took
    feedback: str
    signaling_dt: float


def read_posterior(path: Path) -> Source:
    """The kM samples and attributes of a posterior.h5; InputError for a missing or unfit file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"--posterior {path}: no such file")
    with io.reading_h5(path, "posterior file") as f:
        if "kM" not in f:
            raise InputError(f"--posterior {path}: no kM samples (datasets: {', '.join(sorted(f)) or 'none'}); "
                             "give the posterior.h5 of hyper calibrate --method bayes --fit kM")
        kM = np.asarray(f["kM"][()], dtype=float)
        attrs = {k: (v.item() if hasattr(v, "item") else v) for k, v in f.attrs.items()}
    if kM.ndim != 1 or not kM.size or not np.all(np.isfinite(kM) & (kM > 0)):
        raise InputError(f"--posterior {path}: kM samples must be a non-empty list of finite numbers > 0")
    return Source(path, kM, ckpt.file_digest(path), str(attrs.get("geometry", "idealized")),
                  str(attrs.get("feedback", "hill")), float(attrs.get("signaling_dt", GrowthSettings.signaling_dt)))


def draw(kM: np.ndarray, k: int, seed: int) -> np.ndarray:
    """``k`` of the samples, at random without replacement (seeded), in increasing kM."""
    if k < 2:
        raise InputError(f"--samples {k}: a credible interval needs at least 2 samples")
    if k > kM.size:
        raise InputError(f"--samples {k}: the posterior holds only {kM.size} samples")
    return np.sort(kM[np.random.default_rng(seed).choice(kM.size, size=k, replace=False)])


def specs(source: Source, kM: np.ndarray, geometry: str, protocol: Protocol) -> list[runspec.RunSpec]:
    """One coupled run per kM, with the fit's RK4 step and feedback."""
    settings = GrowthSettings(signaling_dt=source.signaling_dt, feedback=source.feedback)
    base = signaling.SignalingParams()
    return [runspec.RunSpec(geometry, protocol, dataclasses.replace(base, kM=float(k)), settings) for k in kM]


def key(j: int) -> str:
    return f"sample{j:02d}"


def result_path(output: Path, j: int) -> Path:
    return Path(output) / "runs" / f"{key(j)}.h5"


def run_samples(comm, runs: list[runspec.RunSpec], output: Path, *, ranks_per_job: int = 1, stop=None,
                progress_every: float = math.inf) -> list[farm.JobResult]:
    """Every run not done before, on the farm; collective over ``comm``. Each run's own
    progress goes to runs/sampleNN.log, the farm's to the terminal (rank 0)."""
    output = Path(output)
    digests = [s.digest() for s in runs]
    cells = cohort.mesh_cells(runs[0].geometry)
    jobs = [farm.Job(key(j), cost=float(cells * cohort.growth_steps(s.protocol, s.settings.growth_dt)), payload=j)
            for j, s in enumerate(runs)]
    if comm.rank == 0:
        (output / "runs").mkdir(parents=True, exist_ok=True)

    def is_done(job):
        return runspec.Outputs(result_path(output, job.payload)).is_current(digests[job.payload])

    def work(subcomm, job):
        j = job.payload
        out = runspec.Outputs(result_path(output, j))
        with locks.hold(subcomm, [out.h5]):
            on_rank0(subcomm, lambda: cohort.drop_stale_checkpoint(out.checkpoint, digests[j]))
            log = cohort.RunLog(out.h5.with_suffix(".log")) if subcomm.rank == 0 else contextlib.nullcontext()
            try:
                with log:
                    done = driver.execute(subcomm, runs[j], out, stop=stop, progress_every=progress_every)
            except driver.Interrupted:
                return {"interrupted": True} if subcomm.rank == 0 else None
            if subcomm.rank != 0:
                return None
            out.store(done.series, {**done.meta, "protocol": runs[j].protocol.name},
                      runspec.result_groups(runs[j], done.choice))
            return {"csa_ratio": float(done.series["csa_ratio"][-1])}

    return farm.run(comm, jobs, work, ranks_per_job=ranks_per_job, is_done=is_done, label="predictive",
                    progress_every=progress_every)


def _band(values: np.ndarray, axis=0):
    return np.percentile(values, [50, 50 * (1 - LEVEL), 50 * (1 + LEVEL)], axis=axis)


def summarise(source: Source, kM: np.ndarray, output: Path, geometry: str, protocol: Protocol) -> dict:
    """Read the K coupled runs, evaluate the ODE growth model on the same samples at the runs'
    times, and write predictive.h5, predictive.json and predictive.png (one rank)."""
    series = [io.read_series(result_path(output, j)) for j in range(len(kM))]
    t = series[0]["t"]
    csa = np.array([s["csa_ratio"] for s in series])
    volume = np.array([s["volume_ratio"] for s in series])
    factor = surrogate.SECTION_FACTOR.get(source.geometry, 1.0)
    fast = surrogate.grow(signaling.SignalingParams(kM=kM), protocol, t, signaling_dt=source.signaling_dt,
                          feedback=source.feedback, factor=factor)
    fast_csa, fast_volume = fast.csa_ratio.T, fast.N.T  # (K, times)
    gains = {"csa_gain_pct": 100 * (csa[:, -1] - 1), "volume_gain_pct": 100 * (volume[:, -1] - 1),
             "surrogate_csa_gain_pct": 100 * (fast_csa[:, -1] - 1),
             "surrogate_volume_gain_pct": 100 * (fast_volume[:, -1] - 1)}

    def interval(values):
        m, lo, hi = _band(values)
        return {"median": float(m), "low": float(lo), "high": float(hi), "level": LEVEL}

    error = {}
    for measure in ("csa", "volume"):
        diff = np.abs(gains[f"surrogate_{measure}_gain_pct"] - gains[f"{measure}_gain_pct"])
        error[measure] = {"mean_abs_pp": float(diff.mean()), "max_abs_pp": float(diff.max())}
    wall = []
    for j in range(len(kM)):
        with io.reading_h5(result_path(output, j)) as f:
            wall.append(float(f.attrs.get("wall_s", math.nan)))
    summary = {
        "posterior": {"file": str(source.path), "sha256": source.sha256, "samples": int(source.kM.size),
                      "fit_geometry": source.geometry, "feedback": source.feedback,
                      "signaling_dt": source.signaling_dt},
        "draw": "random without replacement, seeded; sorted by kM",
        "geometry": geometry, "protocol": protocol.name, "weeks": protocol.end / protocols.WEEK,
        "kM": kM.tolist(),
        "coupled": {"csa_gain_pct": interval(gains["csa_gain_pct"]),
                    "volume_gain_pct": interval(gains["volume_gain_pct"])},
        "surrogate": {"csa_gain_pct": interval(gains["surrogate_csa_gain_pct"]),
                      "volume_gain_pct": interval(gains["surrogate_volume_gain_pct"]),
                      "section_factor": factor},
        "surrogate_error": error,
        "per_sample": {name: values.tolist() for name, values in gains.items()},
        "coupled_wall_s": wall, "runs": [str(result_path(output, j)) for j in range(len(kM))],
        "versions": io.versions(),
    }
    units = {"kM": io.unit("kM"), **{name: "%" for name in gains}}
    io.write_series(Path(output) / "predictive.h5", {"kM": kM, **gains}, units=units,
                    attrs={"posterior_file": str(source.path), "posterior_sha256": source.sha256,
                           "geometry": geometry, "protocol": protocol.name, "level": LEVEL,
                           "section_factor": factor},
                    groups={"summary": {f"{model}_{name}_{q}": v for model in ("coupled", "surrogate")
                                        for name in ("csa_gain_pct", "volume_gain_pct")
                                        for q, v in summary[model][name].items() if q != "level"}
                            | {f"surrogate_error_{m}_{q}": v for m, e in error.items() for q, v in e.items()}})
    io.write_json(Path(output) / "predictive.json", summary)
    figure(Path(output) / "predictive.png", t, csa, fast_csa, kM, summary)
    return summary


def figure(path: Path, t: np.ndarray, csa: np.ndarray, fast: np.ndarray, kM: np.ndarray, summary: dict) -> Path:
    """The K CSA curves of the coupled runs (with their band) and of the ODE growth model."""
    plt = plot.pyplot()
    fig, ax = plt.subplots(figsize=(6, 4), constrained_layout=True)
    weeks = t / protocols.WEEK
    _, lo, hi = _band(100 * (csa - 1))
    ax.fill_between(weeks, lo, hi, color="C0", alpha=0.2, lw=0, label=f"coupled, {LEVEL:.0%} band of the runs")
    for j in range(len(kM)):
        ax.plot(weeks, 100 * (csa[j] - 1), color="C0", lw=1, label="coupled runs" if j == 0 else None)
        ax.plot(weeks, 100 * (fast[j] - 1), color="C1", lw=1, ls="--", label="ODE growth model" if j == 0 else None)
    c, e = summary["coupled"]["csa_gain_pct"], summary["surrogate_error"]["csa"]
    ax.set_title("\n".join(textwrap.wrap(
        f"{summary['geometry']}, {summary['protocol']}, {len(kM)} posterior samples of kM: CSA gain "
        f"{c['median']:.2f} [{c['low']:.2f}, {c['high']:.2f}] % ({LEVEL:.0%}); ODE growth model's error "
        f"{e['max_abs_pp']:.2g} pp (max)", 90)), fontsize=8)
    ax.set_xlabel("time (weeks)")
    ax.set_ylabel("CSA change (%)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    return plot.save(fig, path)
