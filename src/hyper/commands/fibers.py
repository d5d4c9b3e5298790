"""``hyper fibers``: the Stokes-flow fibres (`hyper.fem.fibers`) of the anatomical meshes,
stored next to each mesh, with a picture and a summary per mesh.

``mpirun -n 2 python -m hyper.fibers`` spreads the meshes over groups of
``--ranks-per-job`` ranks (hyper.runs.farm) and skips a mesh whose fibre file is complete
and whose picture exists; a complete fibre file without its picture is read back, not
recomputed (``--force`` recomputes). It writes ``results/fibers/<geometry>.png`` and
``results/fibers/summary.csv`` and prints the table.
"""

from __future__ import annotations

import csv
import sys
import time
from pathlib import Path

import numpy as np

from hyper.commands import cli
from hyper.core.io import atomic_path, is_complete, write_series
from hyper.core.log import info
from hyper.core.params import InputError, as_attributes
from hyper.fem import fibers
from hyper.fem import geometry as geo
from hyper.runs import farm, plot

SUMMARY_COLUMNS = ("geometry", "muscle", "subject", "side", "cells", "vertices", "share_within_30deg",
                   "max_norm_error", "min_speed", "max_speed", "solve_s", "status")


def parser() -> cli.Parser:
    p = cli.Parser("fibers", description="Stokes-flow fibre fields for the anatomical meshes (MODEL.md §5), stored "
                   f"next to each mesh\nas {fibers.FILE_NAME}, with a picture and a summary per mesh.")
    p.add_argument("--geometries", nargs="+", metavar="ID", default=list(geo.ANATOMICAL),
                   help="geometries to do (the 12 anatomical meshes)")
    p.add_argument("--force", action="store_true", help="recompute fibre files that exist")
    p.add_argument("--ranks-per-job", type=cli.integer(1), default=1, help="MPI ranks per mesh")
    p.add_argument("--output", type=cli.output(folder=True), default="results/fibers",
                   help="folder for summary.csv and the pictures")
    p.add_argument("--meshes-dir", type=Path, default=geo.MESHES_DIR,
                   help="folder of the meshes, where the fibre files go")
    p.add_argument("--penalty", type=cli.number(), default=fibers.StokesParams.penalty, help="Nitsche penalty γ")
    p.add_argument("--degree", type=int, choices=(2, 3), default=fibers.StokesParams.degree,
                   help="velocity degree of the Taylor–Hood flow (3: nearer the converged field where P2 is not, "
                        "e.g. VL_VHM_Left, at about 2.5 GB for an 8k-cell mesh; python -m hyper.bench convergence "
                        "--fibres-only)")
    return p


def _work(args, params: fibers.StokesParams):
    """The farm job for one geometry: fibres (computed or read back), file, picture."""
    def work(comm, job):
        name = job.key
        geometry = geo.load(name, comm, meshes_dir=args.meshes_dir)
        path = fibers.fiber_path(name, args.meshes_dir)
        start = time.perf_counter()
        computed = args.force or not is_complete(path)
        if computed:
            a0, speed = fibers.compute(geometry, params)
            solve_s = time.perf_counter() - start
            stats = {**fibers.statistics(geometry, a0, speed), "solve_s": solve_s}
        else:
            a0 = fibers.load(geometry, path)
            stored = comm.bcast(_stored_stats(path) if comm.rank == 0 else None, root=0)
            stats = {**stored, **fibers.statistics(geometry, a0)}
        if computed:
            data = fibers.gather_nodal(a0, speed)
            if comm.rank == 0:
                write_series(
                    path, data,
                    attrs={"geometry": name, "mesh": geo.GEOMETRIES[name], "method": fibers.stokes_method(params),
                           "element": fibers.ELEMENT, "reference": "Varvik et al. 2021; MODEL.md §5",
                           "inflow_tag": geometry.ends[0], "outflow_tag": geometry.ends[1],
                           "lateral_tag": geometry.lateral, "coordinates": "m",
                           "ranks": comm.size, **stats},
                    groups={"parameters": as_attributes(params)},
                )
        cells = fibers.cell_fibers(geometry, a0)
        axis = fibers.principal_axis(geometry)
        ends = [geo.facet_centroid(geometry, tag) for tag in geometry.ends]
        axis = axis if np.dot(ends[1] - ends[0], axis) >= 0 else -axis
        if comm.rank == 0:
            plot.save(figure(name, *cells, axis, stats), args.output / f"{name}.png", dpi=110)
        return {k: float(v) if isinstance(v, np.floating) else v for k, v in stats.items()}

    return work


def _stored_stats(path: Path) -> dict:
    import h5py

    with h5py.File(path, "r") as f:
        return {k: f.attrs[k] for k in SUMMARY_COLUMNS if k in f.attrs}


def _write_summary(path: Path, names, fiber_paths, results) -> list[dict]:
    rows = []
    for name, stored, result in zip(names, fiber_paths, results):
        muscle, subject, side = geo.split_id(name) if name in geo.ANATOMICAL else ("", "", "")
        row = {"geometry": name, "muscle": muscle, "subject": subject, "side": side, "status": result.status}
        if result.status == "done":
            row.update(result.result)
        elif result.status == "skipped":
            row.update(_stored_stats(stored))
        rows.append(row)
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=SUMMARY_COLUMNS, restval="", extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    return rows


