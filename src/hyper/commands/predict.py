"""The posterior predictive on a real muscle: posterior samples of kM through the coupled model.

    hyper calibrate --data data/defreitas.csv --protocol mwf --fit kM --method bayes --no-check \\
        --output results/calibration/bayes_defreitas
    mpirun -n 2 hyper predict --posterior results/calibration/bayes_defreitas/posterior.h5 \\
        --geometry TA_VHF_Left --samples 8 --output results/predictive

--samples K of the posterior's kM samples (drawn at random without replacement with --seed,
then sorted by kM) each make one coupled run of --protocol on --geometry, with the RK4 step
and feedback the posterior was fitted with, as jobs of the cohort's farm (`hyper.runs.farm`:
--ranks-per-job ranks a run, checkpoints, and a rerun skips the runs already done). Reported:
the CSA and volume gains at the protocol's end, median and 95 % credible interval (the
percentiles of the K runs), the ODE growth model's gains for the same samples (the model the
posterior was sampled on, `hyper.model.surrogate`) and its error against the coupled runs
(mean and max |difference|, percentage points).

Writes OUTPUT/runs/sampleNN.h5 (each run, its progress in sampleNN.log), OUTPUT/predictive.h5
(per sample kM and the gains of both models; the posterior's SHA-256), OUTPUT/predictive.json
(the summary) and OUTPUT/predictive.png (the CSA curves of both models and the band).
Exit status 1 when a run failed, 143 when SIGTERM stopped the runs (run it again to go on).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from hyper.analysis import predictive
from hyper.analysis.cohort import idle_barrier
from hyper.commands import cli
from hyper.core.log import info
from hyper.core.params import InputError
from hyper.model import protocols
from hyper.runs import driver, farm, runspec


def parser() -> cli.Parser:
    p = cli.Parser("predict", __doc__)
    p.add_argument("--posterior", type=Path, required=True, reads=True, metavar="H5",
                   help="posterior.h5 of hyper calibrate --method bayes --fit kM")
    p.add_argument("--geometry", default="TA_VHF_Left",
                   help="the muscle: a built-in geometry id (an anatomical mesh, or cylinder or idealized)")
    p.add_argument("--protocol", default="mwf", metavar="NAME|FILE", reads=True,
                   help="the protocol (a name or a .toml)")
    p.add_argument("--samples", type=cli.integer(2, 1000), default=predictive.DEFAULT_SAMPLES,
                   help="K: posterior samples run")
    p.add_argument("--seed", type=cli.seed(), default=0, help="seed of the samples drawn")
    p.add_argument("--ranks-per-job", type=cli.integer(1), default=1,
                   help="MPI ranks per run; must divide the number of ranks")
    p.add_argument("--output", type=cli.output(folder=True), default="results/predictive", help="output folder")
    cli.progress_option(p)
    return p


def run(comm, args) -> int:
    start = time.perf_counter()
    if comm.size % args.ranks_per_job:
        raise InputError(f"--ranks-per-job must divide the number of MPI ranks ({comm.size}), got {args.ranks_per_job}")
    runspec.check_geometry(comm, args.geometry)
    protocol = protocols.resolve(args.protocol)
    source = predictive.read_posterior(args.posterior)
    kM = predictive.draw(source.kM, args.samples, args.seed)
    runs = predictive.specs(source, kM, args.geometry, protocol)
    info(comm, f"predict: {len(kM)} of {source.kM.size} posterior samples, kM {kM[0]:.5g} … {kM[-1]:.5g} 1/h, "
               f"{args.geometry}/{protocol.name} on {comm.size} rank(s) in groups of {args.ranks_per_job}")
    with driver.StopOnTerm(comm) as stop:
        results = predictive.run_samples(comm, runs, args.output, ranks_per_job=args.ranks_per_job, stop=stop,
                                         progress_every=args.progress_every)
    info(comm, f"predict: {farm.summary_line(results)}")
    if any(r.status == "done" and r.result.get("interrupted") for r in results):
        return cli.EXIT_TERMINATED
    if any(r.status == "failed" for r in results):
        return cli.EXIT_SOME_FAILED
    if comm.rank == 0:
        s = predictive.summarise(source, kM, args.output, args.geometry, protocol)
        for name, label in (("csa_gain_pct", "CSA gain"), ("volume_gain_pct", "volume gain")):
            c, f = s["coupled"][name], s["surrogate"][name]
            e = s["surrogate_error"][name.split("_")[0]]
            info(comm, f"predict: {label} {c['median']:.3f} % [{c['low']:.3f}, {c['high']:.3f}] ({c['level']:.0%}), "
                       f"ODE growth model {f['median']:.3f} % [{f['low']:.3f}, {f['high']:.3f}], its error "
                       f"mean {e['mean_abs_pp']:.3g} pp, max {e['max_abs_pp']:.3g} pp")
        info(comm, f"predict: wrote {args.output / 'predictive.h5'}, predictive.json and predictive.png "
                   f"in {time.perf_counter() - start:.0f} s")
    idle_barrier(comm)
    return cli.EXIT_OK


main = cli.entry(parser, run, locks=lambda args: [args.output])

if __name__ == "__main__":
    sys.exit(main())
