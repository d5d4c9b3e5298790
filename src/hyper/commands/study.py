"""hyper study STUDY.toml: a whole study in one file.

    hyper study studies/custom.toml
    mpirun -n 4 hyper study studies/paper-cohort.toml --ranks-per-job 2
    hyper study studies/paper-cohort.toml --growth-dt 24 --output results/coarse

One geometry × one protocol runs as `hyper grow` does (OUTPUT/GEOMETRY_PROTOCOL.h5, its
fields and OUTPUT/GEOMETRY_growth.png); more run as a cohort on the MPI farm as
`hyper cohort` does (OUTPUT/runs/, summary.csv, ratios.png, shape.png of the first
geometry, table.md), and a rerun skips the runs already done.

The file; every key is checked when it is read, an unknown one is an error, and paths
of inputs are relative to the study file's folder (the output folder to the current one):

    geometries = ["BFLH_VHF_Left", "cylinder"]  # built-in geometry ids
    protocols = ["mwf", "mine.toml"]            # built-in names, "all", or protocol TOML files

    [[mesh]]                   # a mesh file of yours (repeatable): tetrahedral XDMF with
    file = "muscle.xdmf"       # facet tags ft_small (1, 2 the ends, 3 the side)
    unit = "mm"                # its length unit: m or mm
    fibers = "muscle_dti.nii.gz"  # optional: fibres from data (docs/fibres-from-data.md; also
                               # fibers_unit, fibers_min_fa, fibers_radius_mm, fibers_fa)

    [[protocol]]               # a protocol written here (repeatable), as in a protocol file:
    name = "twice-weekly"      # [[protocol.session]] tables (start, duration, intensity, stretch) and
    [protocol.repeat]          # end (h), or a repeat rule:
    weekdays = ["tue", "fri"]  # days of each training week (weeks begin on a Monday), or
                               # every_days = 3
    duration = 1.0             # h, each session
    intensity = 0.8            # fraction of the maximal force
    weeks = 6                  # training weeks; the protocol ends with the last
    lead_in_days = 7           # rest before the first training week (0 by default)

    [signaling]                # signaling parameters (fields of hyper.model.signaling.SignalingParams)
    a10 = 0.09

    [material]                 # the muscle law's parameters (fields of hyper.model.material.MaterialParams)
    sigma_act = 2.5e5          # Pa

    [heterogeneity]            # per-cell signaling parameters (hyper.model.heterogeneity), optional
    model = "uniform-noise"    # or "matern", with length (m) and nu
    epsilon = 0.01
    seed = 1

    [numerics]
    growth_dt = 168.0          # h; or accuracy = 1e-3: the steps and refine hyper.runs.fidelity choose
    signaling_dt = 0.05        # h, the RK4 step
    quadrature_degree = 4      # built-in geometries only
    refine = 0                 # uniform refinements of every mesh (0 to 3; --refine; with accuracy, the least)
    linear_solver = "lu"       # lu, iterative or auto (lu; auto with accuracy)
    max_halvings = 4
    feedback = "hill"          # of CSA on protein synthesis: hill, linear or none
    grow_during_sessions = true   # false: the original code's
    consistent_stress = true      # false: the original code's P = Fe S
    sections = 9               # regional CSA at j/10 of the length (0: none; hyper grow --sections)
    detraining = 500.0         # h, the gain's turnover (left out: none, the paper's model)
    fiber_growth = "stretch"   # along-fibre growth in sessions with a stretch (none: the paper's)
    fiber_tau = 168.0          # h, its time constant τ_f (illustrative, not calibrated)
    fiber_crit = 1.0           # its homeostatic elastic fibre stretch λ_crit

    [output]
    folder = "results/study"   # (the default)
    figures = true
    snapshot_every = 24.0      # h of simulated time between fields snapshots (and the last state)

    [data]                     # measured CSA to compare every run with (hyper.runs.measured), optional;
    file = "mine.csv"          # without it a run is compared with its protocol's own data set, if any

    [sobol]                    # the sensitivity analysis of `hyper sobol --problem STUDY.toml`
    names = ["kM", "kF"]       # (checked here, run there; see hyper.sobol)
    bounds = [[0.005, 0.02], [0.0095, 0.038]]

Precedence: a command-line option wins over the study file, and the file over the
defaults (--output over [output] folder, --growth-dt over [numerics] growth_dt, and so on
for each key). Wherever they come from, a growth or RK4 step given explicitly wins over
the one that accuracy would choose, as in `hyper grow`.

Exit status: as `hyper grow` (one run) or `hyper cohort` (more); 2 for a bad study
file or option, with nothing written.
"""

from __future__ import annotations

import argparse
import time
import traceback
from pathlib import Path

from hyper.analysis import cohortsummary
from hyper.analysis.cohort import idle_barrier
from hyper.analysis.study import Study, check_inputs, cohort_runs, load, one_plan, run_many, steps
from hyper.commands import cli, grow
from hyper.commands.cohort import exit_code
from hyper.core.log import PROGRESS_EVERY, info
from hyper.core.params import InputError
from hyper.fem.coupled import GrowthSettings
from hyper.runs import driver, locks, runspec, sequence


