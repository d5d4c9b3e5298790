"""A whole study in one file (`hyper study STUDY.toml`, whose help describes the file):
its sections read and checked (`load`: every key is checked, an unknown one is an error,
and paths of inputs are relative to the study file's folder), and what it runs: one
geometry × one protocol as `hyper grow` does, more as a cohort on the MPI farm
(`hyper.analysis.cohort`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path

from hyper.analysis import cohort, sobol
from hyper.core import io
from hyper.core.log import PROGRESS_EVERY
from hyper.core.params import (
    InputError,
    as_attributes,
    as_seed,
    build,
    finite,
    positive_hours,
    read_toml,
    replace_from_mapping,
    shown,
)
from hyper.fem import fiberread as fr
from hyper.fem import geometry as geo
from hyper.fem.coupled import GrowthSettings
from hyper.model import material as mat
from hyper.model import protocols, signaling
from hyper.model.growth import FEEDBACK_LAWS
from hyper.model.heterogeneity import Heterogeneity
from hyper.model.protocols import Protocol
from hyper.runs import driver, fidelity, measured, runspec, sequence

KEYS = ("geometries", "protocols", "mesh", "protocol", "signaling", "material", "heterogeneity", "numerics",
        "output", "sobol", "data")
# fibres from data on a mesh (hyper.fem.fiberdata): the file and how it is read
MESH_FIBRE_KEYS = ("fibers", "fibers_unit", "fibers_min_fa", "fibers_radius_mm", "fibers_fa")
MESH_KEYS = ("file", "unit", *MESH_FIBRE_KEYS)
DATA_KEYS = ("file",)
HETEROGENEITY_KEYS = ("model", "epsilon", "length", "nu", "seed")
DEFAULT_FOLDER = Path("results/study")


# ----------------------------------------------------------------------- the sections


@dataclasses.dataclass(frozen=True)
class Numerics:
    """How the runs are solved. None: the default, or what accuracy chooses."""

    growth_dt: float | None = None  # h, the longest growth step
    accuracy: float | None = None  # fraction of the growth (hyper.runs.fidelity), in (0, 0.5)
    signaling_dt: float | None = None  # h, the RK4 step
    quadrature_degree: int | None = None  # of the built-in geometries; None: theirs (4)
    refine: int = 0  # uniform refinements of every mesh (hyper.fem.geometry.refine)
    linear_solver: str | None = None  # lu, iterative or auto; None: lu, or auto with accuracy
    max_halvings: int = GrowthSettings.max_halvings  # cuts of a failing growth step
    feedback: str = GrowthSettings.feedback  # hill, linear or none
    grow_during_sessions: bool = GrowthSettings.grow_during_sessions  # False: the original code's
    consistent_stress: bool = GrowthSettings.consistent_stress  # False: the original code's P = Fe S
    sections: int = GrowthSettings.sections  # regional CSA sections along the principal axis (0: none)
    detraining: float | None = None  # h, the gain's turnover time constant; None: none (the paper's)
    fiber_growth: str = GrowthSettings.fiber_growth  # along-fibre growth: none (the paper's) or stretch
    fiber_tau: float = GrowthSettings.fiber_tau  # h, its time constant
    fiber_crit: float = GrowthSettings.fiber_crit  # its homeostatic elastic fibre stretch
    stimulus: str = GrowthSettings.stimulus  # the exercise stimulus: global (the paper's) or local

    def __post_init__(self):
        for name in ("growth_dt", "signaling_dt"):
            if getattr(self, name) is not None:
                positive_hours(getattr(self, name), name)
        if self.growth_dt is not None and self.signaling_dt is not None and self.signaling_dt > self.growth_dt:
            raise InputError(f"{self.signaling_dt:g} h must not exceed the growth step ({self.growth_dt:g} h)",
                             field="signaling_dt")
        a = self.accuracy
        if a is not None and (isinstance(a, bool) or not isinstance(a, (int, float))
                              or not (finite(a) and 0 < a < 0.5)):
            raise InputError(f"expected a number in (0, 0.5), a fraction of the growth (1e-3 is 0.1 %), got {shown(a)}",
                             field="accuracy")
        q = self.quadrature_degree
        if q is not None and (isinstance(q, bool) or not isinstance(q, int) or not 1 <= q <= 12):
            raise InputError(f"expected an integer in [1, 12], got {shown(q)}", field="quadrature_degree")
        r = self.refine
        if isinstance(r, bool) or not isinstance(r, int) or not 0 <= r <= runspec.MAX_REFINE:
            raise InputError(f"expected an integer in [0, {runspec.MAX_REFINE}], got {shown(r)}", field="refine")
        if self.linear_solver is not None and self.linear_solver not in runspec.LINEAR_SOLVERS:
            raise InputError(f"expected one of {', '.join(runspec.LINEAR_SOLVERS)}, got {self.linear_solver!r}",
                             field="linear_solver")
        m = self.max_halvings
        if isinstance(m, bool) or not isinstance(m, int) or not 0 <= m <= GrowthSettings.MAX_HALVINGS:
            raise InputError(f"expected an integer in [0, {GrowthSettings.MAX_HALVINGS}], got {shown(m)}",
                             field="max_halvings")
        if self.feedback not in FEEDBACK_LAWS:
            raise InputError(f"expected one of {', '.join(FEEDBACK_LAWS)}, got {self.feedback!r}", field="feedback")
        for name in ("grow_during_sessions", "consistent_stress"):
            if not isinstance(getattr(self, name), bool):
                raise InputError(f"expected true or false, got {getattr(self, name)!r}", field=name)
        GrowthSettings(sections=self.sections, detraining=self.detraining, fiber_growth=self.fiber_growth,
                       fiber_tau=self.fiber_tau, fiber_crit=self.fiber_crit,
                       stimulus=self.stimulus)  # checks them, naming them


@dataclasses.dataclass(frozen=True)
class Output:
    folder: Path = DEFAULT_FOLDER  # where the results go
    figures: bool = True  # the growth figure (one run), or ratios.png and shape.png (a cohort)
    snapshot_every: float = driver.SNAPSHOT_EVERY  # h of simulated time between fields snapshots

    def __post_init__(self):
        positive_hours(self.snapshot_every, "snapshot_every")
        if not isinstance(self.folder, Path) or not str(self.folder) or "\0" in str(self.folder):
            raise InputError(f"expected a folder path, got {self.folder!r}", field="folder")
        problem = io.unwritable(self.folder, folder=True)
        if problem is not None:
            raise InputError(problem, field="folder")
        if not isinstance(self.figures, bool):
            raise InputError(f"expected true or false, got {self.figures!r}", field="figures")


@dataclasses.dataclass(frozen=True)
class Study:
    """A checked study: what runs, with which parameters, how solved and where written."""

    geometries: tuple[str, ...]  # built-in geometry ids
    meshes: tuple[runspec.MeshFile, ...]  # the user's mesh files
    protocols: tuple[Protocol, ...]
    signaling: signaling.SignalingParams = signaling.SignalingParams()
    material: mat.MaterialParams = mat.MaterialParams()
    heterogeneity: Heterogeneity | None = None
    seed: int | None = None  # of the per-cell parameters
    numerics: Numerics = Numerics()
    output: Output = Output()
    data: measured.Measured | None = None  # the measured CSA every run is compared with
    # fibres from data of the mesh files, by their stems ([[mesh]] fibers = "FILE")
    fibres: Mapping[str, fr.Source] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        unknown = [g for g in self.geometries if g not in geo.GEOMETRIES]
        if unknown:
            raise InputError(f"unknown {', '.join(map(repr, unknown))}; known: {', '.join(geo.GEOMETRIES)}",
                             field="geometries")
        if not self.names:
            raise InputError("no geometry: give geometries = [...] or [[mesh]] tables", field="geometries")
        if not self.protocols:
            raise InputError("no protocol: give protocols = [...] or [[protocol]] tables", field="protocols")
        for field, names in (("geometries", self.names), ("protocols", [p.name for p in self.protocols])):
            repeated = sorted({n for n in names if names.count(n) > 1})
            if repeated:
                raise InputError(f"names must be unique (a mesh is named by its file's stem); repeated: "
                                 f"{', '.join(repeated)}", field=field)
        if self.meshes and self.numerics.quadrature_degree is not None:
            raise InputError("applies to the built-in geometries only; a [[mesh]] is given",
                             field="numerics.quadrature_degree")
        if (self.heterogeneity is None) != (self.seed is None):
            raise InputError("per-cell parameters need both a model and a seed", field="heterogeneity")
        for p in self.protocols if self.data is not None else ():
            measured.check_span(self.data, p, "data.file")
        if self.data is not None:
            measured.check_section(self.data, self.numerics.sections, "data.file")

    @property
    def names(self) -> list[str]:
        """The geometries' names: the built-in ids, then the mesh files' stems."""
        return [*self.geometries, *(m.path.stem for m in self.meshes)]


# ----------------------------------------------------------------------- reading a file


def table(data: dict, key: str, where: str, known: tuple[str, ...]) -> dict:
    """The table ``data[key]`` (empty when absent), with no key outside ``known``."""
    value = data.get(key, {})
    if not isinstance(value, dict):
        raise InputError(f"{where}: {key}: expected a table ([{key}]), got {value!r}")
    keys_of(value, f"{where}: {key}", known)
    return value


def keys_of(value: dict, where: str, known: tuple[str, ...]) -> None:
    unknown = sorted(set(value) - set(known))
    if unknown:
        raise InputError(f"{where}: unknown key(s) {', '.join(unknown)}; known: {', '.join(known)}")


def tables(data: dict, key: str, where: str) -> list[dict]:
    value = data.get(key, [])
    if not isinstance(value, list) or not all(isinstance(t, dict) for t in value):
        raise InputError(f"{where}: {key}: expected an array of tables ([[{key}]] blocks), got {value!r}")
    return value


def strings(data: dict, key: str, where: str) -> list[str]:
    value = data.get(key, [])
    if not isinstance(value, list) or not all(isinstance(s, str) for s in value):
        raise InputError(f"{where}: {key}: expected an array of strings, got {value!r}")
    return value


def named_protocol(text: str, base: Path, where: str) -> list[Protocol]:
    """A ``protocols`` entry: a built-in name, "all", or a protocol file relative to ``base``."""
    if text in protocols.NAMES or text == "all":
        return protocols.from_option(text, where)
    path = base / text
    if not path.is_file():
        raise InputError(f"{where}: {text!r} is neither a built-in protocol ({', '.join(protocols.NAMES)} or all) "
                         f"nor a protocol file ({path}: no such file)")
    return [protocols.load(path)]


def mesh_file(entry: dict, base: Path, where: str) -> runspec.MeshFile:
    keys_of(entry, where, MESH_KEYS)
    if not isinstance(entry.get("file"), str):
        raise InputError(f"{where}: file: expected the path of an XDMF mesh file, got {entry.get('file')!r}")
    unit = entry.get("unit", "m")
    if unit not in runspec.MESH_UNITS:
        raise InputError(f"{where}: unit: expected one of {', '.join(runspec.MESH_UNITS)}, got {unit!r}")
    path = base / entry["file"]
    if not path.is_file():
        raise InputError(f"{where}: file: {path}: no such file")
    try:
        return runspec.MeshFile(path, unit)
    except InputError as err:
        raise InputError(f"{where}: {err}") from None


def mesh_fibres(entry: dict, base: Path, where: str) -> fr.Source | None:
    """The fibres from data of a [[mesh]] table (its paths relative to ``base``), if it names a file."""
    if "fibers" not in entry:
        given = [k for k in MESH_FIBRE_KEYS if k in entry]
        if given:
            raise InputError(f"{where}: {given[0]} applies to fibres from data: give fibers = \"FILE\" too")
        return None
    for key in ("fibers", "fibers_fa", "fibers_unit"):
        if key in entry and not isinstance(entry[key], str):
            raise InputError(f"{where}: {key}: expected a string, got {entry[key]!r}")
    radius = entry.get("fibers_radius_mm")
    try:
        return fr.Source(base / entry["fibers"], entry.get("fibers_unit", "auto"),
                         entry.get("fibers_min_fa", fr.MIN_FA), None if radius is None else radius * 1e-3,
                         base / entry["fibers_fa"] if "fibers_fa" in entry else None)
    except InputError as err:
        raise InputError(f"{where}: fibers: {err}") from None


def heterogeneity_of(values: dict, where: str) -> tuple[Heterogeneity | None, int | None]:
    if not values:
        return None, None
    values = dict(values)
    seed = as_seed(values.pop("seed", None), f"{where}: seed")  # the per-cell parameters' random seed
    try:
        return Heterogeneity(**values), seed
    except (InputError, TypeError) as err:
        raise InputError(f"{where}: {err}") from None


def data_file(data: dict, base: Path, where: str) -> measured.Measured | None:
    """The [data] table's measured CSA (its file relative to ``base``), if there is one."""
    if "data" not in data:
        return None
    entry = table(data, "data", where, DATA_KEYS)
    if not isinstance(entry.get("file"), str):
        raise InputError(f"{where}: data.file: expected the path of a CSV file of measured CSA (data/README.md), "
                         f"got {entry.get('file')!r}")
    path = base / entry["file"]
    if not path.is_file():
        raise InputError(f"{where}: data.file: {path}: no such file")
    try:
        return measured.read(path)
    except InputError as err:
        raise InputError(f"{where}: data.file: {err}") from None


