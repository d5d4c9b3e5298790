"""Parameters as frozen dataclasses: reading them from TOML and checking them.

Every user-written input goes through here so that a mistake is reported once, with
the file, the field and what was expected, before any heavy work starts.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np


class InputError(ValueError):
    """A user input (file, field or option) is malformed; the message says where and why.

    ``field`` names the dataclass field at fault, so that a command line can say which
    of its options set it (`build`).
    """

    def __init__(self, message: str, *, field: str | None = None):
        super().__init__(message if field is None else f"{field}: {message}")
        self.field = field
        self.reason = message


def build(cls, options: Mapping[str, str], **values):
    """``cls(**values)``, its validation errors naming the option that set the field
    (``options`` maps field names to option names, e.g. growth_dt to --growth-dt)."""
    try:
        return cls(**values)
    except InputError as err:
        if err.field in options:
            raise InputError(f"{options[err.field]}: {err.reason}") from None
        raise


def positive_hours(value: Any, field: str, least: float = 0.0) -> float:
    """A time step or duration: a finite number of hours > 0, and at least ``least`` where
    a smaller one would only take for ever (InputError naming ``field``)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not (finite(value) and value > 0):
        raise InputError(f"expected a finite number of hours > 0, got {shown(value)}", field=field)
    if value < least:
        raise InputError(f"expected at least {least:g} h, got {value:g}", field=field)
    return float(value)


# What a text input may not begin with: the byte order marks of UTF-16 and UTF-32 (a
# spreadsheet's "Unicode text"), which strict UTF-8 would report as a stray byte.
OTHER_ENCODINGS = ((b"\xff\xfe\x00\x00", "UTF-32"), (b"\x00\x00\xfe\xff", "UTF-32"),
                   (b"\xff\xfe", "UTF-16"), (b"\xfe\xff", "UTF-16"))


def input_file(path: str | Path, what: str) -> Path:
    """``path`` as a Path where it is a file; an InputError where it is a folder (not
    ``what``, e.g. "a CSV file") or missing."""
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not {what}")
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    return path


def read_text(path: str | Path, what: str = "text file") -> str:
    """The text of a user's input file (CSV, TOML, XDMF, template), decoded as UTF-8.

    Every reader of a text input goes through here, so that a binary file, a UTF-16 export
    or a stray byte is one InputError naming the file and the byte offset, never a
    UnicodeDecodeError deep in a parser. A UTF-8 byte order mark is dropped (spreadsheets
    write one); a NUL byte means a binary file, which no text format here allows.
    """
    path = input_file(path, f"a {what}")
    try:
        data = path.read_bytes()
    except OSError as err:
        raise InputError(f"{path}: cannot read: {err.strerror or err}") from None
    for mark, encoding in OTHER_ENCODINGS:
        if data.startswith(mark):
            raise InputError(f"{path}: {encoding} text (a byte order mark at byte 0); save it as UTF-8")
    body = data.removeprefix(b"\xef\xbb\xbf")
    start = len(data) - len(body)  # the offsets reported count the file's bytes, the mark's too
    nul = body.find(b"\0")
    if nul >= 0:
        raise InputError(f"{path}: not text: a NUL byte at byte offset {start + nul} "
                         "(a binary file, or UTF-16 text without a byte order mark?)")
    try:
        return body.decode("utf-8")
    except UnicodeDecodeError as err:
        raise InputError(f"{path}: not UTF-8 text: byte 0x{body[err.start]:02x} at byte offset "
                         f"{start + err.start} ({err.reason})") from None


def read_toml(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    text = read_text(path, "TOML file")
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise InputError(f"{path}: malformed TOML: {err}") from None
    except ValueError as err:  # tomllib's int() of an integer past Python's 4300 digits
        raise InputError(f"{path}: a number too long to read: {err}") from None


# The numeric reader. Every number a user writes (a TOML key, an option's text) is read by
# `as_float` / `as_int` (`float_text` / `int_text` for text): finite, representable as a
# float64 or an int64 (what numpy and HDF5 attributes store), and inside the field's range,
# so that no OverflowError, NaN or unstorable value gets past the place where it is read.
INT64 = 2**63  # int64 holds [-INT64, INT64)
# Seeds: numpy's SeedSequence takes any size, but SALib and the legacy numpy seeding take
# 32 bits, and every seed is stored as an HDF5 attribute; one bound for every job.
SEED_MAX = 2**32 - 1
SHOWN = 40  # characters of a bad value shown in a message


def shown(value: Any) -> str:
    """A bad value as a message shows it: a huge integer by its length, long text cut."""
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) >= 10**SHOWN:
        try:
            return f"an integer of {len(str(abs(value)))} digits"
        except ValueError:  # str() refuses past 4300 digits
            return "an integer of more than 4300 digits"
    if isinstance(value, float):
        return f"{value:g}"
    text = repr(value)
    return text if len(text) <= SHOWN else f"{text[:SHOWN]}… ({len(text)} characters)"


