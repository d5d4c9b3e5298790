"""``hyper fibers``: the Stokes-flow fibres (`hyper.fem.fibers`) of the anatomical meshes,
stored next to each mesh (``fibers_stokes.h5`` beside the shipped meshes' own fibres), or
with ``--method laplace`` their own, the Laplace fibres (`hyper.fem.laplace`, ``fibers.h5``,
what runs use), with a picture and a summary per mesh; with ``--fibers FILE``,
fibres from data (`hyper.fem.fiberdata`) of the geometries given; or the fibres of one
mesh file, Stokes, Laplace (`hyper.fem.laplace`: the potential flow between the ends) or
pennate (`hyper.fem.pennate`), beside it:

    hyper fibers --mesh my_muscle/my_muscle.xdmf --mesh-unit mm --method pennate \
        --origin "tags:1 | tags:3 & along:0,0.8" --insertion "tags:2 | midplane & along:0.2,1"

writes my_muscle/fibers.h5 (which `hyper grow --mesh my_muscle/my_muscle.xdmf` then
reads) and my_muscle/fibers.png: fibre glyphs on two mid-slices coloured by the pennation
angle, and the distributions of pennation angle and fascicle length.

``mpirun -n 2 python -m hyper.fibers`` spreads the meshes over groups of
``--ranks-per-job`` ranks (hyper.runs.farm) and skips a mesh whose fibre file is complete
and whose picture exists; a complete fibre file without its picture is read back, not
recomputed (``--force`` recomputes). It writes ``results/fibers/<geometry>.png`` and
``results/fibers/summary.csv`` and prints the table.

``hyper fibers --geometries ID --fibers FILE`` samples a DTI image, streamlines or a
point cloud at the mesh's nodes and writes ``OUTPUT/ID_fibers.h5`` (a fibre file, which
``hyper grow --geometry ID --fibers OUTPUT/ID_fibers.h5`` runs) and ``OUTPUT/ID_fibers.png``
(the fibres coloured by pennation angle), and prints its coverage, pennation angle and
angle against the Stokes fibres beside the mesh; the shipped Stokes fibres stay as they
are. With several geometries FILE names one file per geometry with {geometry}.
"""

from __future__ import annotations

import csv
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

from hyper.commands import cli
from hyper.core.collective import on_rank0
from hyper.core.io import atomic_path, is_complete, write_series
from hyper.core.log import info
from hyper.core.params import InputError, as_attributes
from hyper.fem import fiberdata, fibers, laplace, pennate
from hyper.fem import geometry as geo
from hyper.runs import farm, plot, presets, runspec

SUMMARY_COLUMNS = ("geometry", "muscle", "subject", "side", "cells", "vertices", "share_within_30deg",
                   "max_norm_error", "min_speed", "max_speed", "solve_s", "status")


METHODS = ("stokes", "laplace", "pennate")