def load(path: str | Path, overrides: dict | None = None, data_path: Path | None = None) -> Study:
    """The study of a file, with ``overrides`` (field -> (option, value)) of its
    [numerics] and [output] keys from the command line, and --data instead of
    its [data] file (``data_path``). InputError names the key and the expected form (or the option, for
    a bad overriding value)."""
    path = Path(path)
    where = str(path)
    base = path.parent
    data = read_toml(path)
    keys_of(data, where, KEYS)
    if "sobol" in data:
        sobol.read_config(path)
    overrides = overrides or {}
    protocol_list = [p for text in strings(data, "protocols", where)
                     for p in named_protocol(text, base, f"{where}: protocols")]
    for i, entry in enumerate(tables(data, "protocol", where)):
        protocol_list.append(protocols.from_table(entry, f"{where}: protocol {i}", f"protocol{i}"))
    mesh_tables = tables(data, "mesh", where)
    meshes = tuple(mesh_file(entry, base, f"{where}: mesh {i}") for i, entry in enumerate(mesh_tables))
    fibres = {mesh.path.stem: source for i, (mesh, entry) in enumerate(zip(meshes, mesh_tables))
              if (source := mesh_fibres(entry, base, f"{where}: mesh {i}")) is not None}
    params = replace_from_mapping(signaling.SignalingParams(), table(data, "signaling", where,
                                                                     tuple(as_attributes(signaling.SignalingParams()))),
                                  f"{where}: signaling")
    muscle = mat.from_mapping(table(data, "material", where, tuple(as_attributes(mat.MaterialParams()))),
                              f"{where}: material")
    het, seed = heterogeneity_of(table(data, "heterogeneity", where, HETEROGENEITY_KEYS), f"{where}: heterogeneity")
    against = data_file(data, base, where) if data_path is None else measured.read(data_path)
    sections = {}
    for name, cls in (("numerics", Numerics), ("output", Output)):
        known = tuple(f.name for f in dataclasses.fields(cls))
        values = dict(table(data, name, where, known))
        sources = {key: f"{where}: {name}.{key}" for key in known}
        if name == "output" and "folder" in values:
            if not isinstance(values["folder"], str):
                raise InputError(f"{where}: output.folder: expected a folder path, got {values['folder']!r}")
            values["folder"] = Path(values["folder"])
        for key, (option, value) in overrides.items():
            if key in known:
                values[key] = value
                sources[key] = option
        # an error names where its key was set: the file, or the option that overrode it
        sections[name] = build(cls, sources, **values)
    try:
        return Study(tuple(strings(data, "geometries", where)), meshes, tuple(protocol_list), params, muscle, het,
                     seed, **sections, data=against, fibres=fibres)
    except InputError as err:
        raise InputError(f"{where}: {err}") from None


