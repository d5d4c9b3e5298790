"""Runs one after another in one process, on every rank: the protocols of `hyper grow`,
the single run of a one-geometry `hyper study`. Each is stored as it ends, so a stop
after the second keeps the first; the figure comes last.
"""

from __future__ import annotations

import dataclasses
import enum
from pathlib import Path

from hyper.core import log
from hyper.core.collective import on_rank0
from hyper.core.log import PROGRESS_EVERY, hms, info
from hyper.model.failure import GrowthFailure
from hyper.runs import driver, fidelity, locks, measured, runspec
from hyper.runs.checkpoint import inspect
from hyper.runs.plot import box_section, growth_series


class Ending(enum.Enum):
    """How a sequence of runs ended (the command maps it to its exit status)."""

    DONE = "done"  # every run stored, the figure drawn
    FAILED = "failed"  # a run failed for good, or its checkpoint could not be written (said on stderr)
    INTERRUPTED = "interrupted"  # stopped on request (SIGTERM), the state saved


@dataclasses.dataclass(frozen=True)
class Outcome:
    """The `Ending` of `carry_out`, and for an interruption what to say (the command adds
    its exit status)."""

    ending: Ending
    message: str = ""


@dataclasses.dataclass(frozen=True)
class Plan:
    """The validated command: the runs, where their results go, and how they are written."""

    specs: list[runspec.RunSpec]
    outputs: list[runspec.Outputs]
    plot: Path
    snapshot_every: float  # h of simulated time
    checkpoint_every: int
    restart: bool
    choice: fidelity.Choice | None  # from --accuracy; None: the fixed steps
    box_plots: list[Path | None] | None = None  # per run, the box measure's picture at its end (--plot-box)
    data: measured.Measured | None = None  # --data; None: each run's protocol's own data set, if any
    progress_every: float = PROGRESS_EVERY  # s of wall time between progress lines

    # what every run of the command shares
    geometry = property(lambda self: self.specs[0].geometry)
    mesh = property(lambda self: self.specs[0].mesh)
    settings = property(lambda self: self.specs[0].settings)
    linear_solver = property(lambda self: self.specs[0].linear_solver)


def refuse_foreign_checkpoints(comm, specs: list[runspec.RunSpec], outputs: list[runspec.Outputs]) -> None:
    """An InputError where a run's checkpoint belongs to another run (another digest): it
    is resumed by its own run only, or dropped with --restart."""
    for spec, out in zip(specs, outputs):
        on_rank0(comm, lambda: out.checkpoint.is_file() and inspect(out.checkpoint, spec.digest()))


def draw_box(comm, model, path: Path, title: str) -> None:
    """The box measure's staircase of ``model`` as it is (`hyper.runs.plot.box_section`). Collective."""
    picture = model.section.box.picture()
    if comm.rank == 0:
        info(comm, f"box figure: {box_section(picture, path, title)}")


def title(work: Plan) -> str:
    """What a figure shows: the geometry, the fibres, the protocols and the CSA measure."""
    spec = work.specs[0]
    section = ("its tagged mid-section" if spec.geometry in measured.GENERIC
               else f"the mid-belly section ({work.settings.csa_method})")
    return (f"{spec.geometry}, fibres {spec.fibers}, {', '.join(s.protocol.name for s in work.specs)}; "
            f"CSA of {section}")


def data_of(work: Plan, spec: runspec.RunSpec) -> measured.Measured | None:
    """What a run is compared with: the plan's data, else its protocol's on a compatible muscle
    (`measured.of_protocol`)."""
    return work.data if work.data is not None else measured.of_protocol(spec.protocol, spec.geometry)


def carry_out(comm, work: Plan, stop, figure: bool = True) -> Outcome:
    """Run a checked plan: every run in turn, its result stored (with its error against
    its data, `data_of`), then the figure (unless ``figure`` is false). Returns how it
    ended; the status file of a failed run records the command (`hyper.core.io.command`)."""
    with locks.hold(comm, [o.h5 for o in work.outputs]):
        if work.choice is not None:
            info(comm, f"fidelity: {work.choice.describe()}")
        results, errors = {}, {}
        for spec, out, box_plot in zip(work.specs, work.outputs, work.box_plots or [None] * len(work.specs)):
            if work.restart:
                on_rank0(comm, lambda: out.checkpoint.unlink(missing_ok=True))
            try:
                done = driver.execute(comm, spec, out, snapshot_every=work.snapshot_every,
                                   checkpoint_every=work.checkpoint_every, stop=stop,
                                   progress_every=work.progress_every)
            except driver.Interrupted as err:
                return Outcome(Ending.INTERRUPTED, f"{spec.protocol.name}: {err}")
            except (driver.Unsaved, GrowthFailure) as err:
                log.error(comm, f"{spec.label}: {err}")
                return Outcome(Ending.FAILED)
            groups = runspec.result_groups(spec, done.choice)
            data = data_of(work, spec)
            if data is not None:
                errors[spec.protocol.name] = measured.compare(data, done.series["t"], done.series["csa_ratio"],
                                                              measured.run_sections(done.series, done.meta))
                groups["data"] = errors[spec.protocol.name].attributes()
                info(comm, f"{spec.protocol.name}: {errors[spec.protocol.name].describe()}")
            on_rank0(comm, lambda: out.store(done.series, done.meta, groups))
            info(comm, f"{spec.protocol.name}: CSA/CSA0 {done.series['csa_ratio'][-1]:.5f}, V/V0 "
                       f"{done.series['volume_ratio'][-1]:.5f} in {hms(done.meta['wall_s'])}; wrote {out.h5} "
                       f"and {out.fields}")
            info(comm, f"{spec.protocol.name}: {runspec.spatial_error(spec).describe()}")
            results[spec.protocol.name] = done.series
            if box_plot is not None:
                draw_box(comm, done.model, box_plot, f"{spec.label}, day {done.model.t / 24:g}")
            done = None  # the model goes before the next run builds its own
        if comm.rank == 0 and figure:
            shown = list({id(e.data): e.data for e in errors.values()}.values())
            info(comm, f"figure: {growth_series(results, work.plot, shown, errors, title(work))}")
    return Outcome(Ending.DONE)
