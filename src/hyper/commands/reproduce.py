"""hyper reproduce: the paper's claims and the original code's numbers beside hyper's, switch by switch.

    mpirun -n 2 python -m hyper.reproduce --quick        # 28 runs, about 5 min on 2 cores
    mpirun -n 2 python -m hyper.reproduce                # full: 12 muscles at Δtg = 1 h, heterogeneity
    python -m hyper.reproduce --cases signaling          # one family of cases (no mesh)

For each claim of the paper (MODEL.md §8) and each number of the original code (§9) the
report has three columns: the paper's or the original's value, hyper with the original
code's switches (`--settings original`: every switch of §9; reproduce sets each explicitly too),
and hyper's default. An attribution table per headline number starts from the default
and turns on one switch at a time. Cases (families, --cases):

    signaling     ΔN at 9 weeks for mwf, every3days, weekly; IGF1 and AKT peak times (no mesh)
    idealized     the original's 15-day demo (7 one-hour sessions at 0.8 every 48 h from
                  t = 0, end 360 h) and the 9-week mwf run: CSA, V, kM; the switches alone
    contraction   the activation ramp to α = 1: end force and reaction_force_original
    cohort        the anatomical muscles under mwf: CSA by both measures and volume
    heterogeneity ε = 0.01 per-cell signaling on BFLH_VHF_Left, 5 samples (full mode only)

--quick: the cohort on BFLH_VHF_Left, ST_VHF_Left and TA_VHF_Left, the original column
there at one step per period (168 h) with the exact increment (the left-point rule needs
short steps); the idealized original column at the original's Δtg = 1 h as in full mode
(the 9-week run takes about a minute), the switches' attribution at one step per period
but the left-point rule's at 1 h; no heterogeneity. Full: the 12 muscles, Δtg = 1 h.
Every column and curve names its growth step.

Every coupled run is a job of `hyper.runs.farm` (longest first) and is stored under
OUTPUT/runs/KEY.h5; a rerun skips every run whose result exists with the same digest
(hyper.runs.driver's `RunSpec.digest`), so only the report is rebuilt. Writes OUTPUT/REPORT.md,
OUTPUT/report.json and the figures cohort_ratios.png (Fig. 6C–D analog, both CSA
measures side by side), box_section.png (the box measure's inner and rim facets on
BFLH_VHF_Left at the end of its original-settings run) and idealized_mwf.png.
"""

from __future__ import annotations

import sys
import time

from hyper.analysis.reproduce import CASES, QUICK_CASES, QUICK_MUSCLES, collect, is_done_on, plan, work_on
from hyper.analysis.reproducefigures import box_figure, cohort_figure, idealized_figure
from hyper.analysis.reproducereport import report
from hyper.commands import cli
from hyper.core import io
from hyper.core.log import info
from hyper.core.params import InputError
from hyper.fem import geometry as geo
from hyper.runs import driver, farm, locks, runspec


def parser() -> cli.Parser:
    p = cli.Parser("reproduce", __doc__)
    p.add_argument("--output", type=cli.output(folder=True), default="results/reproduce", help="output folder")
    p.add_argument(
        "--quick", action="store_true",
        help="3 muscles, coarser steps (the idealized original at its 1 h), no heterogeneity (about 5 min, 2 ranks)",
    )
    p.add_argument(
        "--cases",
        nargs="+",
        choices=CASES,
        metavar="CASE",
        help=f"families of cases ({', '.join(CASES)}); all of them (--quick: all but heterogeneity) by default",
    )
    p.add_argument(
        "--ranks-per-job", type=cli.integer(1), default=1, help="MPI ranks per run; must divide the number of ranks"
    )
    cli.progress_option(p)
    return p


def reproduce(comm, args) -> int:
    start = time.perf_counter()
    if args.cases is None:
        args.cases = list(QUICK_CASES if args.quick else CASES)
    if comm.size % args.ranks_per_job:
        raise InputError(f"--ranks-per-job must divide the number of MPI ranks ({comm.size}), got {args.ranks_per_job}")
    if "cohort" in args.cases or "heterogeneity" in args.cases:
        for g in QUICK_MUSCLES if args.quick else geo.ANATOMICAL:
            runspec.check_geometry(comm, g, "--cases cohort")
    jobs, runs = plan(args)
    output = args.output
    with locks.hold(comm, [output]):
        if comm.rank == 0:
            (output / "runs").mkdir(parents=True, exist_ok=True)
        info(
            comm,
            f"reproduce: {len(jobs)} jobs ({', '.join(args.cases)}), {'quick' if args.quick else 'full'} "
            f"mode, on {comm.size} rank(s), output {output}",
        )
        with driver.StopOnTerm(comm) as stop:
            results = farm.run(
                comm,
                jobs,
                work_on(output, runs, stop, args.progress_every),
                ranks_per_job=args.ranks_per_job,
                is_done=is_done_on(output, runs),
                label="reproduce",
                progress_every=args.progress_every,
            )
        stopped = comm.bcast(
            any(r.status == "done" and isinstance(r.result, dict) and r.result.get("interrupted") for r in results)
            if comm.rank == 0
            else None,
            root=0,
        )
        if stopped:
            info(comm, f"reproduce: stopped by SIGTERM; the finished runs are kept, the running ones have "
                       f"checkpoints: rerun the same command to go on (exit status {cli.EXIT_TERMINATED})")
            return cli.EXIT_TERMINATED
        if comm.rank == 0:
            data = collect(output, jobs, results, runs)
            command = (
                "hyper reproduce"
                + (" --quick" if args.quick else "")
                + (
                    ""
                    if args.cases == list(QUICK_CASES if args.quick else CASES)
                    else " --cases " + " ".join(args.cases)
                )
            )
            data.update(
                mode="quick" if args.quick else "full",
                cases=list(args.cases),
                command=command,
                wall_s=time.perf_counter() - start,
            )
            figures = [
                cohort_figure(data, output / "cohort_ratios.png"),
                box_figure(output, output / "box_section.png"),
                idealized_figure(output, output / "idealized_mwf.png", args.quick),
            ]
            text = report(data, args.quick, time.perf_counter() - start, command)
            shown = [f"![{p.stem}]({p.name})" for p in figures if p is not None]
            text += ("\n## Figures\n\n" + "\n\n".join(shown) + "\n") if shown else ""
            with io.atomic_path(output / "REPORT.md") as tmp:
                tmp.write_text(text)
            io.write_json(output / "report.json", data, indent=1)
            info(comm, text)
            info(comm, f"{farm.summary_line(results)}; wrote {output / 'REPORT.md'}, {output / 'report.json'}")
        failed = comm.bcast(any(r.status == "failed" for r in results), root=0)
    return cli.EXIT_SOME_FAILED if failed else cli.EXIT_OK


main = cli.entry(parser, reproduce)

if __name__ == "__main__":
    sys.exit(main())
