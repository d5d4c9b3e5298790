"""Exercise protocols as data (MODEL.md §2): sessions, named protocols, TOML files.

A session is an interval [start, start + duration) of constant intensity; a protocol is a
sorted tuple of non-overlapping sessions and an end time. Times are in hours. Everything
is validated when a ``Protocol`` is built, so a bad protocol never reaches a solver, and
every message names the offending session (by its index, counting from 0) and field.
"""

from __future__ import annotations

import math
import numbers
import re
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from hyper.core.params import InputError, as_float, as_int, finite, read_toml, shown

NAMES = ("mwf", "weekly", "every3days", "daily15", "rest")

WEEK = 168.0  # h


@dataclass(frozen=True)
class Session:
    start: float  # h
    duration: float  # h
    intensity: float  # fraction of the maximal force capacity, in [0, 1]
    # a passive (or eccentric) stretch the session imposes along the fibres, as the stretched
    # length over the rest length (>= 1; 1.1: 10 % longer): what along-fibre growth
    # (`hyper.model.growth.fibre_stretch_step`) responds to. None: none, the paper's sessions.
    stretch: float | None = None

    @property
    def end(self) -> float:
        return self.start + self.duration


# A protocol's name names its result files: letters, digits and . _ + - @, not starting
# with a dot, so that it can neither climb out of a folder nor hide in one.
NAME = re.compile(r"[A-Za-z0-9_+@-][A-Za-z0-9._+@-]{0,63}")
# Ten years of training: beyond it a protocol is a typing mistake, and its step count
# (end / RK4 step) would not fit in memory.
MAX_END = 10 * 52 * WEEK  # h
MAX_SESSIONS = 100_000


@dataclass(frozen=True)
class Protocol:
    sessions: tuple[Session, ...]
    end: float  # h, end of the simulated time span [0, end]
    name: str = "custom"

    def __post_init__(self):
        if not isinstance(self.name, str) or not NAME.fullmatch(self.name):
            raise InputError(f"name must be 1-64 letters, digits or . _ + - @ (not starting with a dot), "
                             f"got {self.name!r}")
        object.__setattr__(self, "sessions", tuple(self.sessions))
        if len(self.sessions) > MAX_SESSIONS:
            raise InputError(f"at most {MAX_SESSIONS} sessions, got {len(self.sessions)}")
        for i, s in enumerate(self.sessions):
            where = f"session {i}"
            for field in ("start", "duration", "intensity"):
                value = getattr(s, field)
                if isinstance(value, bool) or not isinstance(value, numbers.Real) or not finite(value):
                    raise InputError(f"{where}: {field} must be a finite number, got {shown(value)}")
            if s.start < 0:
                raise InputError(f"{where}: start must be >= 0 h, got {s.start:g}")
            if s.duration <= 0:
                raise InputError(f"{where}: duration must be > 0 h, got {s.duration:g}")
            if not 0.0 <= s.intensity <= 1.0:
                raise InputError(f"{where}: intensity must lie in [0, 1], got {s.intensity:g}")
            if s.stretch is not None and (isinstance(s.stretch, bool) or not isinstance(s.stretch, numbers.Real)
                                          or not finite(s.stretch) or s.stretch < 1.0):
                raise InputError(f"{where}: stretch must be a finite number >= 1 (the stretched length over the "
                                 f"rest length), got {shown(s.stretch)}")
            if i > 0:
                prev = self.sessions[i - 1]
                if s.start < prev.start:
                    raise InputError(
                        f"{where}: sessions must be sorted by start, but it starts at {s.start:g} h, "
                        f"before session {i - 1} ({prev.start:g} h)"
                    )
                if s.start < prev.end:
                    raise InputError(
                        f"{where}: overlaps session {i - 1}: it starts at {s.start:g} h, "
                        f"before session {i - 1} ends ({prev.end:g} h)"
                    )
        # plain floats from here on: ints and numpy scalars would leak into attributes and sums
        object.__setattr__(
            self, "sessions",
            tuple(Session(float(s.start), float(s.duration), float(s.intensity),
                          None if s.stretch is None else float(s.stretch)) for s in self.sessions)
        )
        end = self.end
        if isinstance(end, bool) or not isinstance(end, numbers.Real) or not finite(end) or end <= 0:
            raise InputError(f"end must be a finite number > 0 h, got {shown(end)}")
        if end > MAX_END:
            raise InputError(f"end must be at most {MAX_END:g} h (ten years), got {end:g}")
        if self.sessions and end < self.sessions[-1].end:
            last = len(self.sessions) - 1
            raise InputError(f"end ({end:g} h) lies before the end of the last session {last} "
                             f"({self.sessions[-1].end:g} h)")
        object.__setattr__(self, "end", float(end))

    @cached_property
    def starts(self) -> np.ndarray:
        return np.array([s.start for s in self.sessions], dtype=float)

    @cached_property
    def ends(self) -> np.ndarray:
        return np.array([s.end for s in self.sessions], dtype=float)

    @cached_property
    def intensities(self) -> np.ndarray:
        return np.array([s.intensity for s in self.sessions], dtype=float)

    @cached_property
    def stretched(self) -> bool:
        """Whether any session carries a stretch."""
        return any(s.stretch is not None for s in self.sessions)

    def stretch_at(self, t0: float, t1: float) -> float | None:
        """The stretch of the session that is the period [t0, t1] of `periods` (None: a rest,
        or a session without one)."""
        for s in self.sessions:
            if s.start == t0 and s.end == t1:
                return s.stretch
        return None

    def periods(self) -> list[tuple[float, float, bool]]:
        """Consecutive (start, end, in_session) intervals covering [0, end].

        Each session is one period and each rest gap between sessions another; gaps of
        zero length are left out.
        """
        out = []
        t = 0.0
        for s in self.sessions:
            if s.start > t:
                out.append((t, s.start, False))
            out.append((s.start, s.end, True))
            t = s.end
        if self.end > t:
            out.append((t, float(self.end), False))
        return out

    def to_attributes(self) -> dict:
        """The protocol as HDF5 attributes (arrays of session fields; empty for rest), and
        the sessions' stretches (1 where a session has none) only where one has a stretch,
        so that the attributes (and digests) of the paper's protocols stay as they were."""
        out = {
            "name": self.name,
            "end": float(self.end),
            "starts": self.starts,
            "durations": self.ends - self.starts,
            "intensities": self.intensities,
        }
        if self.stretched:
            out["stretches"] = np.array([1.0 if s.stretch is None else s.stretch for s in self.sessions])
        return out


