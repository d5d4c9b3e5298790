"""python -m hyper.cohort: the anatomical cohort of the paper's Fig. 6 on an MPI job farm.

    mpirun -n 2 python -m hyper.cohort                      # 12 meshes × mwf, every3days, weekly
    mpirun -n 4 python -m hyper.cohort --ranks-per-job 2    # 2 groups of 2 ranks
    python -m hyper.cohort --geometries BFLH_VHF_Left --protocols mwf my_protocol.toml
    python -m hyper.cohort --geometries TA_VHF_Left TA_VHF_Right --fibers dti/{geometry}.nii.gz

Every (geometry, protocol) pair is one job of `hyper.runs.farm` (longest first, by the
estimate mesh cells × growth steps), run by `hyper.runs.driver.execute` on its group's
communicator. Per run, under OUTPUT/runs/:

    GEOMETRY_PROTOCOL.h5            the time series (as hyper.grow writes it) with the
                                    attributes geometry, muscle, subject, side, protocol,
                                    csa0_m2, volume0_m3, wall_s, ranks, run_digest and
                                    the groups signaling, material as mat, protocol, settings
                                    and the equivalent study file (hyper.runs.provenance)
    GEOMETRY_PROTOCOL_fields.xdmf   snapshots of u, det Ḡ and a0 every --snapshot-every
                                    simulated hours (ParaView, meshio's TimeSeriesReader)
    GEOMETRY_PROTOCOL.log           the run's own progress lines

and for the cohort, written by rank 0 from the complete .h5 files (so a rerun that had
nothing left to do writes the same summary):

    summary.csv     geometry,muscle,subject,side,protocol,csa0_cm2,volume0_cm3,
                    final_csa_ratio,final_csa_ratio_cut,final_csa_ratio_box,
                    final_csa_ratio_solid,final_volume_ratio,wall_s,data_rmse_pp,
                    data_last_difference_pp,
                    status (final_csa_ratio is the one --csa-method feeds back; cut,
                    box and solid are blank on meshes with a tagged mid-section; data_*:
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

import sys
import time
import traceback
from pathlib import Path

from hyper.analysis import cohortsummary
from hyper.analysis.cohort import PAPER_PROTOCOLS, Run, idle_barrier, plan, run_cohort
from hyper.analysis.cohortplot import SHAPE_GEOMETRY
from hyper.commands import cli, grow
from hyper.core.log import info
from hyper.core.params import InputError
from hyper.fem import geometry as geo
from hyper.fem.coupled import GrowthSettings
from hyper.model import material as mat
from hyper.model import protocols
from hyper.runs import driver, locks, measured, presets, runspec


def parser() -> cli.Parser:
    p = cli.Parser("cohort", __doc__)
    p.add_argument("--geometries", nargs="+", metavar="ID", default=list(geo.ANATOMICAL),
                   help="geometry ids (the 12 anatomical meshes by default; idealized and cylinder work too), "
                        f"or a set: {', '.join(f'{k} ({len(v)})' for k, v in geo.SETS.items())}")
    p.add_argument("--protocols", nargs="+", metavar="NAME|FILE", reads=True, default=list(PAPER_PROTOCOLS),
                   help=f"named protocols ({', '.join(protocols.NAMES)}) or TOML protocol files")
    p.add_argument("--output", type=cli.output(folder=True), default="results/cohort", help="output folder")
    p.add_argument("--ranks-per-job", type=cli.integer(1), default=1,
                   help="MPI ranks per run; must divide the number of ranks")
    p.add_argument("--growth-dt", type=cli.positive("hours"),
                   help=f"growth step Δtg (h); {GrowthSettings.growth_dt:g} unless --settings sets it")
    cli.refine_option(p)
    p.add_argument("--material", type=Path, metavar="F.toml", reads=True,
                   help="TOML file overriding the muscle law's parameters (hyper.model.material.MaterialParams)")
    presets.add_options(p, several=True)
    cli.fibre_data_options(p)
    grow.model_options(p)
    p.add_argument("--max-halvings", type=cli.integer(0, GrowthSettings.MAX_HALVINGS),
                   default=GrowthSettings.max_halvings,
                   help="cuts of a growth step whose Newton solve fails before the run fails; a failed run "
                        "resumes from its checkpoint with a larger value")
    p.add_argument("--snapshot-every", type=cli.positive("hours"), default=driver.SNAPSHOT_EVERY, metavar="HOURS",
                   help="fields snapshot every HOURS of simulated time, besides the first and the last state")
    p.add_argument("--data", type=Path, metavar="CSV", reads=True,
                   help="measured CSA to compare every run with (as hyper grow --data); by default each "
                        "protocol's own data set, if it has one (mwf: DeFreitas)")
    cli.progress_option(p)
    p.add_argument("--plot-geometry", metavar="ID",
                   help=f"geometry of the shape plot (the paper's Fig. 6A), one of --geometries; {SHAPE_GEOMETRY} "
                        "when it is one of them, else the first")
    return p


def check(args, comm) -> tuple[list[Run], GrowthSettings, mat.MaterialParams]:
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
    if (presets.is_data(args.fibers, presets.FIBER_CHOICES) and len(args.geometries) > 1
            and presets.GEOMETRY_FIELD not in args.fibers):
        raise InputError(f"--fibers {args.fibers}: a fibre data file belongs to one geometry; with several, name "
                         f"one file per geometry with {presets.GEOMETRY_FIELD} in its path (e.g. "
                         f"dti/{presets.GEOMETRY_FIELD}.nii.gz)")
    fibres = {name: presets.data_source(args, geometry=name) for name in args.geometries}
    chosen = {"growth_dt": args.growth_dt, "max_halvings": args.max_halvings, **presets.chosen(args)}
    settings = presets.settings(GrowthSettings, args.settings, chosen,
                                {"growth_dt": "--growth-dt", "max_halvings": "--max-halvings"})
    runs = plan(args.geometries, [p for text in args.protocols for p in protocols.from_option(text, "--protocols")],
                fibres={name: source for name, source in fibres.items() if source is not None})
    if args.data is not None:
        data = measured.read(args.data)
        measured.check_section(data, settings.sections)
        for r in runs:
            measured.check_span(data, r.protocol)
    return runs, settings, mat.load(args.material) if args.material else mat.MaterialParams()


def exit_code(outcome: cohortsummary.Outcome) -> int:
    """143 when SIGTERM stopped some runs, else 1 when some failed, else 0."""
    return cli.EXIT_TERMINATED if outcome.interrupted else cli.EXIT_SOME_FAILED if outcome.failed else cli.EXIT_OK


def cohort(comm, args) -> int:
    start = time.perf_counter()
    runs, settings, muscle = check(args, comm)
    with locks.hold(comm, [args.output]):
        info(comm, f"cohort: {len(runs)} runs ({len(args.geometries)} geometries × {len(args.protocols)} "
                   f"protocols) on {comm.size} rank(s) in groups of {args.ranks_per_job}, growth step "
                   f"{settings.growth_dt:g} h, output {args.output}")
        with driver.StopOnTerm(comm) as stop:
            results = run_cohort(comm, runs, args.output, settings=settings, snapshot_every=args.snapshot_every,
                                 ranks_per_job=args.ranks_per_job, stop=stop, progress_every=args.progress_every,
                                 data=None if args.data is None else measured.read(args.data),
                                 options={**args.shape, "material": muscle, "refine": args.refine})
        code = 0
        if comm.rank == 0:
            try:
                code = exit_code(cohortsummary.finish(args.output, runs, results, settings,
                                                      time.perf_counter() - start, plot_geometry=args.plot_geometry))
            except Exception:  # noqa: BLE001 - the other ranks wait below: report, never leave them hanging
                traceback.print_exc()
                code = cli.EXIT_SOME_FAILED
        idle_barrier(comm)
    return int(comm.bcast(code, root=0))


main = cli.entry(parser, cohort)

if __name__ == "__main__":
    sys.exit(main())
