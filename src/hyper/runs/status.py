"""Status files: why an unfinished run stopped, and how to resume it (``RESULT.status.json``)."""

from __future__ import annotations

import datetime
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from hyper.core import io
from hyper.runs.checkpoint import plain


def write_status(path: Path, status: Mapping[str, Any]) -> None:
    """A JSON status file, written atomically (call on one rank)."""
    text = json.dumps(plain({**status, "written": datetime.datetime.now(datetime.UTC).isoformat()}), indent=2)
    with io.atomic_path(path) as tmp:
        tmp.write_text(text + "\n")


def read_status(path: Path) -> dict:
    return json.loads(Path(path).read_text())