def _regular(name: str, first: float, every: float, count: int, duration: float, intensity: float,
             end: float) -> Protocol:
    return Protocol(
        tuple(Session(first + every * k, duration, intensity) for k in range(count)), end, name
    )


def named(name: str) -> Protocol:
    """The protocols of the paper (MODEL.md §2): one week of rest, then eight weeks of training."""
    if name == "mwf":
        starts = [WEEK + WEEK * w + d for w in range(8) for d in (0.0, 48.0, 96.0)]
        return Protocol(tuple(Session(s, 1.0, 0.8) for s in starts), 9 * WEEK, name)
    if name == "weekly":
        return _regular(name, WEEK, WEEK, 8, 1.0, 0.8, 9 * WEEK)
    if name == "every3days":
        return _regular(name, WEEK, 72.0, 18, 4.0, 0.2, 9 * WEEK)
    if name == "daily15":
        return _regular(name, 0.0, 24.0, 15, 1.0, 0.8, 480.0)
    if name == "rest":
        return Protocol((), 9 * WEEK, name)
    raise InputError(f"unknown protocol {name!r}; known: {', '.join(NAMES)}")


SESSION_KEYS = ("start", "duration", "intensity")
SESSION_OPTIONAL = ("stretch",)  # a session's passive stretch (`Session.stretch`), none if left out
# The training weeks begin on a Monday (after the rest lead-in): day 0 of a week is "mon".
WEEKDAYS = ("mon", "tue", "wed", "thu", "fri", "sat", "sun")
REPEAT_KEYS = ("weekdays", "every_days", "duration", "intensity", "weeks", "lead_in_days")
DAY = 24.0  # h