def parser() -> cli.Parser:
    p = cli.Parser("fibers", description="Stokes-flow fibre fields for the anatomical meshes (MODEL.md §5), stored "
                   f"next to each mesh\nas {fibers.STOKES_FILE_NAME} (--method laplace: their own fibres, "
                   f"{fibers.FILE_NAME}), with a picture and a summary\nper mesh; or, with --mesh, the Stokes, "
                   f"Laplace or pennate fibres of one mesh file beside it.\n\n{pennate.SYNTAX}")
    p.add_argument("--geometries", nargs="+", metavar="ID", default=list(geo.ANATOMICAL),
                   help="geometries to do (the 12 anatomical meshes)")
    p.add_argument("--mesh", type=Path, reads=True,
                   help=f"instead of --geometries: one XDMF mesh with facet tags ft_small (1, 2 the ends, 3 the "
                        f"lateral surface), whose fibres go beside it as {fibers.FILE_NAME} with fibers.png")
    p.add_argument("--mesh-unit", choices=tuple(runspec.MESH_UNITS), default="mm", help="length unit of --mesh")
    p.add_argument("--method", choices=METHODS, default="stokes",
                   help="Stokes flow (hyper.fem.fibers; for --geometries their Stokes fibres, "
                        f"{fibers.STOKES_FILE_NAME} where the own fibres are another kind), the potential flow "
                        f"between the ends (hyper.fem.laplace; for --geometries their own fibres, {fibers.FILE_NAME}, "
                        "as shipped) or, with --mesh, pennate fibres between --origin and --insertion "
                        "(hyper.fem.pennate)")
    p.add_argument("--origin", default=pennate.DEFAULT_ORIGIN, metavar="PATCH",
                   help="pennate: the origin aponeurosis (patch syntax above)")
    p.add_argument("--insertion", default=pennate.DEFAULT_INSERTION, metavar="PATCH",
                   help="pennate: the insertion aponeurosis (patch syntax above)")
    p.add_argument("--force", action="store_true", help="recompute fibre files that exist")
    p.add_argument("--ranks-per-job", type=cli.integer(1), default=1, help="MPI ranks per mesh")
    p.add_argument("--output", type=cli.output(folder=True), default="results/fibers",
                   help="folder for summary.csv and the pictures")
    p.add_argument("--meshes-dir", type=Path, default=geo.MESHES_DIR,
                   help="folder of the meshes, where the fibre files go")
    p.add_argument("--penalty", type=cli.number(), default=fibers.StokesParams.penalty, help="Nitsche penalty γ")
    p.add_argument("--fibers", metavar="FILE", help=f"fibres from data instead of Stokes flow: {presets.DATA_HELP}"
                   f"{presets.PER_GEOMETRY_HELP}; written to OUTPUT/ID_fibers.h5 with a picture")
    cli.fibre_data_options(p)
    p.add_argument("--degree", type=cli.integer(2, 3), default=fibers.StokesParams.degree,
                   help="velocity degree of the Taylor–Hood flow (3: nearer the converged field where P2 is not, "
                        "e.g. VL_VHM_Left, at about 2.5 GB for an 8k-cell mesh; python -m hyper.bench convergence "
                        "--fibres-only)")
    return p


def _work(args, params: fibers.StokesParams):
    """The farm job for one geometry: fibres (computed or read back), file, picture."""
    def work(comm, job):
        name = job.key
        geometry = geo.load(name, comm, meshes_dir=args.meshes_dir)
        path = target(name, args)
        start = time.perf_counter()
        computed = args.force or not is_complete(path)
        if computed and args.method == "laplace":
            a0, speed = laplace.compute(geometry)
            stats = {**fibers.statistics(geometry, a0, speed), "solve_s": time.perf_counter() - start}
            laplace.store(path, geometry, a0, speed, mesh=geo.GEOMETRIES[name], solve_s=stats["solve_s"])
        elif computed:
            a0, speed = fibers.compute(geometry, params)
            solve_s = time.perf_counter() - start
            stats = {**fibers.statistics(geometry, a0, speed), "solve_s": solve_s}
        else:
            a0 = fibers.load(geometry, path)
            stored = comm.bcast(_stored_stats(path) if comm.rank == 0 else None, root=0)
            stats = {**stored, **fibers.statistics(geometry, a0)}
        if computed and args.method == "stokes":
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


def target(name: str, args) -> Path:
    """The fibre file ``hyper fibers --geometries`` writes: a geometry's own (Laplace, as
    shipped) or its Stokes fibres (`fibers.fiber_path`)."""
    return fibers.fiber_path(name, args.meshes_dir, kind=args.method)


def _flow_cells(folder: Path) -> int | None:
    """The cells of the mesh `hyper mesh` solved a mesh folder's fibre flow on, where it did."""
    record = folder / "mesh.json"
    return json.loads(record.read_text()).get("flow_cells_target") if record.is_file() else None


def _remade_elsewhere(what: str, flow: int, folder: Path, how: str) -> str:
    # solved on the mesh itself they would be another, coarser field (docs/convergence.md)
    return (f"{what}: its Laplace fibres were solved by hyper mesh on a {flow}-cell mesh of its surface "
            f"({folder / 'mesh.json'}); remake them with hyper mesh ({how})")


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


