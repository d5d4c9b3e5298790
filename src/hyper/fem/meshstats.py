"""Statistics of the anatomical meshes: size, volume, reference cross-section, length.

``hyper meshstats --output results/meshes/stats.csv`` writes one row per mesh,

    geometry,muscle,subject,side,cells,vertices,volume_cm3,csa0_cm2,length_cm

and a figure like the paper's Fig. 5B next to it (same name, .png): volume and CSA0 per
muscle, subject and side, with the group means. Definitions (MODEL.md §4):

- volume: the integral of 1 over the mesh;
- csa0: the exact area of the cut of the mesh by the plane through the mean of all
  vertices, normal to their first principal axis (``section.principal_plane``,
  ``section.CutSection.area0``);
- length: the extent of the vertices along that axis (max - min of the projections);
- csa_solid, length_solid: the same by the solid's own frame (``section.solid_plane``):
  the plane through the centroid of the volume, normal to its principal axis of inertia.
  csa0 is what the growth model feeds back (MODEL.md §4), but the vertices' mean and axis
  move with where a mesher puts its vertices (fTetWild's meshes are denser near the
  surface: on the shipped meshes the vertex plane lies 3-39 mm off the centroid and tilts
  0.4-3.2° off the inertia axis), whereas the solid's frame is a property of the shape:
  the shipped meshes and `hyper mesh`'s agree with the STL's own frame to 0.5 mm and 0.15°.
  length_solid still depends on how the mesh rounds the two tips.

Every quantity counts each vertex and cell once, whatever the number of ranks; rank 0
writes. The paper's group means of the volume (Devold et al. 2026, Discussion) are
checked and printed.
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np

from hyper.commands import cli
from hyper.core.log import info
from hyper.core.params import InputError
from hyper.fem import geometry as geo
from hyper.fem import section
from hyper.runs.plot import pyplot

COLUMNS = ("geometry", "muscle", "subject", "side", "cells", "vertices", "volume_cm3", "csa0_cm2", "length_cm",
           "csa_solid_cm2", "length_solid_cm")
# Group means of the initial volumes (cm³) as the paper reports them, to 0.1 cm³.
PAPER_VOLUME_CM3 = {"BFLH": 252.4, "ST": 190.1, "TA": 132.4}
PAPER_DECIMALS = 1


def statistics(geometry: geo.Geometry) -> dict:
    """One row of the table for a loaded geometry (in metres); collective."""
    mesh = geometry.mesh
    points = section.global_vertices(mesh)
    origin, normal = section.principal_plane(points)
    along = section.signed_distance(points, origin, normal)
    row = {"geometry": geometry.name}
    if geometry.name in geo.ANATOMICAL:
        row.update(zip(("muscle", "subject", "side"), geo.split_id(geometry.name)))
    row.update(
        cells=geometry.num_cells(),
        vertices=len(points),
        volume_cm3=geometry.reference_volume() * 1e6,
        csa0_cm2=section.CutSection(mesh, origin, normal).area0() * 1e4,
        length_cm=float(along.max() - along.min()) * 1e2,
    )
    origin, normal = section.solid_plane(mesh)
    along = section.signed_distance(points, origin, normal)
    row.update(csa_solid_cm2=section.CutSection(mesh, origin, normal).area0() * 1e4,
               length_solid_cm=float(along.max() - along.min()) * 1e2)
    return row


def group_means(rows, column: str = "volume_cm3") -> dict[str, float]:
    """Mean of ``column`` per muscle, in the order of geometry.MUSCLES."""
    means = {}
    for muscle in geo.MUSCLES:
        values = [row[column] for row in rows if row.get("muscle") == muscle]
        if values:
            means[muscle] = float(np.mean(values))
    return means


def matching_digits(value: float, reference: float) -> int:
    """How many significant digits of ``reference`` ``value`` reproduces when rounded
    to as many digits (0 if not even the first)."""
    digits = 0
    for n in range(1, 16):
        scale = 10.0 ** (np.floor(np.log10(abs(reference))) - n + 1)
        if round(value / scale) * scale != round(reference / scale) * scale:
            break
        digits = n
    return digits


def figure(rows):
    """Bar charts of volume and CSA0 per muscle, one bar per subject and side, with the
    group means as lines (the analogue of the paper's Fig. 5B)."""
    plt = pyplot()
    muscles = [m for m in geo.MUSCLES if any(r.get("muscle") == m for r in rows)]
    members = [("VHF", "Left"), ("VHF", "Right"), ("VHM", "Left"), ("VHM", "Right")]
    colours = {"VHF": ("#c0392b", "#e6958d"), "VHM": ("#1f5f99", "#8fb3d6")}
    width = 0.2
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), layout="constrained")
    for ax, column, label in ((axes[0], "volume_cm3", "volume (cm³)"), (axes[1], "csa0_cm2", "CSA0 (cm²)")):
        means = group_means(rows, column)
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
            if column == "volume_cm3" and muscle in PAPER_VOLUME_CM3:
                ax.plot(i, PAPER_VOLUME_CM3[muscle], "k*", ms=7,
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
    from hyper.core.io import atomic_path
    from hyper.runs import plot

    unknown = [g for g in args.geometries if g not in geo.GEOMETRIES]
    if unknown:
        raise InputError(f"--geometries: unknown {', '.join(unknown)}; known: {', '.join(geo.GEOMETRIES)}")
    rows = [statistics(geo.load(name, comm, meshes_dir=args.meshes_dir)) for name in args.geometries]
    if comm.rank == 0:
        with atomic_path(args.output) as tmp, open(tmp, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=COLUMNS, restval="")
            writer.writeheader()
            for row in rows:
                writer.writerow({k: (f"{v:.12g}" if isinstance(v, float) else v) for k, v in row.items()})
        png = plot.save(figure(rows), args.output.with_suffix(".png"), dpi=130)

        info(comm, f"{'geometry':<16} {'cells':>6} {'vertices':>8} {'volume cm³':>11} {'CSA0 cm²':>9} {'length cm':>9}")
        for row in rows:
            info(comm, f"{row['geometry']:<16} {row['cells']:>6d} {row['vertices']:>8d} {row['volume_cm3']:>11.3f} "
                       f"{row['csa0_cm2']:>9.3f} {row['length_cm']:>9.3f}")
        csa = group_means(rows, "csa0_cm2")
        for muscle, mean in group_means(rows).items():
            paper = PAPER_VOLUME_CM3[muscle]
            n = sum(r.get("muscle") == muscle for r in rows)
            ok = round(mean, PAPER_DECIMALS) == paper
            info(comm, f"{muscle:<5} mean of {n}: volume {mean:.4f} cm³ (paper {paper:.1f}: "
                       f"{'matches' if ok else 'DIFFERS'}, {matching_digits(mean, paper)} significant digits), "
                       f"CSA0 {csa[muscle]:.3f} cm²")
        info(comm, f"wrote {args.output} and {png}")
    return cli.EXIT_OK


main = cli.entry(parser, run, locks=lambda args: [args.output])

if __name__ == "__main__":
    sys.exit(main())
