"""The figures of a Sobol analysis: the bootstrap spread of the indices (the paper's Fig. 3F)
and the indices as bars, coloured by the species a parameter belongs to."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from hyper.analysis.sobol import Indices
from hyper.model.protocols import Protocol
from hyper.runs import plot

# The species a parameter belongs to (the figures' colours). A coupling parameter belongs to
# the species whose equation it sits in; ``SOURCE`` names the species it comes from.
SPECIES = {
    "IGF1": ("a10", "b1"),
    "AKT": ("a20", "b2", "c21"),
    "FOXO": ("a3", "b3", "c32"),
    "mTOR": ("a4", "b4", "c42", "c43"),
    "balance": ("kM", "kF", "thetaM", "thetaF"),
    "feedback": ("hill_n",),
}
SOURCE = {"c21": "IGF1", "c32": "AKT", "c42": "AKT", "c43": "FOXO"}

COLOURS = {"IGF1": "tab:blue", "AKT": "tab:orange", "FOXO": "tab:red", "mTOR": "tab:green", "balance": "tab:purple",
           "feedback": "tab:brown", "other": "tab:gray"}


def species_of(name: str) -> str:
    return next((s for s, names in SPECIES.items() if name in names), "other")


# label placement in figure_spread, in pixels of the figure as drawn (100 dpi): a
# character of an 8 pt label, the room around a label, its height, a marker's radius
LABEL_CHAR_PX, LABEL_PAD_PX, LABEL_HEIGHT_PX, MARKER_PX = 6.0, 6.0, 13.0, 8.0


def label_offsets(points: np.ndarray, sizes, marker: float) -> list[tuple[float, float]]:
    """Offsets (pixels, from its point to its box's lower left corner) of one label per
    point such that no two label boxes overlap and no box covers a point: each label in
    turn takes the first free place on rings of growing radius around its point."""
    points = np.asarray(points, dtype=float)
    boxes: list[tuple[float, float, float, float]] = []

    def free(x0, y0, w, h) -> bool:
        if any(x0 < b[2] and b[0] < x0 + w and y0 < b[3] and b[1] < y0 + h for b in boxes):
            return False
        return not np.any((points[:, 0] > x0 - marker) & (points[:, 0] < x0 + w + marker)
                          & (points[:, 1] > y0 - marker) & (points[:, 1] < y0 + h + marker))

    out = []
    for (x, y), (w, h) in zip(points, sizes):
        choice = None
        for radius in marker * (1.2 + 0.8 * np.arange(15)):
            for angle in np.deg2rad([30, -30, 150, -150, 90, -90, 0, 180, 60, -60, 120, -120]):
                dx, dy = radius * math.cos(angle), radius * math.sin(angle)
                # the box extends from the point's side away from it
                x0 = x + dx - (w if dx < 0 else 0.0)
                y0 = y + dy - (h if dy < 0 else 0.0)
                if free(x0, y0, w, h):
                    choice = (x0 - x, y0 - y, w, h)
                    break
            if choice is not None:
                break
        if choice is None:  # nowhere free: the first place, overlapping
            choice = (marker, marker, w, h)
        boxes.append((x + choice[0], y + choice[1], x + choice[0] + w, y + choice[1] + h))
        out.append(choice[:2])
    return out


def figure_spread(ind: Indices, output: str = "N(480 h)"):
    """The Fig. 3F analog: for each parameter the bootstrap mean of its index against the bootstrap
    standard deviation, first-order and total side by side. Colour: species; a coupling
    parameter is split between its own species and the one it comes from. Labels are
    placed where they overlap no other label and no point (`label_offsets`)."""
    plt = plot.pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6))
    boots = []
    for ax, (label, boot) in zip(axes, (("first-order $S_1$", ind.S1_boot), ("total $S_T$", ind.ST_boot))):
        mean, std = boot.mean(axis=0), boot.std(axis=0, ddof=1)
        for k, name in enumerate(ind.names):
            species = species_of(name)
            alt = SOURCE.get(name)
            ax.plot(mean[k], std[k], "o", ms=10, color=COLOURS[species], markeredgecolor="k",
                    fillstyle="left" if alt else "full", markerfacecoloralt=COLOURS[alt] if alt else "none")
        ax.margins(0.12)  # room for the labels of the outer points
        ax.set_xlabel(f"mean of {label} over the bootstrap")
        ax.set_ylabel("standard deviation over the bootstrap")
        ax.grid(alpha=0.3)
        boots.append((ax, mean, std))
    present = {species_of(n) for n in ind.names}
    handles = [plt.Line2D([], [], marker="o", ls="", color=COLOURS[s], markeredgecolor="k", label=s)
               for s in SPECIES if s in present]
    axes[1].legend(handles=handles, loc="best", fontsize=8, title="species (split: coupling)")
    fig.suptitle(f"Sobol indices of {output}, {ind.base_samples} base samples")
    fig.tight_layout()
    fig.canvas.draw()  # the final limits and layout, so that points map to their pixels
    pt = 72.0 / fig.dpi
    for ax, mean, std in boots:
        points = ax.transData.transform(np.column_stack([mean, std]))
        sizes = [(LABEL_CHAR_PX * len(n) + LABEL_PAD_PX, LABEL_HEIGHT_PX) for n in ind.names]
        for k, (dx, dy) in enumerate(label_offsets(points, sizes, MARKER_PX)):
            far = math.hypot(dx, dy) > 3 * MARKER_PX
            ax.annotate(ind.names[k], (mean[k], std[k]), xytext=(dx * pt, dy * pt),
                        textcoords="offset points", fontsize=8, ha="left", va="bottom",
                        arrowprops={"arrowstyle": "-", "lw": 0.5, "color": "0.4"} if far else None)
    return fig


def figure_bars(ind: Indices, output: str = "N(480 h)"):
    """S1 and ST with their confidence intervals, parameters by decreasing ST."""
    plt = plot.pyplot()
    order = np.argsort(-ind.ST)
    x = np.arange(len(order))
    fig, ax = plt.subplots(figsize=(10, 4.2))
    ax.bar(x - 0.2, ind.S1[order], 0.4, yerr=ind.S1_conf[order], capsize=2, label="$S_1$", color="tab:blue")
    ax.bar(x + 0.2, ind.ST[order], 0.4, yerr=ind.ST_conf[order], capsize=2, label="$S_T$", color="tab:orange")
    ax.set_xticks(x, [ind.names[k] for k in order])
    for tick, k in zip(ax.get_xticklabels(), order):
        tick.set_color(COLOURS[species_of(ind.names[k])])
    ax.set_ylabel("Sobol index")
    ax.axhline(0.0, color="k", lw=0.5)
    ax.legend()
    ax.set_title(f"first-order and total Sobol indices of {output} (bars: 95 % bootstrap intervals)")
    fig.tight_layout()
    return fig



def output_label(function: str, protocol: Protocol | None, at: float | None) -> str:
    """The output's name in the figures' titles: N or the CSA gain at ``at`` h (default: the
    protocol's end) of ``protocol``, or the Ishigami function."""
    at = (protocol.end if at is None else at) if protocol else None
    return {"signaling": f"N({at:g} h, {protocol.name})" if protocol else "",
            "csa-gain": f"the CSA gain at {at:g} h ({protocol.name})" if protocol else "",
            "ishigami": "the Ishigami function"}[function]


FIGURES = (("spread.png", figure_spread), ("indices.png", figure_bars))


def save_figures(ind: Indices, output: str, folder: Path) -> None:
    """Both figures of ``ind`` (the output named ``output``) in ``folder``: spread.png and indices.png."""
    for name, make in FIGURES:
        plot.save(make(ind, output), folder / name, dpi=130)