def steps(study: Study) -> tuple[GrowthSettings, fidelity.Choice | None]:
    """The growth settings, and the fidelity choice where accuracy sets the steps."""
    n = study.numerics
    choice = None
    growth_dt, signaling_dt = n.growth_dt, n.signaling_dt
    if n.accuracy is not None:
        try:
            choice = mesh_and_steps(study, growth_dt, signaling_dt)
        except InputError as err:
            raise InputError(f"numerics.accuracy {n.accuracy:g}: {err}") from None
        growth_dt, signaling_dt = choice.growth_dt, choice.signaling_dt
    settings = build(GrowthSettings, {k: f"numerics.{k}" for k in ("growth_dt", "signaling_dt", "max_halvings",
                                                                    "sections", "detraining", "fiber_growth",
                                                                    "fiber_tau", "fiber_crit", "stimulus")},
                     growth_dt=GrowthSettings.growth_dt if growth_dt is None else growth_dt,
                     signaling_dt=GrowthSettings.signaling_dt if signaling_dt is None else signaling_dt,
                     max_halvings=n.max_halvings, feedback=n.feedback, grow_during_sessions=n.grow_during_sessions,
                     consistent_stress=n.consistent_stress, sections=n.sections, detraining=n.detraining,
                     fiber_growth=n.fiber_growth, fiber_tau=n.fiber_tau, fiber_crit=n.fiber_crit,
                     stimulus=n.stimulus)
    return settings, choice


