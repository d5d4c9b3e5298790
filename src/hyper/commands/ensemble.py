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

import sys
import time
from pathlib import Path

from mpi4py import MPI

from hyper.analysis.ensemble import Sample, run_sample, write_results
from hyper.commands import cli
from hyper.core.log import hms, info
from hyper.core.params import SEED_MAX, InputError, build
from hyper.fem.coupled import GrowthSettings
from hyper.model import heterogeneity, protocols
from hyper.runs import driver, farm, locks, runspec

# one coupled run each: beyond this an ensemble is a typing mistake, and its job list would not fit in memory
MAX_SAMPLES = 100_000


def parser() -> cli.Parser:
    p = cli.Parser("ensemble", __doc__)
    p.add_argument("--geometry", default="BFLH_VHF_Left", help="geometry id (idealized, BFLH_VHF_Left, …)")
    p.add_argument("--protocol", default="mwf", metavar="NAME|FILE",
                   help=f"a named protocol ({', '.join(protocols.NAMES)}) or a TOML protocol file")
    p.add_argument("--samples", type=cli.integer(1, MAX_SAMPLES), default=5,
                   help="heterogeneous samples besides the uniform case")
    p.add_argument("--first-seed", type=cli.seed(), default=1,
                   help="seed of the first sample (then +1 each)")
    p.add_argument("--epsilon", type=cli.number(), default=0.01, help="relative half-width ε of the perturbation")
    p.add_argument("--model", choices=heterogeneity.MODELS, default="uniform-noise", help="heterogeneity model")
    p.add_argument("--length", type=cli.number(), default=heterogeneity.Heterogeneity.length,
                   help="Matérn correlation range ℓ (m; matern only)")
    p.add_argument("--nu", type=cli.number(), default=heterogeneity.Heterogeneity.nu,
                   help="Matérn smoothness ν (matern only)")
    p.add_argument("--growth-dt", type=cli.positive("hours"), default=GrowthSettings.growth_dt,
                   help="growth step Δtg (h)")
    p.add_argument("--signaling-dt", type=cli.positive("hours"), default=GrowthSettings.signaling_dt,
                   help="RK4 step (h)")
    p.add_argument("--ranks-per-job", type=cli.integer(1), default=1, help="MPI ranks per coupled run")
    p.add_argument("--snapshot-every", type=cli.positive("hours"), default=driver.SNAPSHOT_EVERY, metavar="HOURS",
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

    # the seeds first_seed, first_seed + 1, …: the last one too must be a seed (params.SEED_MAX)
    if args.first_seed + args.samples - 1 > SEED_MAX:
        raise InputError(f"--first-seed {args.first_seed} with --samples {args.samples}: the last seed would be "
                         f"{args.first_seed + args.samples - 1}, past {SEED_MAX}")
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
            with locks.hold(sub, [job.payload.outputs.h5]):  # the run's own lock, as `hyper grow` takes it
                return run_sample(sub, job.payload, snapshot_every=args.snapshot_every, stop=stop,
                                  progress_every=args.progress_every)
        except driver.Interrupted:
            return {"interrupted": True}

    with locks.hold(comm, [folder]), driver.StopOnTerm(comm) as stop:
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
    title = f"{args.geometry}, {protocol}, {het.label()}"
    numbers, paths = write_results(jobs, het, results, folder, title)
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