@dataclass(frozen=True)
class Repeat:
    """Sessions by rule: on some weekdays of every week, or every N days, for a number of
    training weeks after a rest lead-in. Exactly one of ``weekdays`` and ``every_days``."""

    duration: float  # h, of each session
    intensity: float  # fraction of the maximal force capacity, in [0, 1]
    weeks: int  # training weeks; the protocol ends with the last of them
    weekdays: tuple[str, ...] = ()  # of WEEKDAYS, the days of each training week with a session
    every_days: float | None = None  # days from one session's start to the next's
    lead_in_days: float = 0.0  # days of rest before the first training week

    def __post_init__(self):
        object.__setattr__(self, "weekdays", tuple(self.weekdays))
        if bool(self.weekdays) == (self.every_days is not None):
            raise InputError("give exactly one of weekdays (e.g. [\"mon\", \"wed\", \"fri\"]) and every_days "
                             "(a number of days)", field="repeat")
        for day in self.weekdays:
            if day not in WEEKDAYS:
                raise InputError(f"expected days of {', '.join(WEEKDAYS)}, got {day!r}", field="weekdays")
        if len(set(self.weekdays)) < len(self.weekdays):
            raise InputError(f"a day appears twice in {list(self.weekdays)}", field="weekdays")
        if self.every_days is not None and not (finite(self.every_days) and self.every_days > 0):
            raise InputError(f"expected a finite number of days > 0, got {shown(self.every_days)}",
                             field="every_days")
        as_int(self.weeks, "weeks", 1, int(MAX_END / WEEK))
        # the lead-in and the training weeks together within MAX_END, so that start times stay finite
        most = MAX_END / DAY - self.weeks * 7
        if not (finite(self.lead_in_days) and 0 <= self.lead_in_days <= most):
            raise InputError(f"expected a number of days in [0, {most:g}] (with {self.weeks} weeks, ten years in "
                             f"all), got {shown(self.lead_in_days)}", field="lead_in_days")
        # bound before expanding: a tiny period would build millions of sessions first
        if self._periods() > MAX_SESSIONS:
            raise InputError(f"{self._periods():.3g} sessions, more than {MAX_SESSIONS}: every_days "
                             f"{self.every_days:g} over {self.weeks} weeks", field="every_days")

    def _periods(self) -> float:
        """The sessions the rule makes, as a float (inf for a period too small to count)."""
        if self.weekdays:
            return float(self.weeks * len(self.weekdays))
        # every_days apart from the lead-in's end until the last training week ends (`protocol`)
        first = self.lead_in_days * DAY
        return (first + self.weeks * WEEK - first) / (self.every_days * DAY)

    def count(self) -> int:
        """How many sessions the rule makes, counted without making them (at most MAX_SESSIONS)."""
        return math.ceil(self._periods())

    def protocol(self, name: str, end: float | None = None) -> Protocol:
        """The sessions of the rule; ``end`` (h) by default the end of the last training week."""
        first = self.lead_in_days * DAY
        stop = first + self.weeks * WEEK
        if self.weekdays:
            starts = sorted(first + w * WEEK + WEEKDAYS.index(d) * DAY for w in range(self.weeks)
                            for d in self.weekdays)
        else:
            # sessions start in the training weeks: every_days apart, the first at the lead-in's end
            starts = [first + k * self.every_days * DAY for k in range(self.count())]
        return Protocol(tuple(Session(s, self.duration, self.intensity) for s in starts),
                        stop if end is None else end, name)


def repeat_from_table(table, where: str) -> Repeat:
    """A `Repeat` from a TOML table (a protocol's ``[repeat]``); messages start with ``where``."""
    if not isinstance(table, dict):
        raise InputError(f"{where}: expected a table of {', '.join(REPEAT_KEYS)}, got {table!r}")
    unknown = sorted(set(table) - set(REPEAT_KEYS))
    if unknown:
        raise InputError(f"{where}: unknown key(s) {', '.join(unknown)}; known: {', '.join(REPEAT_KEYS)}")
    missing = [k for k in ("duration", "intensity", "weeks") if k not in table]
    if missing:
        raise InputError(f"{where}: missing {', '.join(missing)}")
    weekdays = table.get("weekdays", [])
    if not isinstance(weekdays, list) or not all(isinstance(d, str) for d in weekdays):
        raise InputError(f"{where}: weekdays: expected an array of day names ({', '.join(WEEKDAYS)}), "
                         f"got {weekdays!r}")
    weeks = as_int(table["weeks"], f"{where}: weeks", 1, int(MAX_END / WEEK))
    every = table.get("every_days")
    try:
        return Repeat(as_float(table["duration"], f"{where}: duration"),
                      as_float(table["intensity"], f"{where}: intensity"), weeks, tuple(weekdays),
                      None if every is None else as_float(every, f"{where}: every_days"),
                      as_float(table.get("lead_in_days", 0.0), f"{where}: lead_in_days"))
    except InputError as err:
        raise InputError(f"{where}: {err}") from None


