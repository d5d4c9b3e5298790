"""``hyper meshstats``: the table of `hyper.fem.meshstats` for the anatomical meshes.

``hyper meshstats --output results/meshes/stats.csv`` writes one row per mesh (columns
`hyper.fem.meshstats.COLUMNS`) and a figure like the paper's Fig. 5B next to it (same
name, .png): volume and CSA0 per muscle, subject and side, with the group means. Rank 0
writes; the paper's group means of the volume are checked and printed.
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

from hyper.commands import cli
from hyper.core.io import atomic_path
from hyper.core.log import info
from hyper.core.params import InputError
from hyper.fem import geometry as geo
from hyper.fem import meshstats
from hyper.runs import plot


def figure(rows):
    """Bar charts of volume and CSA0 per muscle, one bar per subject and side, with the
    group means as lines (the analogue of the paper's Fig. 5B)."""
    plt = plot.pyplot()
    muscles = [m for m in geo.MUSCLES if any(r.get("muscle") == m for r in rows)]
    members = [("VHF", "Left"), ("VHF", "Right"), ("VHM", "Left"), ("VHM", "Right")]
    colours = {"VHF": ("#c0392b", "#e6958d"), "VHM": ("#1f5f99", "#8fb3d6")}
    width = 0.2
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), layout="constrained")
    for ax, column, label in ((axes[0], "volume_cm3", "volume (cm³)"), (axes[1], "csa0_cm2", "CSA0 (cm²)")):
        means = meshstats.group_means(rows, column)
        for i, muscle in enumerate(muscles):
            for j, (subject, side) in enumerate(members):
                match = [r for r in rows
                         if (r.get("muscle"), r.get("subject"), r.get("side")) == (muscle, subject, side)]
                if not match:
                    continue
                x = i + (j - 1.5) * width
                colour = colours[subject][0 if side == "Left" else 1]
                ax.bar(x, match[0][column], width * 0.92, color=colour,
                       label=f"{subject[2]} {side[0]}" if i == 0 else None)
            ax.hlines(means[muscle], i - 2 * width, i + 2 * width, colors="k", linestyles="--")
            ax.annotate(f"{means[muscle]:.1f}", (i + 2 * width, means[muscle]), xytext=(2, 2),
                        textcoords="offset points", fontsize=8)
            if column == "volume_cm3" and muscle in meshstats.PAPER_VOLUME_CM3:
                ax.plot(i, meshstats.PAPER_VOLUME_CM3[muscle], "k*", ms=7,
                        label="paper's mean" if i == 0 else None)
        ax.set_xticks(range(len(muscles)), muscles)
        ax.set_ylabel(label)
    axes[0].set_title("muscle volume (dashed: group mean)")
    axes[1].set_title("cross-section at the mid-plane (exact cut)")
    axes[0].legend(fontsize=8, ncols=1, title="F/M, left/right", title_fontsize=8)
    return fig


def parser() -> cli.Parser:
    p = cli.Parser("meshstats", description="Cells, vertices, volume, reference cross-section (exact cut) and "
                   "length of the anatomical\nmeshes, with a bar chart like the paper's Fig. 5B.")
    p.add_argument("--output", type=cli.output(folder=False, suffixes=(".csv",)), default="results/meshes/stats.csv",
                   help="CSV file to write; the figure goes next to it as .png")
    p.add_argument("--geometries", nargs="+", metavar="ID", default=list(geo.ANATOMICAL),
                   help="geometries (the 12 anatomical meshes)")
    p.add_argument("--meshes-dir", type=Path, default=geo.MESHES_DIR, help="folder of the meshes")
    return p


def run(comm, args) -> int:
    unknown = [g for g in args.geometries if g not in geo.GEOMETRIES]
    if unknown:
        raise InputError(f"--geometries: unknown {', '.join(unknown)}; known: {', '.join(geo.GEOMETRIES)}")
    rows = [meshstats.statistics(geo.load(name, comm, meshes_dir=args.meshes_dir)) for name in args.geometries]
    if comm.rank == 0:
        with atomic_path(args.output) as tmp, open(tmp, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=meshstats.COLUMNS, restval="")
            writer.writeheader()
            for row in rows:
                writer.writerow({k: (f"{v:.12g}" if isinstance(v, float) else v) for k, v in row.items()})
        png = plot.save(figure(rows), args.output.with_suffix(".png"), dpi=130)

        info(comm, f"{'geometry':<16} {'cells':>6} {'vertices':>8} {'volume cm³':>11} {'CSA0 cm²':>9} {'length cm':>9}")
        for row in rows:
            info(comm, f"{row['geometry']:<16} {row['cells']:>6d} {row['vertices']:>8d} {row['volume_cm3']:>11.3f} "
                       f"{row['csa0_cm2']:>9.3f} {row['length_cm']:>9.3f}")
        csa = meshstats.group_means(rows, "csa0_cm2")
        for muscle, mean in meshstats.group_means(rows).items():
            paper = meshstats.PAPER_VOLUME_CM3[muscle]
            n = sum(r.get("muscle") == muscle for r in rows)
            ok = round(mean, meshstats.PAPER_DECIMALS) == paper
            digits = meshstats.matching_digits(mean, paper)
            info(comm, f"{muscle:<5} mean of {n}: volume {mean:.4f} cm³ (paper {paper:.1f}: "
                       f"{'matches' if ok else 'DIFFERS'}, {digits} significant digits), "
                       f"CSA0 {csa[muscle]:.3f} cm²")
        info(comm, f"wrote {args.output} and {png}")
    return cli.EXIT_OK


main = cli.entry(parser, run, locks=lambda args: [args.output])

if __name__ == "__main__":
    sys.exit(main())
