"""hyper grow: the coupled growth model on one geometry for one or more protocols.

    hyper grow --geometry idealized --protocol mwf --output results/grow/idealized_mwf.h5
    hyper grow --geometry idealized --protocol all --output results/grow
    hyper grow --mesh my_muscle.xdmf --mesh-unit mm --protocol my_protocol.toml --output results/mine
    hyper grow --geometry idealized --protocol mwf --accuracy 1e-3
    hyper grow --geometry TA_VHF_Right --fibers tests/data/synthetic_dti_TA_VHF_Right.nii.gz
    hyper grow --ask signaling --protocol mwf --accuracy 1e-3 --output results/signaling/mwf.h5

Writes per run an HDF5 time series (t, CSA and volume ratios, kM, the signaling states,
Newton iterations, step cuts) with its provenance as attributes, an XDMF file of
snapshots for ParaView (u, det Ḡ, fibres; every --snapshot-every simulated hours and the
last state, one temporal series that ParaView and meshio's TimeSeriesReader read whole)
and the paper's Fig. 4C–E analog (--plot). On a mesh without a tagged mid-section (the
anatomical ones) every CSA measure is recorded, csa_ratio_cut (the exact cut by the
vertices' plane), csa_ratio_box (the original code's box staircase, MODEL.md §9) and
csa_ratio_solid (the exact cut by the solid's plane of inertia, the same plane on any
mesh of the shape); csa_ratio is the one --csa-method feeds back. --plot-box draws the
box's inner and rim facets at the end of each run, with the exact cut. Against measured
CSA (--data, or the protocol's own data set where it was measured on a muscle the
geometry is compatible with: DeFreitas, the thigh, for mwf on idealized, cylinder or a
thigh muscle; `hyper.runs.measured`) the
run's RMSE in percentage points of CSA change and its difference at the last measured
time are printed, stored (the result's `data` group) and the data drawn on the figure,
whose title names the geometry, fibres, protocols and CSA measure.

--accuracy A (hyper.runs.fidelity): the cheapest model, the longest steps whose tabulated
error stays within A of the growth, and the linear solver that fits the memory; the
choice is printed and stored as the result's `fidelity` attributes. --ask signaling:
N alone, the signaling ODEs without a mesh or DOLFINx (exit status 3 if they fail).

Restart (hyper.runs.driver): a checkpoint RESULT.ckpt.h5 every --checkpoint-every growth steps
and after a SIGTERM; the same command resumes to the uninterrupted result. A step whose
Newton solve still fails after --max-halvings cuts stops the run (RESULT.status.json).

Exit status: 0 done; 2 bad input (nothing written); 3 a growth step failed for good;
4 another run holds the output; 143 stopped by SIGTERM (run the same command again).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hyper.commands import cli
from hyper.commands.signaling import answer, method_option
from hyper.core import io, log
from hyper.core.collective import on_rank0
from hyper.core.log import info
from hyper.core.params import InputError
from hyper.model import material as mat
from hyper.model import protocols, signaling
from hyper.runs import driver, fidelity, measured, presets, runspec, sequence

SIGNALING_SAMPLE_EVERY = 0.5  # h, the series of --ask signaling, as hyper signaling samples it
# the options that set GrowthSettings' fields, for errors that name what the user typed
SETTING_OPTIONS = {"growth_dt": "--growth-dt", "signaling_dt": "--signaling-dt", "feedback": "--feedback",
                   "max_halvings": "--max-halvings", "growth_fields": "--growth-fields",
                   "csa_method": "--csa-method"}


def scene_options(p: cli.Parser) -> None:
    """The options a signaling question shares with a growth run."""
    p.add_argument("--ask", choices=fidelity.ASKS, default="growth",
                   help="what the run answers: CSA and volume (the coupled model on a mesh) or N and the "
                        "signaling states (the ODEs alone, no mesh)")
    p.add_argument("--accuracy", type=cli.number(), nargs="?", const=fidelity.DEFAULT_ACCURACY, metavar="A",
                   help="the cheapest model and longest steps whose tabulated error stays within A, a fraction "
                        f"of the growth (or of N); A in (0, 0.5), {fidelity.DEFAULT_ACCURACY:g} when left out. "
                        "An explicit --growth-dt or --signaling-dt wins over it")
    p.add_argument("--protocol", default="mwf", metavar="NAME|FILE", reads=True,
                   help=f"a named protocol ({', '.join(protocols.NAMES)}), 'all' for "
                        f"{', '.join(protocols.PAPER)}, or a TOML protocol file")
    p.add_argument("--params", type=Path, reads=True, help="TOML file overriding signaling parameters")
    p.add_argument("--signaling-dt", type=cli.positive("hours"),
                   help=f"RK4 step (h); {fidelity.SIGNALING_DT0:g} unless --accuracy chooses one")
    method_option(p, default=None)


def model_options(p: cli.Parser) -> None:
    """--sections, --detraining, --fiber-growth and --stimulus, the switches beyond the paper (issue 35) that grow,
    cohort and study share; left out (None): the defaults."""
    from hyper.fem.section import MAX_SECTIONS, SECTIONS  # DOLFINx, as in parser()

    p.add_argument("--sections", type=cli.integer(0, MAX_SECTIONS), metavar="K",
                   help=f"record the CSA (exact cut) at K sections along the principal axis, at j/(K+1) of the "
                        f"length (csa_ratio_sections, time × section, at the result's section_fractions), beside "
                        f"the mid-belly series; 0: none. A measure only: the feedback sees the mid-belly CSA. "
                        f"{SECTIONS} (10 %%, 20 %%, …, 90 %%) by default")
    p.add_argument("--detraining", type=cli.positive("hours"), metavar="TAU",
                   help="turnover of the gain with time constant TAU hours, dN/dt = f − (N − 1)/TAU "
                        "(hyper.model.growth.detrained): the gain decays when training stops. Off by default "
                        "(the paper's model keeps every gain)")
    p.add_argument("--fiber-growth", choices=("none", "stretch"),
                   help="along-fibre growth: 'stretch' lengthens the fibres during the sessions that carry a "
                        "stretch (a protocol's [[session]] stretch = …), dϑ_f/dt = ⟨λ/ϑ_f − λ_crit⟩/τ_f "
                        "(hyper.model.growth.fibre_stretch_step), recorded as the fiber_stretch series; "
                        "'none' (the default): the paper's transverse growth")
    p.add_argument("--stimulus", choices=("global", "local"),
                   help="the exercise stimulus: 'local' scales each cell's β I Fmax by its active fibre stress in "
                        "the contraction at the sessions' intensity, over its volume-weighted mean "
                        "(hyper.fem.stimulus; a field per intensity), recorded as the stimulus_factor field; "
                        "'global' (the default): the paper's one stimulus for every cell")


def parser(ask: str = "growth") -> cli.Parser:
    if ask == "signaling":
        p = cli.Parser("grow --ask signaling", "A signaling question: the ODEs alone for each protocol, no mesh.")
        scene_options(p)
        p.add_argument("--output", type=cli.output(), default="results/signaling", help="an .h5 file or a folder")
        return p

    # here, not at the top: they load DOLFINx and UFL, which --ask signaling never needs
    from hyper.fem import fibers
    from hyper.fem.coupled import GrowthSettings
    from hyper.model.growth import FEEDBACK_LAWS

    p = cli.Parser("grow", __doc__)
    p.add_argument("--geometry", help="geometry id (idealized, cylinder, BFLH_VHF_Left, …); idealized by default")
    p.add_argument("--mesh", type=Path, reads=True,
                   help="your own tetrahedral XDMF mesh instead of --geometry (facet tags "
                   f"'ft_small': 1, 2 the ends, 3 the side); its fibres: the {fibers.FILE_NAME} beside it "
                   "(what hyper mesh writes: Laplace fibres by default), else Stokes fibres computed and kept "
                   "there if the folder is writable "
                   "(--fibers chooses others)")
    p.add_argument("--mesh-unit", help=f"length unit of --mesh ({' or '.join(runspec.MESH_UNITS)}); m by default")
    cli.refine_option(p)
    scene_options(p)
    p.add_argument("--output", type=cli.output(), default="results/grow", help="an .h5 file (one protocol) or a folder")
    p.add_argument("--material", type=Path, metavar="F.toml", reads=True,
                   help="TOML file overriding the muscle law's parameters (hyper.model.material.MaterialParams)")
    p.add_argument("--growth-dt", type=cli.positive("hours"),
                   help=f"growth step Δtg (h); {GrowthSettings.growth_dt:g} unless --accuracy chooses one")
    p.add_argument("--feedback", choices=FEEDBACK_LAWS, default="hill", help="feedback of CSA on protein synthesis")
    presets.add_options(p, signaling_method=False)
    cli.fibre_data_options(p)
    model_options(p)
    p.add_argument("--max-halvings", type=cli.integer(0, GrowthSettings.MAX_HALVINGS),
                   default=GrowthSettings.max_halvings,
                   help="cuts of a growth step whose Newton solve fails before the run stops")
    p.add_argument("--linear-solver", choices=runspec.LINEAR_SOLVERS, help="MUMPS LU, GMRES with MUMPS's block "
                   "low-rank LU (less memory, same answer) or auto (LU while it fits); lu, or auto with --accuracy")
    p.add_argument("--petsc-option", action="append", default=[], metavar="KEY=VALUE",
                   help="a PETSc option of the mechanics solver, e.g. snes_max_it=50 (repeatable)")
    p.add_argument("--snapshot-every", type=cli.positive("hours"), default=driver.SNAPSHOT_EVERY, metavar="HOURS",
                   help="fields snapshot every HOURS of simulated time (at the first growth step on or after "
                        "each multiple), besides the first and the last state")
    p.add_argument("--checkpoint-every", type=cli.integer(0), default=driver.CHECKPOINT_EVERY,
                   help="checkpoint every K growth steps (0: only on SIGTERM and failures)")
    p.add_argument("--data", type=Path, metavar="CSV", reads=True,
                   help="measured CSA to compare with (data/README.md: a time column named week, day or hour, "
                        "and csa or csa_change_percent); by default the project's data set of the protocol, "
                        "if it has one (mwf: DeFreitas)")
    cli.progress_option(p)
    p.add_argument("--restart", action="store_true", help="ignore and delete an existing checkpoint")
    p.add_argument("--plot", type=cli.output(folder=False, suffixes=(".png",)), help="figure; beside the output: "
                   "RESULT.png, or in a folder GEOMETRY_PROTOCOL_growth.png (one protocol), GEOMETRY_growth.png")
    p.add_argument("--plot-box", type=cli.output(folder=False, suffixes=(".png",)), metavar="PNG",
                   help="the box measure's staircase at the end of the run: inner and rim facets, each one's area "
                        "change and the exact cut (meshes without a tagged mid-section); with several protocols "
                        "PNG's stem gets _PROTOCOL")
    return p


def box_plots(path, runs) -> list:
    """Where --plot-box draws each run: ``path``, or one per protocol."""
    if path is None:
        return [None] * len(runs)
    return [path] if len(runs) == 1 else [path.with_name(f"{path.stem}_{p.name}.png") for p in runs]
def untabulated(args) -> list[str]:
    """The options given that change the model away from the one --accuracy's tables
    measured (a signaling question has only the first)."""
    out = []
    if args.signaling_method == "rk45-original":
        out.append("--signaling-method rk45-original")
    if getattr(args, "growth_increment", None) == "left-point":
        out.append("--growth-increment left-point")
    for option, value in (("csa_method", "box"), ("growth_fields", "dg1")):
        if getattr(args, option, None) == value:
            out.append(f"--{option.replace('_', '-')} {value}")
    if getattr(args, "settings", "default") != "default":
        out.append(f"--settings {args.settings}")
    return out


def choose(scene: fidelity.Scene, args, growth_dt=None, mesh_file: bool = False, fibres: str = "stokes"
           ) -> fidelity.Choice | None:
    if args.accuracy is not None and untabulated(args):
        raise InputError(f"--accuracy chooses steps from the errors of the default model; it does not "
                         f"combine with {untabulated(args)[0]}")
    try:
        if args.accuracy is None:
            return None
        if scene.ask == "growth":
            return fidelity.choose_on_mesh(scene, args.accuracy, refine=args.refine, mesh_file=mesh_file,
                                           fibres=fibres, growth_dt=growth_dt, signaling_dt=args.signaling_dt)
        return fidelity.choose(scene, args.accuracy, signaling_dt=args.signaling_dt)
    except InputError as err:
        raise InputError(f"--accuracy {args.accuracy:g}: {err}") from None


def plan(comm, argv) -> sequence.Plan:
    """Parse and check every input; raises InputError before anything is written."""
    return plan_from(comm, parser().parse_args(argv))


def plan_from(comm, args) -> sequence.Plan:
    from hyper.fem import geometry as geo  # DOLFINx: here, as in parser()
    from hyper.fem.coupled import LAG_OPTION, GrowthSettings, jacobian_lag

    if args.mesh is not None and args.geometry is not None:
        raise InputError("--geometry and --mesh exclude each other: give one of them")
    if args.mesh_unit is not None and args.mesh is None:
        raise InputError("--mesh-unit declares the length unit of a --mesh file; there is none")
    mesh = runspec.MeshFile(args.mesh, args.mesh_unit or "m") if args.mesh is not None else None
    name = args.mesh.stem if mesh is not None else (args.geometry if args.geometry is not None else "idealized")
    if mesh is None:
        runspec.check_geometry(comm, name)
    runs = protocols.from_option(args.protocol)
    params = signaling.load_params(args.params) if args.params else signaling.SignalingParams()
    muscle = mat.load(args.material) if args.material else mat.MaterialParams()
    # hyper grow takes uniform parameters only (per-cell ones are hyper ensemble's)
    table, mesh_file, fibres = runspec.table_name(name, mesh, args.fibers or "auto")
    scene = fidelity.Scene(table, ",".join(p.name for p in runs), heterogeneous=False, ask="growth")
    choice = choose(scene, args, args.growth_dt, mesh_file=mesh_file, fibres=fibres)
    steps = (choice.growth_dt, choice.signaling_dt) if choice is not None else (args.growth_dt, args.signaling_dt)
    settings = presets.settings(GrowthSettings, args.settings,
                                {"growth_dt": steps[0], "signaling_dt": steps[1], "feedback": args.feedback,
                                 "max_halvings": args.max_halvings, **presets.chosen(args)}, SETTING_OPTIONS)
    petsc_options = dict(cli.petsc_option(text) for text in args.petsc_option)
    if LAG_OPTION in petsc_options:
        jacobian_lag(petsc_options[LAG_OPTION])
    results = io.result_paths(args.output, [f"{name}_{p.name}" for p in runs])
    # named per run for one protocol: array tasks of one geometry share an output folder
    if args.plot is not None:
        plot = args.plot
    elif args.output.suffix == ".h5":
        plot = args.output.with_suffix(".png")
    else:
        plot = results[0].with_name(f"{results[0].stem}_growth.png") if len(runs) == 1 else \
            args.output / f"{name}_growth.png"
    problem = io.unwritable(plot, folder=False)
    if problem is not None:
        raise InputError(f"--plot: {problem}")

    if args.plot_box is not None:
        if mesh is None and name not in geo.ANATOMICAL + geo.MESHED:
            raise InputError(f"--plot-box: {name} has a tagged mid-section, measured on its facets; the box "
                             "measure is that of the meshes without one")
        problem = io.unwritable(args.plot_box, folder=False)
        if problem is not None:
            raise InputError(f"--plot-box: {problem}")
    data = None
    if args.data is not None:
        data = measured.read(args.data)
        measured.check_section(data, settings.sections)
        for p in runs:
            measured.check_span(data, p)
    if mesh is not None:
        mesh.load(comm)  # units and tags, before anything is written
    solver = args.linear_solver or ("auto" if args.accuracy is not None else "lu")
    shape = presets.shape(args, [name], mesh=mesh is not None)
    source = presets.data_source(args)
    refine = args.refine if choice is None else choice.refine
    specs = [runspec.RunSpec(name, p, params, settings, petsc_options, mesh=mesh, linear_solver=solver, choice=choice,
                             **shape, material=muscle, refine=refine, fiber_data=source) for p in runs]
    if not args.restart:
        sequence.refuse_foreign_checkpoints(comm, specs, [runspec.Outputs(h5) for h5 in results])
    outputs = [runspec.Outputs(h5) for h5 in results]
    return sequence.Plan(specs, outputs, plot, args.snapshot_every, args.checkpoint_every, args.restart,
                         choice, box_plots(args.plot_box, runs), data=data, progress_every=args.progress_every)


def answer_signaling(comm, args) -> int:
    """--ask signaling: the signaling ODEs alone for each protocol, on rank 0; no mesh."""
    runs = protocols.from_option(args.protocol)
    params = signaling.load_params(args.params) if args.params else signaling.SignalingParams()
    scene = fidelity.Scene(None, ",".join(p.name for p in runs), heterogeneous=False, ask="signaling")
    choice = choose(scene, args) or fidelity.assess(scene, None, args.signaling_dt or fidelity.SIGNALING_DT0)
    paths = io.result_paths(args.output, [p.name for p in runs])
    info(comm, f"fidelity: {choice.describe()}")
    method = args.signaling_method or "rk4"
    try:
        on_rank0(comm, lambda: answer(comm, runs, paths, params, choice.signaling_dt, SIGNALING_SAMPLE_EVERY,
                                      groups={"fidelity": choice.as_attributes()}, method=method))
    except signaling.SignalingError as err:
        log.error(comm, str(err))
        return cli.EXIT_FAILED
    return cli.EXIT_OK


EXIT_STATUS = {sequence.Ending.DONE: cli.EXIT_OK, sequence.Ending.FAILED: cli.EXIT_FAILED,
               sequence.Ending.INTERRUPTED: cli.EXIT_TERMINATED}


def exit_status(comm, outcome: sequence.Outcome) -> int:
    """The exit status of a `sequence.carry_out`; an interruption says so, with the status."""
    code = EXIT_STATUS[outcome.ending]
    if outcome.ending is sequence.Ending.INTERRUPTED:
        info(comm, f"{outcome.message}; exit status {code}")
    return code


def grow(comm, args) -> int:
    with driver.StopOnTerm(comm) as stop:
        return exit_status(comm, sequence.carry_out(comm, plan_from(comm, args), stop))


def asks(argv: list[str]) -> str:
    """--ask, read first: a signaling question has its own options and needs no DOLFINx."""
    first = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    first.add_argument("--ask")
    return "signaling" if first.parse_known_args(argv)[0].ask == "signaling" else "growth"


def main(argv=None, comm=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if asks(argv) == "signaling":
        return cli.entry(lambda: parser("signaling"), answer_signaling)(argv, comm)
    return cli.entry(parser, grow)(argv, comm)