def from_data(comm, args) -> int:
    """--fibers FILE: fibres from data for each of --geometries, one after the other on all ranks."""
    if args.geometries == list(geo.ANATOMICAL) and presets.GEOMETRY_FIELD not in args.fibers:
        raise InputError("--fibers FILE: name the geometry it belongs to with --geometries ID")
    if len(args.geometries) > 1 and presets.GEOMETRY_FIELD not in args.fibers:
        raise InputError(f"--fibers {args.fibers}: a fibre data file belongs to one geometry; with several, name "
                         f"one file per geometry with {presets.GEOMETRY_FIELD} in its path")
    sources = {name: presets.data_source(args, (), name) for name in args.geometries}
    for name, source in sources.items():
        geometry = geo.load(name, comm, meshes_dir=args.meshes_dir)
        stokes = fiberdata.stokes_beside(geometry, fibers.fiber_path(name, args.meshes_dir, kind="stokes"))
        a0, field = fiberdata.make(geometry, source, *stokes)
        path = args.output / f"{name}_fibers.h5"
        sha = on_rank0(comm, lambda s=source: hashlib.sha256(s.path.read_bytes()).hexdigest())
        fiberdata.store(path, geometry, a0, field, source, sha, mesh=geo.GEOMETRIES[name])
        picture(geometry, a0, field, path.with_suffix(".png"), f"{name}: fibres from {source.path.name}")
        info(comm, f"{name}: {fiberdata.summary(field)}")
        info(comm, f"wrote {path} and {path.with_suffix('.png')}")
    return cli.EXIT_OK


def picture(geometry, a0, field, path: Path, title: str) -> None:
    """The fibre glyphs of `figure` for fibres from data, beside their fibre file. Collective."""
    stats = {"share_within_30deg": fibers.aligned_share(geometry, a0, field.line_of_action)}
    cells = fibers.cell_fibers(geometry, a0)
    if geometry.comm.rank == 0:
        plot.save(figure(geometry.name, *cells, field.line_of_action, stats, title=title,
                         angle_label="pennation angle"), path, dpi=110)


def run(comm, args) -> int:
    if args.fibers is not None:
        return from_data(comm, args)
    if args.method != "pennate" and (args.origin, args.insertion) != (pennate.DEFAULT_ORIGIN,
                                                                      pennate.DEFAULT_INSERTION):
        raise InputError("--origin and --insertion are the attachments of --method pennate")
    if args.mesh is not None:
        if args.geometries != list(geo.ANATOMICAL):
            raise InputError("--mesh and --geometries: one or the other")
        return run_mesh(comm, args)
    if args.method == "pennate":
        raise InputError("--method pennate: give the --mesh file whose fibres to make (its aponeuroses are that "
                         "muscle's; copy a shipped mesh folder to make them beside it)")
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
        if args.method == "laplace" and (args.force or not is_complete(target(name, args))):
            flow = _flow_cells(mesh_file.parent)
            if flow:
                raise InputError(_remade_elsewhere(name, flow, mesh_file.parent, "the shipped ones: make new-meshes"))
    jobs = [farm.Job(name, cost=1.0) for name in args.geometries]

    def is_done(job):
        return (not args.force and is_complete(target(job.key, args))
                and (args.output / f"{job.key}.png").is_file())

    results = farm.run(comm, jobs, _work(args, params), ranks_per_job=args.ranks_per_job,
                       is_done=is_done, label="fibres")
    status = 0
    if comm.rank == 0:
        paths = [target(name, args) for name in args.geometries]
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