def parser() -> cli.Parser:
    p = cli.Parser("study", __doc__)
    p.add_argument("study", type=Path, metavar="STUDY.toml", reads=True, help="the study file")
    p.add_argument("--output", type=cli.output(folder=True), help="output folder; overrides [output] folder")
    p.add_argument("--figures", action=argparse.BooleanOptionalAction,
                   help="write the figures (--no-figures: none); overrides [output] figures")
    p.add_argument("--growth-dt", type=cli.positive("hours"), help="growth step (h); overrides [numerics] growth_dt")
    p.add_argument("--accuracy", type=cli.number(),
                   help="fidelity choice of the steps and of the meshes' refinement (their spatial error counted); "
                   "overrides [numerics] accuracy")
    p.add_argument("--signaling-dt", type=cli.positive("hours"), help="RK4 step (h); overrides [numerics] signaling_dt")
    p.add_argument("--quadrature-degree", type=cli.integer(1, 12), help="overrides [numerics] quadrature_degree")
    cli.refine_option(p, default=None)
    p.add_argument("--linear-solver", choices=runspec.LINEAR_SOLVERS, help="overrides [numerics] linear_solver")
    p.add_argument("--max-halvings", type=cli.integer(0, GrowthSettings.MAX_HALVINGS),
                   help="overrides [numerics] max_halvings")
    p.add_argument("--snapshot-every", type=cli.positive("hours"), metavar="HOURS",
                   help="fields snapshot every HOURS of simulated time; overrides [output] snapshot_every")
    p.add_argument("--data", type=Path, metavar="CSV", reads=True,
                   help="measured CSA to compare with; overrides [data] file")
    grow.model_options(p)  # override [numerics] sections and detraining
    p.add_argument("--ranks-per-job", type=cli.integer(1), default=1,
                   help="MPI ranks per run of a cohort; must divide the number of ranks")
    cli.progress_option(p)
    return p


OVERRIDES = {"output": "folder", "figures": "figures", "growth_dt": "growth_dt", "accuracy": "accuracy",
             "signaling_dt": "signaling_dt", "quadrature_degree": "quadrature_degree", "refine": "refine",
             "linear_solver": "linear_solver", "max_halvings": "max_halvings", "snapshot_every": "snapshot_every",
             "sections": "sections", "detraining": "detraining", "fiber_growth": "fiber_growth",
             "stimulus": "stimulus"}


def from_args(args) -> Study:
    overrides = {field: ("--" + option.replace("_", "-"), getattr(args, option))
                 for option, field in OVERRIDES.items() if getattr(args, option) is not None}
    return load(args.study, overrides, args.data)


def one_run(comm, study: Study, settings, choice, stop, progress_every: float = PROGRESS_EVERY) -> int:
    """One geometry × one protocol: `hyper grow`'s plan and its execution."""
    work = one_plan(comm, study, settings, choice, progress_every)
    return grow.exit_status(comm, sequence.carry_out(comm, work, stop, figure=study.output.figures))


def many_runs(comm, study: Study, settings, choice, stop, ranks_per_job: int,
              progress_every: float = PROGRESS_EVERY) -> int:
    """More runs: `hyper cohort`'s farm and its summary."""
    start = time.perf_counter()
    if comm.size % ranks_per_job:
        raise InputError(f"--ranks-per-job must divide the number of MPI ranks ({comm.size}), got {ranks_per_job}")
    folder = study.output.folder
    runs = cohort_runs(study)
    with locks.hold(comm, [folder]):
        info(comm, f"study: {len(runs)} runs ({len(study.names)} geometries × {len(study.protocols)} protocols) "
                   f"on {comm.size} rank(s) in groups of {ranks_per_job}, growth step {settings.growth_dt:g} h, "
                   f"output {folder}")
        results = run_many(comm, study, runs, settings, choice, stop, ranks_per_job, progress_every)
        code = 0
        if comm.rank == 0:
            try:
                code = exit_code(cohortsummary.finish(folder, runs, results, settings, time.perf_counter() - start,
                                                      plot_geometry=study.names[0], figures=study.output.figures))
            except Exception:  # noqa: BLE001 - the other ranks wait for the code: report, never leave them hanging
                traceback.print_exc()
                code = cli.EXIT_SOME_FAILED
        idle_barrier(comm)
    return int(comm.bcast(code, root=0))


def carry_out(comm, args) -> int:
    study = from_args(args)
    settings, choice = steps(study)
    check_inputs(comm, study)
    with driver.StopOnTerm(comm) as stop:
        if len(study.names) * len(study.protocols) == 1:
            return one_run(comm, study, settings, choice, stop, args.progress_every)
        return many_runs(comm, study, settings, choice, stop, args.ranks_per_job, args.progress_every)


main = cli.entry(parser, carry_out)