PROTOCOL_KEYS = ("end", "name", "repeat", "session")


def from_table(data: dict, where: str, name: str) -> Protocol:
    """A protocol from a TOML table: optional ``name`` (else ``name``), and either
    ``[[session]]`` tables (``start``, ``duration`` in h, ``intensity``) with ``end`` (h), or a
    ``[repeat]`` rule (`Repeat`) with an optional ``end``. Unknown keys are an error;
    messages start with ``where``."""
    unknown = sorted(set(data) - set(PROTOCOL_KEYS))
    if unknown:
        raise InputError(f"{where}: unknown key(s) {', '.join(unknown)}; known: {', '.join(PROTOCOL_KEYS)}")
    name = data.get("name", name)
    if not isinstance(name, str):
        raise InputError(f"{where}: name must be a string, got {name!r}")
    if "repeat" in data and "session" in data:
        raise InputError(f"{where}: give either [[session]] tables or a [repeat] rule, not both")
    end = as_float(data["end"], f"{where}: end") if "end" in data else None
    if "repeat" in data:
        rule = repeat_from_table(data["repeat"], f"{where}: repeat")
        try:
            return rule.protocol(name, end)
        except InputError as err:
            raise InputError(f"{where}: {err}") from None
    if end is None:
        raise InputError(f"{where}: missing 'end' (the end time of the protocol in hours)")
    tables = data.get("session", [])
    if not isinstance(tables, list) or not all(isinstance(t, dict) for t in tables):
        raise InputError(f"{where}: 'session' must be an array of tables ([[session]] blocks)")
    sessions = []
    for i, table in enumerate(tables):
        at = f"{where}: session {i}"
        known = SESSION_KEYS + SESSION_OPTIONAL
        unknown = sorted(set(table) - set(known))
        if unknown:
            raise InputError(f"{at}: unknown key(s) {', '.join(unknown)}; known: {', '.join(known)}")
        missing = [k for k in SESSION_KEYS if k not in table]
        if missing:
            raise InputError(f"{at}: missing {', '.join(missing)}")
        stretch = as_float(table["stretch"], f"{at}: stretch", least=1.0) if "stretch" in table else None
        sessions.append(Session(*(as_float(table[k], f"{at}: {k}") for k in SESSION_KEYS), stretch))
    try:
        return Protocol(tuple(sessions), end, name)
    except InputError as err:
        raise InputError(f"{where}: {err}") from None


def load(path: str | Path) -> Protocol:
    """A protocol from a TOML file (`from_table`); its name defaults to the file's stem."""
    path = Path(path)
    return from_table(read_toml(path), str(path), path.stem)


def resolve(name_or_path: str | Path) -> Protocol:
    """A named protocol, or one loaded from a ``.toml`` file."""
    text = str(name_or_path)
    if text in NAMES:
        return named(text)
    if text.endswith(".toml") or Path(text).is_file():
        return load(text)
    raise InputError(f"unknown protocol {text!r}: give one of {', '.join(NAMES)} or a .toml file")


PAPER = ("mwf", "every3days", "weekly")  # the three protocols of the paper's Figs. 3 and 4


def from_option(value: str, option: str = "--protocol") -> list[Protocol]:
    """The protocols a ``--protocol NAME|FILE`` option names: a built-in protocol, ``all`` for
    the paper's three (``PAPER``), or a TOML protocol file (a value ending in .toml or naming
    an existing file). A bad value is an InputError that names ``option``."""
    if value == "all":
        return [named(name) for name in PAPER]
    if value in NAMES or value.endswith(".toml") or Path(value).is_file():
        return [resolve(value)]
    raise InputError(f"{option}: unknown protocol {value!r}; known: {', '.join(NAMES)}, or 'all' for "
                     f"{' '.join(PAPER)}, or a .toml protocol file")
