# ruff: noqa: E501
# (the chart of docs/convergence.md, "Laplace fibres"; kept to redraw it, not as library code)
"""Stokes against Laplace fibres at hyper mesh's 8000 cells, per muscle: the fibres' 95th
percentile angle to the finest level of the study, and the CSA gain's estimated spatial error
(`python -m hyper.bench convergence --spatial-table`'s numbers: the largest of the CSA,
volume and mechanics' errors). From the kept `--all` studies; run from the repository root:

    python jobs/laplace_chart.py --stokes results/bench/convergence_full results/bench/convergence_32k results/bench/convergence_64k --laplace results/bench/convergence_laplace --output docs/laplace-fibres.png
"""
import argparse
from pathlib import Path

import numpy as np

from hyper.commands.bench import convergence as cv
from hyper.fem import meshing as hm
from hyper.runs import plot

p = argparse.ArgumentParser()
p.add_argument("--stokes", type=Path, nargs="+", required=True)
p.add_argument("--laplace", type=Path, nargs="+", required=True)
p.add_argument("--output", type=Path, required=True)
a = p.parse_args()
rows = {kind: {r["muscle"]: r for r in cv.spatial_rows(folders, hm.DEFAULT_CELLS)}
        for kind, folders in (("Stokes", a.stokes), ("Laplace", a.laplace))}
muscles = sorted(rows["Stokes"])
plt = plot.pyplot()
fig, axes = plt.subplots(2, 1, figsize=(13, 7.5), sharex=True, layout="constrained")
x = np.arange(len(muscles))
for k, (kind, colour) in enumerate((("Stokes", "0.55"), ("Laplace", "C0"))):
    got = rows[kind]
    angle = [got[m]["fibre_p95_deg"] if m in got else np.nan for m in muscles]
    error = [cv.spatial_error(got[m]) if m in got else np.nan for m in muscles]
    axes[0].bar(x + (k - 0.5) * 0.4, angle, 0.4, color=colour, label=f"{kind} fibres")
    axes[1].bar(x + (k - 0.5) * 0.4, error, 0.4, color=colour, label=f"{kind} fibres")
    print(f"{kind}: {sum(np.nan_to_num(angle, nan=99) <= cv.FIBRES_GOAL_DEG)} of {len(got)} within "
          f"{cv.FIBRES_GOAL_DEG:g} deg, {sum(np.nan_to_num(error, nan=1) <= cv.GROWTH_GOAL)} of {len(got)} within "
          f"{cv.GROWTH_GOAL:g} of the growth")
axes[0].axhline(cv.FIBRES_GOAL_DEG, color="C3", lw=1, ls="--", label=f"goal {cv.FIBRES_GOAL_DEG:g}°")
axes[0].set_ylabel("fibres at 8k cells: p95 angle\nto the study's finest level (°)")
axes[1].axhline(cv.GROWTH_GOAL, color="C3", lw=1, ls="--", label=f"goal {cv.GROWTH_GOAL:g} of the growth")
axes[1].set_yscale("log")
axes[1].set_ylabel("CSA and volume gains at 8k cells:\nestimated error (of the growth)")
axes[1].set_xticks(x, muscles, rotation=60, ha="right", fontsize=8)
for ax in axes:
    ax.legend(fontsize=8, loc="upper left")
axes[0].set_title("Stokes against Laplace fibres at hyper mesh's 8000 cells (missing bar: no study)", fontsize=10)
plot.save(fig, a.output, dpi=110)
print(f"wrote {a.output}")
