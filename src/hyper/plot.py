"""Figures: one place that picks matplotlib's file backend and saves atomically.

Jobs run on clusters without a screen, so the backend is Agg, chosen here once,
before pyplot is first imported; `save` writes through `hyper.io.atomic_path`, so a
killed job never leaves half a PNG that looks whole.
"""

from __future__ import annotations

from pathlib import Path


def pyplot():
    """matplotlib.pyplot on the Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig, path: str | Path, *, dpi: int = 150) -> Path:
    """Write ``fig`` to ``path`` (format from its suffix) atomically and close it."""
    from hyper import io

    path = Path(path)
    with io.atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".") or "png")
    pyplot().close(fig)
    return path