def finite(value) -> bool:
    """math.isfinite without its OverflowError on an integer too large for a float."""
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def _range(least, most, above, below) -> str:
    """' >= 0', ' in [0, 1)', ' > 0' … of the bounds given."""
    low = (f"[{least:g}" if least is not None else f"({above:g}" if above is not None else None)
    high = (f"{most:g}]" if most is not None else f"{below:g})" if below is not None else None)
    if low is not None and high is not None:
        return f" in {low}, {high}"
    if low is not None:
        return f" {'>=' if least is not None else '>'} {low[1:]}"
    if high is not None:
        return f" {'<=' if most is not None else '<'} {high[:-1]}"
    return ""


def as_float(value: Any, where: str, least: float | None = None, most: float | None = None, *,
             above: float | None = None, below: float | None = None) -> float:
    """A finite real number (ints are accepted, booleans and strings are not) within the
    given bounds (``least``/``most`` inclusive, ``above``/``below`` exclusive); InputError
    naming ``where`` (its ``field``), so `build` can name the option that set it."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise InputError(f"expected a number, got {shown(value)}", field=where)
    if not finite(value):
        raise InputError(f"expected a finite number, got {shown(value)}", field=where)
    value = float(value)
    if ((least is not None and value < least) or (most is not None and value > most)
            or (above is not None and value <= above) or (below is not None and value >= below)):
        raise InputError(f"expected a number{_range(least, most, above, below)}, got {value:g}", field=where)
    return value


def as_int(value: Any, where: str, least: int | None = None, most: int | None = None) -> int:
    """An integer (not a boolean, not a float) in [least, most] and in int64; InputError naming ``where``."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise InputError(f"expected an integer, got {value!r}" if isinstance(value, float)
                         else f"expected an integer, got {shown(value)}", field=where)
    value = int(value)
    if (least is not None and value < least) or (most is not None and value > most):
        bounds = f">= {least}" if most is None else f"<= {most}" if least is None else f"in [{least}, {most}]"
        raise InputError(f"expected an integer {bounds}, got {shown(value)}", field=where)
    if not -INT64 <= value < INT64:
        raise InputError(f"expected an integer that fits in 64 bits, got {shown(value)}", field=where)
    return value


def as_seed(value: Any, where: str) -> int:
    """A random seed: an integer in [0, SEED_MAX]."""
    return as_int(value, where, 0, SEED_MAX)


def float_text(text: str, where: str, least: float | None = None, most: float | None = None, *,
               above: float | None = None, below: float | None = None) -> float:
    """`as_float` of an option's text ("1e400" and "nan" parse, and are refused here)."""
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"expected a number, got {shown(text)}", field=where) from None
    if not finite(value):  # "1e400" parses as inf: show what was typed
        raise InputError(f"expected a finite number, got {shown(text)}", field=where)
    return as_float(value, where, least, most, above=above, below=below)


def int_text(text: str, where: str, least: int | None = None, most: int | None = None) -> int:
    """`as_int` of an option's text (a decimal integer; "2.5" and "1e3" are not)."""
    try:
        value = int(text)
    except ValueError:  # also past Python's 4300 digits
        raise InputError(f"expected an integer, got {shown(text)}", field=where) from None
    return as_int(value, where, least, most)


def as_vector(values, where: str) -> tuple[float, float, float]:
    """A direction: three finite numbers, not all zero, scaled to unit length."""
    values = list(values)
    if len(values) != 3:
        raise InputError(f"expected 3 components, got {len(values)}", field=where)
    v = np.array([as_float(x, where) for x in values])
    if not v.any():
        raise InputError("expected a nonzero direction, got 0 0 0", field=where)
    with np.errstate(over="ignore", under="ignore"):
        norm = float(np.linalg.norm(v))
    if not (math.isfinite(norm) and norm > 0):  # 1e200 components overflow it, 1e-200 underflow: scale first
        v = v / np.abs(v).max()
        norm = float(np.linalg.norm(v))
    return tuple(float(x) for x in v / norm)


def replace_from_mapping(base, values: Mapping[str, Any], source: str):
    """`base` with the fields named in `values` replaced; unknown keys are an error.

    Numbers are checked here; the dataclass's own ``__post_init__`` checks ranges.
    """
    names = {f.name for f in dataclasses.fields(base)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise InputError(
            f"{source}: unknown parameter(s) {', '.join(unknown)}; "
            f"known: {', '.join(sorted(names))}"
        )
    changes = {k: as_float(v, f"{source}: {k}") for k, v in values.items()}
    try:
        return dataclasses.replace(base, **changes)
    except InputError as err:
        raise InputError(f"{source}: {err}") from None


def load_params(cls, path: str | Path | None = None, **overrides):
    """Default parameters of ``cls``, overridden by a TOML file and then by keywords."""
    params = cls()
    if path is not None:
        params = replace_from_mapping(params, read_toml(path), str(path))
    if overrides:
        params = replace_from_mapping(params, overrides, "overrides")
    return params


def check_positive(obj, *names: str) -> None:
    """Raise InputError unless every named field is finite and > 0 (arrays: elementwise)."""

    for name in names:
        v = np.asarray(getattr(obj, name), dtype=float)
        if not (np.all(np.isfinite(v)) and np.all(v > 0)):
            raise InputError(f"{name} must be a finite positive number, got {getattr(obj, name)!r}")


def as_attributes(obj) -> dict[str, Any]:
    """The fields of a parameter dataclass, for HDF5 attributes (scalars only)."""
    return {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}
