"""The pennate fibre generator (`hyper.fem.pennate`) on shipped muscles, against their
Stokes fibres, timed on the ranks it runs on (the issue-34 goal: at most 60 s a muscle on
1 core):

    generator   patches, Laplace solve and nodal fibres (`pennate.compute`), then the
                statistics with the streamlines (`pennate.statistics`): wall and CPU s
    architecture  pennation angle to the line of action and fascicle length (mean,
                5/50/95 %) of the pennate fibres and of the stored Stokes fibres
                (`pennate.stokes_statistics`: streamlines from end to end)
    --growth    the 9-week `mwf` growth with each field (`hyper grow --mesh` on a copy of
                the mesh with the field beside it, --sections 9): CSA and volume gains,
                and the CSA gain at the nine sections along the length, drawn in
                pennate_growth.png: where the muscle grows

The rules (`RULES`): the tibialis anterior bipennate (the generator's default patches), the
gastrocnemius medialis unipennate (from the superficial side of the proximal 80 % to the
deep side of the distal 80 %). Writes results/bench/pennate.json and, with --growth, the
runs under results/bench/pennate/ and pennate_growth.png.

    python -m hyper.bench pennate [--geometries TA_VHF_Left GM_VHF_Left] [--growth]
"""

from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np

from hyper.commands import cli, grow
from hyper.commands import fibers as fibers_job
from hyper.commands.bench import common
from hyper.core import io
from hyper.core.log import info
from hyper.core.params import InputError
from hyper.fem import fibers, pennate
from hyper.fem import geometry as geo
from hyper.runs import plot, runspec

RULES = {
    "TA": (pennate.DEFAULT_ORIGIN, pennate.DEFAULT_INSERTION),
    "GM": ("tags:1 | tags:3 & along:0,0.8 & side:3", "tags:2 | tags:3 & along:0.2,1 & side:-3"),
}
SECTIONS = 9
SHOWN = ("pennation_deg_mean", "pennation_deg_p5", "pennation_deg_p50", "pennation_deg_p95", "fascicle_mm_mean",
         "fascicle_mm_p5", "fascicle_mm_p50", "fascicle_mm_p95", "fascicles", "fascicles_reached_share",
         "share_within_30deg")


def parser() -> cli.Parser:
    p = cli.Parser("bench pennate", __doc__)
    p.add_argument("--geometries", nargs="+", metavar="ID", default=["TA_VHF_Left", "GM_VHF_Left"],
                   help=f"shipped muscles of {', '.join(RULES)}")
    p.add_argument("--output", type=Path, default=Path("results/bench"), help="folder for pennate.json and the runs")
    p.add_argument("--growth", action="store_true", help="also the 9-week mwf growth with each field (about 2 min "
                   "a run on 1 core)")
    return p


def timed(action):
    wall, cpu = time.perf_counter(), time.process_time()
    value = action()
    return value, time.perf_counter() - wall, time.process_time() - cpu


def rule(name: str) -> tuple[str, str]:
    muscle = name.split("_")[0]
    if muscle not in RULES or name not in geo.GEOMETRIES:
        raise InputError(f"--geometries: {name!r} is not a shipped mesh of {', '.join(RULES)}")
    return RULES[muscle]


def growth(comm, args, name: str, origin: str, insertion: str) -> dict:
    """The 9-week mwf run with each field on a copy of the mesh: gains and sections. The
    jobs run without --quiet: each sets up the logging again, and --quiet would silence
    this bench's own lines after it."""
    source = geo.MESHES_DIR / geo.GEOMETRIES[name]
    out = {}
    for field in ("stokes", "pennate"):
        folder = args.output / "pennate" / f"{name}_{field}"
        if comm.rank == 0:
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir(parents=True)
            for path in runspec.mesh_files(source):
                shutil.copy(path, folder / path.name)
        comm.barrier()
        mesh = folder / source.name
        made = ["--method", "pennate", "--origin", origin, "--insertion", insertion] if field == "pennate" else []
        if fibers_job.main(["--mesh", str(mesh), *made], comm=comm) != cli.EXIT_OK:
            raise InputError(f"{name}: hyper fibers --mesh failed")
        result = folder / "mwf.h5"
        (_, wall, cpu) = timed(lambda: grow.main(["--mesh", str(mesh), "--mesh-unit", "mm", "--protocol", "mwf",
                                                 "--sections", str(SECTIONS), "--output", str(result)],
                                                comm=comm))
        series = io.read_series(result)
        with io.reading_h5(result) as f:
            fractions = [float(v) for v in f.attrs["section_fractions"]]
        out[field] = {"csa_gain_pct": 100 * (series["csa_ratio"][-1] - 1),
                      "volume_gain_pct": 100 * (series["volume_ratio"][-1] - 1),
                      "section_gain_pct": [100 * (v - 1) for v in series["csa_ratio_sections"][-1]],
                      "fractions": fractions, "run_wall_s": wall, "run_cpu_s": cpu}
    return out


