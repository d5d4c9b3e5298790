"""Figures: one place that picks matplotlib's file backend and saves atomically.

Jobs run on clusters without a screen, so the backend is Agg, chosen here once,
before pyplot is first imported; `save` writes through `hyper.core.io.atomic_path`, so a
killed job never leaves half a PNG that looks whole.
"""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np

from hyper.core import io

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
    path = Path(path)
    with io.atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".") or "png")
    pyplot().close(fig)
    return path


def growth_series(results: dict[str, dict], path: str | Path, data=(), errors=None, title: str = "") -> Path:
    """CSA, volume and kM against time for several protocols (the paper's Fig. 4C–E),
    with measured CSA courses (``data``: `hyper.runs.measured.Measured`) and each protocol's
    RMSE against them (``errors``: protocol -> `hyper.runs.measured.Comparison`) where given;
    ``title`` says what ran (geometry, fibres, protocols, CSA measure). Where a run grew along
    its fibres (its ``fiber_stretch`` series) a fourth panel shows the fascicle length change."""
    plt = pyplot()
    fibre = [name for name, s in results.items() if "fiber_stretch" in s]
    fig, axes = plt.subplots(1, 3 + bool(fibre), figsize=(13 + 4 * bool(fibre), 3.8), constrained_layout=True)
    end = 0.0
    for name, s in results.items():
        weeks = s["t"] / 168.0
        end = max(end, float(weeks[-1]))
        colour = protocol_colour(name)
        error = (errors or {}).get(name)
        label = name if error is None else f"{name} (RMSE {error.rmse_pp:.2f} pp)"
        axes[0].plot(weeks, 100 * (s["csa_ratio"] - 1), label=label, color=colour)
        axes[1].plot(weeks, 100 * (s["volume_ratio"] - 1), label=name, color=colour)
        axes[2].plot(weeks, s["kM"], label=name, color=colour)
        if name in fibre:
            axes[3].plot(weeks, 100 * (np.asarray(s["fiber_stretch"]) - 1), label=name, color=colour)
    for i, measured in enumerate(data):
        muscle = getattr(measured, "muscle", None)
        axes[0].plot(measured.t / 168.0, 100 * (measured.csa_ratio - 1), "k" + "osD^v"[i % 5], ms=4, mfc="none",
                     label=measured.label if muscle is None else f"{measured.label} ({muscle})")
        end = max(end, float(max(measured.t)) / 168.0)
    for ax in axes:  # one time range in the three panels, with room for the end points
        ax.set_xlim(-0.02 * end, 1.02 * end)
    axes[0].set_ylabel("CSA change (%)")
    axes[1].set_ylabel("volume change (%)")
    axes[2].set_ylabel("kM (1/h)")
    if fibre:
        axes[3].set_ylabel("fascicle length change, a0·Ḡ a0 (%)")
    for ax in axes:
        ax.set_xlabel("time (weeks)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=9)
    return save(fig, path)


def box_section(picture: dict, path: str | Path, title: str = "") -> Path:
    """The original code's box measure on a muscle (`hyper.fem.boxsection.BoxSection.picture`):
    the staircase facets, inner or rim, with the exact cut's outline (left), and each
    facet's deformed / reference area (right)."""
    from matplotlib import colors
    from matplotlib.collections import LineCollection, PolyCollection

    plt = pyplot()
    tri, inner, ratio = picture["triangles"] * 1e2, picture["inner"], picture["ratio"]  # cm
    outline = picture["outline"] * 1e2
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    a_in, a_rim = area[inner].sum(), area[~inner].sum()

    def mean(part):
        return float(ratio[part] @ area[part] / area[part].sum()) if part.any() else float("nan")

    fig, axes = plt.subplots(1, 2, figsize=(12, 5.2), layout="constrained")
    colours = np.where(inner[:, None], colors.to_rgba_array("tab:blue"), colors.to_rgba_array("tab:orange"))
    axes[0].add_collection(PolyCollection(tri, facecolors=colours, edgecolors="white", linewidths=0.3))
    axes[0].set_title(f"staircase {a_in + a_rim:.3f} cm²: inner {a_in:.3f} cm² (blue), rim {a_rim:.3f} cm² (orange)",
                      fontsize=10)
    # a few rim facets read far off (down to J < 0): the scale is set by the bulk
    spread = max(float(np.percentile(np.abs(ratio - 1), 90)), 2 * abs(mean(inner) - 1), 1e-6)
    norm = colors.Normalize(1.0 - spread, 1.0 + spread)
    faces = PolyCollection(tri, array=ratio, cmap="RdBu_r", norm=norm, edgecolors="0.6", linewidths=0.2)
    axes[1].add_collection(faces)
    fig.colorbar(faces, ax=axes[1], extend="both", label="deformed / reference area of the facet")
    axes[1].set_title(f"reads {100 * (mean(np.ones_like(inner)) - 1):+.2f} %: inner {100 * (mean(inner) - 1):+.2f} %, "
                      f"rim {100 * (mean(~inner) - 1):+.2f} %", fontsize=10)
    for ax in axes:
        ax.add_collection(LineCollection(outline, colors="k", linewidths=1.0, label="exact cut"))
        ax.set_aspect("equal")
        ax.autoscale_view()
        ax.set_xlabel("second principal axis (cm)")
        ax.set_ylabel("third principal axis (cm)")
    axes[0].legend(loc="upper right", fontsize=8)
    if title:
        fig.suptitle(title)
    return save(fig, path)