def run_mesh(comm, args) -> int:
    """The fibres of one mesh file, written beside it with their picture (module docstring)."""
    mesh = runspec.MeshFile(args.mesh, unit=args.mesh_unit)
    path = mesh.fibres
    picture = path.with_suffix(".png")
    if not on_rank0(comm, mesh.path.is_file):
        raise InputError(f"--mesh {mesh.path}: no such file")
    cache, why = mesh.fibre_cache()
    if cache is None:
        raise InputError(f"--mesh {mesh.path}: its fibres cannot go beside it ({why}); copy the mesh folder")
    if not args.force and on_rank0(comm, path.exists):
        raise InputError(f"{path}: exists; give --force to replace it")
    flow = on_rank0(comm, lambda: _flow_cells(mesh.path.parent)) if args.method == "laplace" else None
    if flow:
        raise InputError(_remade_elsewhere(str(mesh.path), flow, mesh.path.parent, "hyper mesh --flow-cells 0 gives "
                                           "the mesh's own"))
    if args.method == "pennate":  # the patches parsed before any work: a bad one writes nothing
        origin = pennate.parse(args.origin, "--origin")
        insertion = pennate.parse(args.insertion, "--insertion")
    geometry = mesh.load(comm)
    start = time.perf_counter()
    identity = {"mesh": str(mesh.path), "mesh_sha256": mesh.identity()["mesh_sha256"]}
    if args.method == "pennate":
        result = pennate.compute(geometry, origin, insertion)
        a0 = result.a0
        solve_s = time.perf_counter() - start
        stats = pennate.statistics(result)
        pennate.store(path, result, {**stats, "solve_s": solve_s}, **identity)
        label = f"pennate fibres (origin {origin.spec!r}, insertion {insertion.spec!r})"
    elif args.method == "laplace":
        a0, speed = laplace.compute(geometry)
        solve_s = time.perf_counter() - start
        stats = pennate.stokes_statistics(geometry, a0)
        laplace.store(path, geometry, a0, speed, solve_s=solve_s,
                      **{f"architecture_{k}": v for k, v in stats.items() if k.startswith(("pennation", "fascicle"))},
                      **identity)
        label = "Laplace fibres (the potential flow between the ends)"
    else:
        params = fibers.StokesParams(penalty=args.penalty)
        a0, speed = fibers.compute(geometry, params)
        solve_s = time.perf_counter() - start
        stats = pennate.stokes_statistics(geometry, a0)
        fibers.store(path, geometry, a0, speed, params, kind="stokes", solve_s=solve_s,
                     **{f"architecture_{k}": v for k, v in stats.items() if k.startswith(("pennation", "fascicle"))},
                     **identity)
        label = "Stokes fibres"
    cells = fibers.cell_fibers(geometry, a0)
    axis = pennate.Frame(geometry).axis
    if comm.rank == 0:
        plot.save(pennation_figure(geometry.name, *cells, axis, stats, label), picture, dpi=110)
    info(comm, f"{geometry.name}: {label}")
    info(comm, f"  pennation angle to the line of action (first principal axis): mean "
               f"{stats['pennation_deg_mean']:.1f}°, 5/50/95 % {stats['pennation_deg_p5']:.1f}/"
               f"{stats['pennation_deg_p50']:.1f}/{stats['pennation_deg_p95']:.1f}°")
    if "fascicle_mm_mean" in stats:
        info(comm, f"  fascicle length: mean {stats['fascicle_mm_mean']:.1f} mm, 5/50/95 % "
                   f"{stats['fascicle_mm_p5']:.1f}/{stats['fascicle_mm_p50']:.1f}/{stats['fascicle_mm_p95']:.1f} mm "
                   f"({100 * stats['fascicles_reached_share']:.1f} % of the origin area reached the insertion)")
    info(comm, f"  fibres within 30° of the axis: {100 * stats['share_within_30deg']:.1f} % of the volume; "
               f"made in {solve_s:.1f} s")
    info(comm, f"wrote {path} and {picture}")
    return cli.EXIT_OK