def run(comm, args) -> int:
    rows = []
    for name in args.geometries:
        origin, insertion = rule(name)
        geometry = geo.load(name, comm)
        result, compute_wall, compute_cpu = timed(lambda: pennate.compute(geometry, origin, insertion))
        stats, stats_wall, stats_cpu = timed(lambda: pennate.statistics(result))
        stokes = pennate.stokes_statistics(geometry, fibers.load(geometry))
        row = {"geometry": name, "machine": common.machine(), "cells": stats["cells"], "ranks": comm.size,
               "origin": origin, "insertion": insertion, "compute_wall_s": compute_wall, "compute_cpu_s": compute_cpu,
               "statistics_wall_s": stats_wall, "statistics_cpu_s": stats_cpu,
               "pennate": {k: stats.get(k) for k in SHOWN}, "stokes": {k: stokes.get(k) for k in SHOWN}}
        if args.growth:
            row["growth"] = growth(comm, args, name, origin, insertion)
        rows.append(row)
        info(comm, f"{name} ({stats['cells']} cells, {comm.size} rank(s)): generator {compute_wall:.2f} s wall / "
                   f"{compute_cpu:.2f} s CPU, statistics {stats_wall:.1f} s / {stats_cpu:.1f} s")
        for field in ("pennate", "stokes"):
            s = row[field]
            info(comm, f"  {field:<8} pennation mean {s['pennation_deg_mean']:.1f}°, 5/50/95 % "
                       f"{s['pennation_deg_p5']:.1f}/{s['pennation_deg_p50']:.1f}/{s['pennation_deg_p95']:.1f}°; "
                       f"fascicle mean {s['fascicle_mm_mean']:.0f} mm, 5/50/95 % {s['fascicle_mm_p5']:.0f}/"
                       f"{s['fascicle_mm_p50']:.0f}/{s['fascicle_mm_p95']:.0f} mm")
            if args.growth:
                g = row["growth"][field]
                info(comm, f"  {field:<8} mwf 9 weeks: CSA +{g['csa_gain_pct']:.2f} %, volume "
                           f"+{g['volume_gain_pct']:.2f} %; sections "
                           + " ".join(f"{v:.2f}" for v in g["section_gain_pct"]))
    if comm.rank == 0:
        io.write_json(args.output / "pennate.json", {"rows": rows})
        if args.growth:
            plot.save(figure(rows), args.output / "pennate_growth.png", dpi=110)
    info(comm, f"wrote {args.output / 'pennate.json'}")
    return cli.EXIT_OK


def figure(rows):
    """The CSA gain at the sections along the length, pennate against Stokes, per muscle."""
    plt = plot.pyplot()
    fig, axes = plt.subplots(1, len(rows), figsize=(5.5 * len(rows), 4.0), layout="constrained", squeeze=False)
    for ax, row in zip(axes[0], rows):
        for field, colour in (("stokes", "0.4"), ("pennate", "C1")):
            g = row["growth"][field]
            ax.plot(np.asarray(g["fractions"]), g["section_gain_pct"], "o-", color=colour,
                    label=f"{field}: CSA0 +{g['csa_gain_pct']:.2f} %, V +{g['volume_gain_pct']:.2f} %")
        ax.set_xlabel("section along the principal axis (share of the length)")
        ax.set_ylabel("CSA gain after 9 weeks of mwf (%)")
        ax.set_title(row["geometry"], fontsize=10)
        ax.legend(fontsize=8)
    fig.suptitle("Where the muscle grows: the cut area at 9 sections, pennate against Stokes fibres")
    return fig


main = cli.entry(parser, run)

if __name__ == "__main__":
    sys.exit(main())
