"""The figures of ``hyper reproduce``: the cohort's CSA and volume changes by both
columns (Fig. 6C–D analog), the box measure's facets on BFLH_VHF_Left and the idealized
mwf runs against the measured data."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hyper.analysis.reproduce import BOX_FIGURE_GEOMETRY, ORIGINAL_GROWTH_DT, PAPER_MWF, series_path
from hyper.analysis.reproducereport import cohort_rows, get
from hyper.core import io
from hyper.model import protocols
from hyper.runs import measured, plot


def cohort_figure(data: dict, path: Path) -> Path | None:
    """Fig. 6C–D analog: per muscle, CSA by the cut and by the box and volume, default and original side by side."""
    orig, dflt = cohort_rows(data, "original"), cohort_rows(data, "default")
    names = sorted(set(orig) | set(dflt))
    if not names:
        return None
    plt = plot.pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(max(8, 1.1 * len(names) + 4), 4.4), layout="constrained")
    bars = (
        ("default, cut", dflt, "csa_cut", "tab:blue"),
        ("default, box", dflt, "csa_box", "lightsteelblue"),
        ("original, cut", orig, "csa_cut", "tab:red"),
        ("original, box", orig, "csa_box", "salmon"),
    )
    x = np.arange(len(names))
    for j, (label, col, key, colour) in enumerate(bars):
        axes[0].bar(
            x + (j - 1.5) * 0.2, [get(col.get(g), key) or np.nan for g in names], 0.18, label=label, color=colour
        )
    for j, (label, col, colour) in enumerate((("default", dflt, "tab:blue"), ("original", orig, "tab:red"))):
        axes[1].bar(
            x + (j - 0.5) * 0.3, [get(col.get(g), "volume") or np.nan for g in names], 0.28, label=label, color=colour
        )
    for ax, quantity, title in ((axes[0], "csa", "mid-belly CSA, both measures"), (axes[1], "volume", "volume")):
        lo, hi = PAPER_MWF[quantity]
        ax.axhspan(lo, hi, color="0.85", zorder=0, label="paper, mwf")
        ax.set_xticks(x, names, rotation=45, ha="right", fontsize=8)
        ax.set_ylabel(f"{title} change (%)")
        ax.grid(axis="y", alpha=0.3)
        ax.set_ylim(0.0, 1.4 * ax.get_ylim()[1])  # room above the bars for the legend
        ax.legend(fontsize=7, ncol=3, loc="upper center")
    fig.suptitle("cohort under mwf, 9 weeks: hyper's default and the original code's switches")
    plot.save(fig, path, dpi=130)
    plt.close(fig)
    return path


def box_figure(output: Path, path: Path) -> Path | None:
    saved = output / "runs" / f"{BOX_FIGURE_GEOMETRY}_mwf_original_box.npz"
    if not saved.is_file():
        return None
    with np.load(saved) as f:
        picture = {k: f[k] for k in f.files}
    picture.setdefault("outline", np.empty((0, 2, 2)))
    return plot.box_section(
        picture,
        path,
        f"{BOX_FIGURE_GEOMETRY}, mwf, 9 weeks, the original's switches: the box measure's inner and rim facets",
    )


def idealized_figure(output: Path, path: Path, quick: bool) -> Path | None:
    dt = ORIGINAL_GROWTH_DT  # the original column's step, in --quick too
    # each curve says its growth step: the original's own 1 h, the default's one per period
    files = {
        "default (Δtg = 168 h)": series_path(output, "idealized_mwf_default"),
        f"original (Δtg = {dt:g} h)": series_path(output, f"idealized_mwf_original_dt{dt:g}"),
    }
    results = {name: io.read_series(p) for name, p in files.items() if io.is_complete(p)}
    data = measured.of_protocol(protocols.named("mwf"), "idealized")
    title = "idealized, fibres auto, mwf (default and the original's switches); CSA of its tagged mid-section"
    return plot.growth_series(results, path, [data] if data else [], title=title) if results else None
