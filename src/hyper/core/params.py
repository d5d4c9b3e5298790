"""Parameters as frozen dataclasses: reading them from TOML and checking them.

Every user-written input goes through here so that a mistake is reported once, with
the file, the field and what was expected, before any heavy work starts.
"""

from __future__ import annotations

import dataclasses
import math
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
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
        shown = f"{value:g}" if isinstance(value, (int, float)) and not isinstance(value, bool) else repr(value)
        raise InputError(f"expected a finite number of hours > 0, got {shown}", field=field)
    if value < least:
        raise InputError(f"expected at least {least:g} h, got {value:g}", field=field)
    return float(value)


# What a text input may not begin with: the byte order marks of UTF-16 and UTF-32 (a
# spreadsheet's "Unicode text"), which strict UTF-8 would report as a stray byte.
OTHER_ENCODINGS = ((b"\xff\xfe\x00\x00", "UTF-32"), (b"\x00\x00\xfe\xff", "UTF-32"),
                   (b"\xff\xfe", "UTF-16"), (b"\xfe\xff", "UTF-16"))


def read_text(path: str | Path, what: str = "text file") -> str:
    """The text of a user's input file (CSV, TOML, XDMF, template), decoded as UTF-8.

    Every reader of a text input goes through here, so that a binary file, a UTF-16 export
    or a stray byte is one InputError naming the file and the byte offset, never a
    UnicodeDecodeError deep in a parser. A UTF-8 byte order mark is dropped (spreadsheets
    write one); a NUL byte means a binary file, which no text format here allows.
    """
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a {what}")
    if not path.is_file():
        raise InputError(f"{path}: no such file")
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


def as_float(value: Any, where: str) -> float:
    """A finite real number from TOML (ints are accepted, booleans and strings are not)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{where}: expected a number, got {value!r}")
    try:
        value = float(value)
    except OverflowError:  # an integer of hundreds of digits
        raise InputError(f"{where}: expected a finite number, got an integer of {len(str(value))} digits") from None
    if not math.isfinite(value):
        raise InputError(f"{where}: expected a finite number, got {value!r}")
    return value


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