def mesh_and_steps(study: Study, growth_dt, signaling_dt) -> fidelity.Choice:
    """`fidelity.choose_on_mesh` over every geometry of the study: one refinement for all
    (a study's `refine` is one number), the fewest that each geometry's mesh needs, and the
    steps from what the worst mesh at that refinement leaves of the accuracy."""
    n, protocols = study.numerics, ",".join(p.name for p in study.protocols)
    files = {m.path.stem: m for m in study.meshes}

    def on(name: str, refine: int) -> fidelity.Choice:
        table, mesh_file, fibres = runspec.table_name(name, files.get(name))
        scene = fidelity.Scene(table, protocols, heterogeneous=study.heterogeneity is not None, ask="growth")
        return fidelity.choose_on_mesh(scene, n.accuracy, refine=refine, mesh_file=mesh_file, fibres=fibres,
                                       growth_dt=growth_dt, signaling_dt=signaling_dt)

    refine = max(on(name, n.refine).refine for name in study.names)
    return max((on(name, refine) for name in study.names), key=lambda c: c.spatial_error)


def spec_options(study: Study, choice) -> dict:
    """The `RunSpec` fields a study sets beyond geometry, protocol, parameters and settings."""
    solver = study.numerics.linear_solver or ("auto" if choice is not None else "lu")
    return {"heterogeneity": study.heterogeneity, "seed": study.seed, "linear_solver": solver, "choice": choice,
            "quadrature_degree": study.numerics.quadrature_degree,
            "refine": study.numerics.refine if choice is None or choice.refine is None else choice.refine,
            "material": study.material}