def pennation_figure(name: str, centroid, fiber, volume, axis, stats: dict, label: str):
    """Fibre glyphs on two orthogonal mid-slices coloured by the pennation angle (to the
    line of action ``axis``), and the distributions of pennation angle and fascicle length."""
    plt = plot.pyplot()
    from matplotlib.collections import LineCollection

    angle = np.degrees(np.arccos(np.clip(np.abs(fiber @ axis), 0.0, 1.0)))
    centred = centroid - centroid.mean(axis=0)
    across = centred - np.outer(centred @ axis, axis)
    spread = np.linalg.svd(across, full_matrices=False)[2]
    basis = np.vstack([axis, spread[0], np.cross(axis, spread[0])])
    p = centred @ basis.T * 1e3
    d = fiber @ basis.T
    cmap, norm = plt.get_cmap("viridis"), plt.Normalize(0.0, 30.0)
    glyph = 0.012 * np.ptp(p[:, 0])
    fig = plt.figure(figsize=(13, 6.0), layout="constrained")
    grid = fig.add_gridspec(2, 2, width_ratios=(3.0, 1.0))
    for row, (shown, hidden) in enumerate(((1, 2), (2, 1))):
        ax = fig.add_subplot(grid[row, 0])
        slab = np.abs(p[:, hidden] - np.median(p[:, hidden])) < 0.08 * np.ptp(p[:, hidden])
        xy = p[slab][:, [0, shown]]
        uv = d[slab][:, [0, shown]]
        uv = uv / np.maximum(np.linalg.norm(uv, axis=1), 1e-12)[:, None] * glyph
        ax.add_collection(LineCollection(np.stack([xy - uv, xy + uv], axis=1), colors=cmap(norm(angle[slab])),
                                         linewidths=1.0))
        ax.set_xlim(p[:, 0].min() - glyph, p[:, 0].max() + glyph)
        ax.set_ylim(p[:, shown].min() - glyph, p[:, shown].max() + glyph)
        ax.set_aspect("equal")
        ax.set_ylabel(f"{('', '2nd', '3rd')[shown]} axis (mm)")
        ax.set_title(f"mid-slice across the {('', '3rd', '2nd')[shown]} axis: {slab.sum()} cells", fontsize=10)
    ax.set_xlabel("line of action: first principal axis (mm), from the origin end to the insertion end")
    fig.colorbar(plt.cm.ScalarMappable(cmap=cmap, norm=norm), ax=fig.axes, shrink=0.6, location="bottom",
                 aspect=40, label="pennation angle to the line of action (°, clipped at 30)")
    top = fig.add_subplot(grid[0, 1])
    top.hist(angle, bins=np.arange(0, 46, 1.5), weights=volume / volume.sum() * 100, color="0.4")
    top.set_xlabel("pennation angle (°)")
    top.set_ylabel("share of volume (%)")
    top.set_title(f"mean {stats['pennation_deg_mean']:.1f}°, median {stats['pennation_deg_p50']:.1f}°", fontsize=10)
    bottom = fig.add_subplot(grid[1, 1])
    if "fascicle_mm_mean" in stats:
        bottom.axvspan(stats["fascicle_mm_p5"], stats["fascicle_mm_p95"], color="C0", alpha=0.25,
                       label="5-95 %")
        bottom.axvline(stats["fascicle_mm_p50"], color="C0", label="median")
        bottom.axvline(stats["fascicle_mm_mean"], color="C3", ls="--", label="mean")
        bottom.set_xlim(0, max(1.1 * stats["fascicle_mm_p95"], 10.0))
        bottom.legend(fontsize=8)
        bottom.set_title(f"fascicle length: mean {stats['fascicle_mm_mean']:.0f} mm", fontsize=10)
    bottom.set_yticks([])
    bottom.set_xlabel("fascicle length, origin to insertion (mm)")
    fig.suptitle(f"{name}: {label}", fontsize=11)
    return fig


def figure(name: str, centroid, fiber, volume, axis, stats: dict, title: str | None = None,
           angle_label: str = "angle to principal axis"):
    """Fibre glyphs on two orthogonal mid-slices through the muscle's long axis, coloured
    by the angle to the principal axis, and the volume-weighted histogram of that angle.

    ``axis`` (unit) should point from the inflow end to the outflow end; ``title`` says
    what the fibres are (the Stokes-flow fibres by default)."""
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
                 aspect=40, label=f"{angle_label} (°, clipped at 45)")

    ax2 = fig.add_subplot(grid[:, 1])
    ax2.hist(angle, bins=np.arange(0, 91, 2.5), weights=volume / volume.sum() * 100, color="0.4")
    ax2.axvline(fibers.ALIGNMENT_DEG, color="C3", ls="--")
    ax2.set_xlabel(f"{angle_label} (°)")
    ax2.set_ylabel("share of volume (%)")
    ax2.set_title(f"within {fibers.ALIGNMENT_DEG:g}°: {100 * stats['share_within_30deg']:.1f} % of the volume",
                  fontsize=10)
    fig.suptitle(f"{title or name + ': Stokes-flow fibres'} (cell means of the nodal field)")
    return fig


main = cli.entry(parser, run,
                 locks=lambda args: [args.output] if args.mesh is None else [args.mesh.parent / fibers.FILE_NAME])

if __name__ == "__main__":
    sys.exit(main())
