"""Figures: one place that picks matplotlib's file backend and saves atomically.

Jobs run on clusters without a screen, so the backend is Agg, chosen here once,
before pyplot is first imported; `save` writes through `hyper.io.atomic_path`, so a
killed job never leaves half a PNG that looks whole.
"""

from __future__ import annotations

import zlib
from pathlib import Path

# One colour per protocol name in every figure (signaling, growth, cohort): the built-in
# protocols their own, any other name one of OTHER_COLOURS picked by the name itself, not
# by its place in a figure (two such names may share one).
PROTOCOL_COLOURS = {"mwf": "#c0392b", "every3days": "#2471a3", "weekly": "#229954", "daily15": "#8e44ad",
                    "rest": "#555555"}
OTHER_COLOURS = ("#d35400", "#17a589", "#b7950b", "#2e4053", "#a04000", "#1f618d", "#7b241c", "#6c3483")


def protocol_colour(name: str) -> str:
    return PROTOCOL_COLOURS.get(name) or OTHER_COLOURS[zlib.crc32(name.encode()) % len(OTHER_COLOURS)]


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


def growth_series(results: dict[str, dict], path: str | Path, data: Path | None = None) -> Path:
    """CSA, volume and kM against time for several protocols (the paper's Fig. 4C–E),
    with DeFreitas et al.'s CSA (``data``: their CSV) where given."""
    import numpy as np

    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8), constrained_layout=True)
    end = 0.0
    for name, s in results.items():
        weeks = s["t"] / 168.0
        end = max(end, float(weeks[-1]))
        colour = protocol_colour(name)
        axes[0].plot(weeks, 100 * (s["csa_ratio"] - 1), label=name, color=colour)
        axes[1].plot(weeks, 100 * (s["volume_ratio"] - 1), label=name, color=colour)
        axes[2].plot(weeks, s["kM"], label=name, color=colour)
    if data is not None and data.is_file():
        measured = np.genfromtxt(data, delimiter=",", names=True)
        axes[0].plot(measured["week"], 100 * (measured["csa"] / measured["csa"][0] - 1), "ko", ms=4,
                     label="DeFreitas 2011 (mwf)")
        end = max(end, float(np.max(measured["week"])))
    for ax in axes:  # one time range in the three panels, with room for the end points
        ax.set_xlim(-0.02 * end, 1.02 * end)
    axes[0].set_ylabel("CSA change (%)")
    axes[1].set_ylabel("volume change (%)")
    axes[2].set_ylabel("kM (1/h)")
    for ax in axes:
        ax.set_xlabel("time (weeks)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    return save(fig, path)