def check_inputs(comm, study: Study) -> None:
    """The geometries can run and the mesh files have the units they declare (collective)."""
    for name in study.geometries:
        runspec.check_geometry(comm, name, "geometries")
    for mesh in study.meshes:
        mesh.load(comm)
    # the Stokes fibres of the meshes without a fibre file, computed and kept once before
    # any run (their digests name the file); those with fibres from data need none
    driver.prepare_fibres(comm, [m for m in study.meshes if m.path.stem not in study.fibres])


def first_spec(study: Study, settings, choice) -> runspec.RunSpec:
    """The run of the first geometry with the first protocol."""
    source = study.fibres.get(study.names[0])
    return runspec.RunSpec(study.names[0], study.protocols[0], study.signaling, settings, {},
                           mesh=study.meshes[0] if study.meshes else None, **spec_options(study, choice),
                           **cohort.data_fields(source))


# ----------------------------------------------------------------------- running it


def one_plan(comm, study: Study, settings, choice, progress_every: float = PROGRESS_EVERY) -> sequence.Plan:
    """One geometry × one protocol: `hyper grow`'s plan (collective: it refuses another
    run's checkpoint where the result goes)."""
    name, protocol = study.names[0], study.protocols[0]
    folder = study.output.folder
    spec = first_spec(study, settings, choice)
    outputs = [runspec.Outputs(folder / f"{name}_{protocol.name}.h5")]
    sequence.refuse_foreign_checkpoints(comm, [spec], outputs)
    return sequence.Plan([spec], outputs, folder / f"{name}_growth.png", study.output.snapshot_every,
                         driver.CHECKPOINT_EVERY, False, choice, data=study.data, progress_every=progress_every)


def cohort_runs(study: Study) -> list[cohort.Run]:
    """More runs: every geometry (the mesh files by their stems) with every protocol."""
    return cohort.plan(study.names, list(study.protocols), {m.path.stem: m for m in study.meshes}, study.fibres)


def run_many(comm, study: Study, runs: list[cohort.Run], settings, choice, stop, ranks_per_job: int,
             progress_every: float = PROGRESS_EVERY):
    """`hyper cohort`'s farm over ``runs`` with the study's parameters, numerics and data."""
    return cohort.run_cohort(comm, runs, study.output.folder, params=study.signaling, settings=settings,
                             ranks_per_job=ranks_per_job, stop=stop, options=spec_options(study, choice),
                             snapshot_every=study.output.snapshot_every, data=study.data,
                             progress_every=progress_every)
