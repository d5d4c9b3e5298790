"""Measured CSA time courses, and how far a run's CSA is from them.

A data file is a CSV (data/README.md) with a time column named after its unit (``week``,
``day`` or ``hour``) and the CSA: ``csa`` in any unit, or ``csa_change_percent``, the
change from the baseline in percent. Its first row is time 0, the baseline every later
row is divided by, so what is compared is CSA / CSA at time 0 against the model's
CSA/CSA0. The project's data sets (DeFreitas, Damas, Seynnes) were each measured under
one protocol (`SHIPPED`) on one muscle.

Metadata. Lines before the header of the form ``# muscle: NAME`` and ``# measure: TEXT``
say which muscle was measured (one of `MUSCLES`) and how (e.g. "anatomical CSA, mid-thigh,
pQCT"); other ``#`` lines are comments. The shipped files must name both. A run is compared
with a shipped data set unasked (`of_protocol`) only where it ran under that data set's
protocol and on a compatible geometry (`compatible`): an anatomical mesh of a muscle the
measured one contains (the thigh holds the quadriceps and the hamstrings, the quadriceps its
four heads), or a generic shape (idealized, cylinder), which stands for no particular muscle,
as the paper's idealized muscle stood for the DeFreitas thigh. Any other comparison is
asked for with --data.

The error of a run against a data set (`compare`): the root-mean-square difference of
the CSA change over the measured times after time 0, in percentage points, and the
difference (model − measured) at the last measured time; the model's CSA is interpolated
linearly between its growth steps.

Where a CSA was measured. MRI studies measure at a fraction of a muscle's length (or of a
bone's, which approximates one). Lines before the header may name it, as ``section = 0.5``
(or ``# section = 0.5``): a fraction in (0, 1) of the muscle's length along its principal
axis, from the end lowest on that axis. The comparison then uses the run's regional CSA
(`hyper.fem.section.section_fractions`, the result's csa_ratio_sections), linearly
interpolated between the two sections about it (none needed at a recorded one); without the
line, the mid-belly series as before. Other lines beginning with ``#`` are comments.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import re
from pathlib import Path

import numpy as np

from hyper.core import resources
from hyper.core.params import InputError, float_text, read_text
from hyper.model import protocols
from hyper.model.protocols import Protocol
from hyper.runs.checkpoint import file_digest

DATA_DIR = resources.folder("data")
# muscle a data set may name -> the anatomical geometries' muscle codes (the prefix of their
# ids, hyper.fem.geometry.MUSCLES and NEW_MUSCLES) of what it contains
QUADRICEPS = ("RF", "VL", "VM", "VI")
MUSCLES = {
    "thigh": QUADRICEPS + ("BFLH", "ST"),
    "quadriceps": QUADRICEPS,
    "rectus femoris": ("RF",), "vastus lateralis": ("VL",), "vastus medialis": ("VM",),
    "vastus intermedius": ("VI",), "biceps femoris long head": ("BFLH",), "semitendinosus": ("ST",),
    "tibialis anterior": ("TA",), "gastrocnemius medialis": ("GM",),
    "triceps brachii": (),  # no mesh of it: compared on the generic shapes only
}
GENERIC = ("idealized", "cylinder")  # shapes of no particular muscle
TIME_UNITS = {"week": protocols.WEEK, "day": 24.0, "hour": 1.0}  # h per unit
CSA_COLUMNS = ("csa", "csa_change_percent")
METADATA = ("muscle", "measure", "section")  # what the lines before the header may say
SETTING = re.compile(r"([A-Za-z_]\w*)\s*[:=]\s*(.*?)")
# file -> (its label, the protocol it was measured under: a built-in name or a file in DATA_DIR)
SHIPPED = {
    "defreitas.csv": ("DeFreitas et al. 2011", "mwf"),
    "damas.csv": ("Damas et al. 2016", "damas.toml"),
    "seynnes.csv": ("Seynnes et al. 2007", "seynnes.toml"),
    "narici.csv": ("Narici et al. 1989", "narici.toml"),
    "ogasawara.csv": ("Ogasawara et al. 2010", "ogasawara.toml"),
    "ogasawara-continuous.csv": ("Ogasawara et al. 2010, continuous", "ogasawara-continuous.toml"),
}


@dataclasses.dataclass(frozen=True)
class Measured:
    """A measured CSA time course after time 0."""

    path: Path
    label: str
    t: np.ndarray  # h, the measurement times after time 0, increasing
    csa_ratio: np.ndarray  # CSA / CSA at time 0, at t
    section: float | None = None  # the fraction of the muscle's length it was measured at; None: mid-belly
    muscle: str | None = None  # the muscle measured (a key of MUSCLES), where the file says
    measure: str | None = None  # how its CSA was measured, where the file says


def _setting(path: Path, k: int, name: str, value: str):
    """The value of metadata ``name`` given on line ``k``, checked."""
    if name == "section":
        try:
            return float_text(value, "", above=0.0, below=1.0)
        except InputError as err:
            raise InputError(f"{path}: line {k}: section: {err.reason}, a fraction of the muscle's length") from None
    if name == "muscle" and value.lower() not in MUSCLES:
        raise InputError(f"{path}: line {k}: unknown muscle {value!r}; known: {', '.join(MUSCLES)}")
    return value.lower() if name == "muscle" else value


def _metadata(path: Path, lines: list[str]) -> tuple[dict, int]:
    """(metadata by name, the number of lines before the header): the leading lines that
    are blank, comments (``#``) or settings of `METADATA`, ``name: value`` or
    ``name = value``: the first after a ``#``, the second after a ``#`` or not. The header
    is the first other line. An ``=`` setting must name a known setting (a misspelt one is
    an error, not lost); a ``#`` line with a colon naming none is a comment (``# source: …``),
    and so is any other."""
    found, count = {}, 0
    for k, line in enumerate(lines, start=1):
        text = line.strip()
        comment = text.startswith("#")
        if text and not comment and "=" not in text:
            break  # the header
        count = k
        body = text.lstrip("#").strip()
        setting = SETTING.fullmatch(body)
        if setting is None or (comment and "=" not in body and setting.group(1).lower() not in METADATA):
            if text and not comment:
                raise InputError(f"{path}: line {k}: expected a setting 'name = value' before the header, "
                                 f"got {text!r}")
            continue  # a blank line or a comment
        name, value = setting.group(1).lower(), setting.group(2).strip()
        if name not in METADATA:
            raise InputError(f"{path}: line {k}: unknown setting {name!r}; known: {', '.join(METADATA)}")
        if name in found:
            raise InputError(f"{path}: line {k}: {name} given twice")
        found[name] = _setting(path, k, name, value)
    return found, count


def _table(path: Path) -> tuple[str, str, np.ndarray, dict]:
    """(time unit, CSA column, rows of [time, csa], metadata) of a data file; InputError
    naming what is wrong."""
    text = read_text(path, "CSV file")
    metadata, skipped = _metadata(path, text.splitlines())
    # newline="": the csv module's own reading of line ends, as with open(path, newline="")
    rows = list(csv.reader(io.StringIO(text, newline="")))[skipped:]
    if not rows:
        raise InputError(f"{path}: empty file")
    header = [h.strip().lower() for h in rows[0]]
    csa = [h for h in header if h in CSA_COLUMNS]
    if not csa:
        raise InputError(f"{path}: missing column 'csa' (or 'csa_change_percent', in %); columns: "
                         f"{', '.join(header)}")
    if len(csa) > 1:
        raise InputError(f"{path}: give the CSA once, as 'csa' or as 'csa_change_percent', not both")
    units = [h for h in header if h != csa[0]]
    if len(units) != 1:
        raise InputError(f"{path}: expected one time column besides '{csa[0]}', named after its unit "
                         f"({', '.join(TIME_UNITS)}); columns: {', '.join(header)}")
    if units[0] not in TIME_UNITS:
        raise InputError(f"{path}: unknown time unit {units[0]!r}; known: {', '.join(TIME_UNITS)}")
    it, ic = header.index(units[0]), header.index(csa[0])
    values, lines = [], []
    for k, row in enumerate(rows[1:], start=skipped + 2):
        if not any(cell.strip() for cell in row):
            continue
        if len(row) != len(header):
            raise InputError(f"{path}: line {k}: expected {len(header)} values, got {len(row)}")
        try:
            values.append((float(row[it]), float(row[ic])))
        except ValueError:
            raise InputError(f"{path}: line {k}: not a number: {row}") from None
        lines.append(k)
    data = np.array(values, dtype=float).reshape(-1, 2)
    if len(data) < 2:
        raise InputError(f"{path}: need at least two rows (time 0 and a later one)")
    bad = ~np.isfinite(data).all(axis=1)
    if bad.any():
        raise InputError(f"{path}: line {lines[int(np.flatnonzero(bad)[0])]}: NaN or infinite value")
    back = np.diff(data[:, 0]) <= 0
    if back.any():
        raise InputError(f"{path}: line {lines[int(np.flatnonzero(back)[0]) + 1]}: time must increase strictly")
    if data[0, 0] != 0.0:
        raise InputError(f"{path}: the first row must be time 0 (the baseline CSA), got {data[0, 0]:g}")
    return units[0], csa[0], data, metadata


def read(path: str | Path) -> Measured:
    """The CSA time course of a data file (hours, CSA / CSA at time 0)."""
    path = Path(path)
    unit, column, data, meta = _table(path)
    csa = data[:, 1] if column == "csa" else 1.0 + data[:, 1] / 100.0
    if np.any(csa <= 0):
        raise InputError(f"{path}: CSA must be > 0" if column == "csa" else f"{path}: a CSA change must be > -100 %")
    if is_shipped(path):
        missing = [key for key in ("muscle", "measure") if key not in meta]
        if missing:  # the compatibility check rests on it: no shipped file without it
            raise InputError(f"{path}: a shipped data file must say its {' and '.join(missing)} "
                             f"('# {missing[0]}: …' above the header)")
    label = SHIPPED[path.name][0] if is_shipped(path) else path.stem
    return Measured(path, label, data[1:, 0] * TIME_UNITS[unit], csa[1:] / csa[0], meta.get("section"),
                    meta.get("muscle"), meta.get("measure"))


def is_shipped(path: Path) -> bool:
    return path.name in SHIPPED and path.resolve().parent == DATA_DIR.resolve()


def same_schedule(a: Protocol, b: Protocol) -> bool:
    """The same sessions and end, whatever the names."""
    return a.sessions == b.sessions and a.end == b.end


def compatible(data: Measured, geometry: str) -> bool:
    """Whether a run on ``geometry`` may be compared with ``data`` unasked: a generic shape,
    or an anatomical mesh (id MUSCLE_SUBJECT_SIDE) of a muscle the measured one contains."""
    if data.muscle is None:
        return False
    if geometry in GENERIC:
        return True
    return geometry.split("_")[0] in MUSCLES[data.muscle]


def of_protocol(protocol: Protocol, geometry: str) -> Measured | None:
    """The project's data set measured under ``protocol`` (by schedule) on a muscle
    ``geometry`` is compatible with (`compatible`), if any."""
    for name, (_, measured_under) in SHIPPED.items():
        path = DATA_DIR / name
        if not path.is_file():
            continue
        if measured_under in protocols.NAMES:
            theirs = protocols.from_option(measured_under)[0]
        else:
            theirs = protocols.load(DATA_DIR / measured_under)
        if same_schedule(protocol, theirs):
            data = read(path)
            if compatible(data, geometry):
                return data
    return None


def check_span(data: Measured, protocol: Protocol, where: str = "--data") -> None:
    """InputError where the data go on beyond the end of the run."""
    if data.t[-1] > protocol.end * (1 + 1e-12):
        raise InputError(f"{where} {data.path}: measured up to {data.t[-1]:g} h, beyond the end of protocol "
                         f"{protocol.name} ({protocol.end:g} h)")


def check_section(data: Measured, sections: int, where: str = "--data") -> None:
    """InputError where the data were measured at a section that a run recording ``sections``
    regional sections (`hyper.fem.section.section_fractions`) does not span."""
    if data.section is None:
        return
    if sections == 0:
        raise InputError(f"{where} {data.path}: measured at section {data.section:g} of the length; the runs "
                         f"record no regional sections (--sections 0)")
    lo, hi = 1.0 / (sections + 1), sections / (sections + 1)
    if not lo - SAME_SECTION <= data.section <= hi + SAME_SECTION:
        raise InputError(f"{where} {data.path}: measured at section {data.section:g} of the length, outside the "
                         f"{sections} regional sections ({lo:g} to {hi:g}); give more with --sections")


# A section named within this of a recorded one is that one (0.3 in a file, 3/10 in a run).
SAME_SECTION = 1e-9


def section_series(data: Measured, fractions, ratios) -> np.ndarray:
    """The run's CSA/CSA0 over time at the section ``data`` was measured at: its regional
    series ``ratios`` (time × section, at ``fractions``) at that section, linearly between
    the two recorded about it."""
    fractions, ratios = np.asarray(fractions, dtype=float), np.asarray(ratios, dtype=float)
    at = np.flatnonzero(np.abs(fractions - data.section) <= SAME_SECTION)
    if len(at):
        return ratios[:, at[0]]
    if not fractions[0] < data.section < fractions[-1]:
        raise InputError(f"{data.path}: measured at section {data.section:g} of the length, outside the run's "
                         f"sections ({fractions[0]:g} to {fractions[-1]:g})")
    j = int(np.searchsorted(fractions, data.section))
    w = (data.section - fractions[j - 1]) / (fractions[j] - fractions[j - 1])
    return (1.0 - w) * ratios[:, j - 1] + w * ratios[:, j]


@dataclasses.dataclass(frozen=True)
class Comparison:
    """A run's CSA against a measured course, in percentage points of CSA change."""

    data: Measured
    model_csa_ratio: np.ndarray  # the run's CSA/CSA0 at data.t

    @property
    def difference_pp(self) -> np.ndarray:
        return 100.0 * (self.model_csa_ratio - self.data.csa_ratio)

    @property
    def rmse_pp(self) -> float:
        return float(math.sqrt(np.mean(self.difference_pp ** 2)))

    @property
    def last_difference_pp(self) -> float:
        return float(self.difference_pp[-1])

    def describe(self) -> str:
        return (f"against {self.data.label} ({self.data.path.name}, {self.data.muscle or 'muscle not given'}, "
                f"{len(self.data.t)} points): RMSE "
                f"{self.rmse_pp:.2f} percentage points of CSA change, model − data at "
                f"{self.data.t[-1]:g} h {self.last_difference_pp:+.2f} points")

    def attributes(self) -> dict:
        """The result's ``data`` group."""
        where = {} if self.data.section is None else {"section": self.data.section}
        return {"file": str(self.data.path), "file_sha256": file_digest(self.data.path), "label": self.data.label,
                **where, "muscle": self.data.muscle or "not given", "measure": self.data.measure or "not given",
                "rmse_pp": self.rmse_pp, "last_difference_pp": self.last_difference_pp,
                "last_time_h": float(self.data.t[-1]), "time_h": self.data.t,
                "measured_csa_ratio": self.data.csa_ratio, "model_csa_ratio": self.model_csa_ratio}


def compare(data: Measured, t: np.ndarray, csa_ratio: np.ndarray, sections=None) -> Comparison:
    """The run with series ``t`` (h, from 0) and ``csa_ratio`` against ``data`` (within the run).

    ``sections``: (fractions, ratios) of the run's regional CSA (`section_series`), which data
    measured at a section are compared with; InputError for such data without them."""
    if data.section is not None:
        if sections is None:
            raise InputError(f"{data.path}: measured at section {data.section:g} of the length; the run "
                             f"records no regional sections")
        csa_ratio = section_series(data, *sections)
    return Comparison(data, np.interp(data.t, np.asarray(t, dtype=float), np.asarray(csa_ratio, dtype=float)))


def run_sections(series: dict, meta: dict):
    """(fractions, ratios) of a run's regional CSA for `compare`, or None where it has none."""
    if "csa_ratio_sections" not in series:
        return None
    return meta["section_fractions"], series["csa_ratio_sections"]