def run(comm, args) -> int:
    unknown = [g for g in args.geometries if g not in geo.GEOMETRIES]
    if unknown:
        raise InputError(f"--geometries: unknown {', '.join(unknown)}; known: {', '.join(geo.GEOMETRIES)}")
    if len(set(args.geometries)) != len(args.geometries):
        raise InputError("--geometries: each geometry once")
    params = fibers.StokesParams(penalty=args.penalty, degree=args.degree)
    for name in args.geometries:
        mesh_file = fibers.fiber_path(name, args.meshes_dir).parent / Path(geo.GEOMETRIES[name]).name
        if not mesh_file.is_file():
            raise InputError(f"{mesh_file}: no such mesh file")
    jobs = [farm.Job(name, cost=1.0) for name in args.geometries]

    def is_done(job):
        return (not args.force and is_complete(fibers.fiber_path(job.key, args.meshes_dir))
                and (args.output / f"{job.key}.png").is_file())

    results = farm.run(comm, jobs, _work(args, params), ranks_per_job=args.ranks_per_job,
                       is_done=is_done, label="fibres")
    status = 0
    if comm.rank == 0:
        paths = [fibers.fiber_path(name, args.meshes_dir) for name in args.geometries]
        rows = _write_summary(args.output / "summary.csv", args.geometries, paths, results)
        info(comm, f"{'geometry':<16} {'cells':>6} {'within 30°':>10} {'max||a0|-1|':>12} "
                   f"{'speed min..max':>15} {'solve s':>8}  status")
        for row in rows:
            if "share_within_30deg" in row:
                info(comm, f"{row['geometry']:<16} {row['cells']:>6d} {100 * row['share_within_30deg']:>9.2f}% "
                           f"{row['max_norm_error']:>12.1e} {row.get('min_speed', np.nan):>7.3f}.."
                           f"{row.get('max_speed', np.nan):<7.3f} {row.get('solve_s', np.nan):>8.1f}  "
                           f"{row['status']}")
            else:
                info(comm, f"{row['geometry']:<16} {'':>48}  {row['status']}")
        info(comm, farm.summary_line(results))
        info(comm, f"summary: {args.output / 'summary.csv'}")
        status = int(any(r.status == "failed" for r in results))
    return comm.bcast(status, root=0)


def figure(name: str, centroid, fiber, volume, axis, stats: dict):
    """Fibre glyphs on two orthogonal mid-slices through the muscle's long axis, coloured
    by the angle to the principal axis, and the volume-weighted histogram of that angle.

    ``axis`` (unit) should point from the inflow end to the outflow end."""
    plt = plot.pyplot()
    from matplotlib.collections import LineCollection

    angle = np.degrees(np.arccos(np.clip(np.abs(fiber @ axis), 0.0, 1.0)))
    # Principal coordinates (mm): the fibres' reference axis, then the two widest spreads.
    centred = centroid - centroid.mean(axis=0)
    across = centred - np.outer(centred @ axis, axis)
    spread = np.linalg.svd(across, full_matrices=False)[2]
    basis = np.vstack([axis, spread[0], np.cross(axis, spread[0])])
    p = centred @ basis.T * 1e3
    d = fiber @ basis.T
    cmap, norm = plt.get_cmap("viridis"), plt.Normalize(0.0, 45.0)
    glyph = 0.012 * np.ptp(p[:, 0])

    fig = plt.figure(figsize=(12, 5.6), layout="constrained")
    grid = fig.add_gridspec(2, 2, width_ratios=(3.0, 1.0))
    for row, (shown, hidden) in enumerate(((1, 2), (2, 1))):
        ax = fig.add_subplot(grid[row, 0])
        # A slab around the mid-plane: glyphs from one depth, not a pile of all depths.
        slab = np.abs(p[:, hidden] - np.median(p[:, hidden])) < 0.08 * np.ptp(p[:, hidden])
        xy = p[slab][:, [0, shown]]
        uv = d[slab][:, [0, shown]]
        uv = uv / np.maximum(np.linalg.norm(uv, axis=1), 1e-12)[:, None] * glyph
        lines = np.stack([xy - uv, xy + uv], axis=1)
        ax.add_collection(LineCollection(lines, colors=cmap(norm(angle[slab])), linewidths=1.0))
        ax.set_xlim(p[:, 0].min() - glyph, p[:, 0].max() + glyph)
        ax.set_ylim(p[:, shown].min() - glyph, p[:, shown].max() + glyph)
        ax.set_aspect("equal")
        ax.set_ylabel(f"{('', '2nd', '3rd')[shown]} axis (mm)")
        ax.set_title(f"mid-slice across the {('', '3rd', '2nd')[shown]} axis: {slab.sum()} cells", fontsize=10)
    ax.set_xlabel("principal axis (mm), from the inflow end to the outflow end")
    fig.colorbar(plt.cm.ScalarMappable(cmap=cmap, norm=norm), ax=fig.axes, shrink=0.6, location="bottom",
                 aspect=40, label="angle to principal axis (°, clipped at 45)")

    ax2 = fig.add_subplot(grid[:, 1])
    ax2.hist(angle, bins=np.arange(0, 91, 2.5), weights=volume / volume.sum() * 100, color="0.4")
    ax2.axvline(fibers.ALIGNMENT_DEG, color="C3", ls="--")
    ax2.set_xlabel("angle to principal axis (°)")
    ax2.set_ylabel("share of volume (%)")
    ax2.set_title(f"within {fibers.ALIGNMENT_DEG:g}°: {100 * stats['share_within_30deg']:.1f} % of the volume",
                  fontsize=10)
    fig.suptitle(f"{name}: Stokes-flow fibres (cell means of the nodal field)")
    return fig


main = cli.entry(parser, run, locks=lambda args: [args.output])

if __name__ == "__main__":
    sys.exit(main())
