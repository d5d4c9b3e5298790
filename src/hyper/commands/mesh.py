"""``hyper mesh``: a muscle's surface (STL) to a mesh folder, by the steps of
`hyper.fem.meshing` (whose docstring is the job's help): read, check, tetrahedralize and
tag on rank 0, then the XDMF mesh, its fibres (Stokes, `hyper.fem.fibers`; Laplace,
`hyper.fem.laplace`; pennate or from data), its statistics
(`hyper.fem.meshstats`), mesh.json and a picture, written to a staging folder that
replaces ``--output`` whole."""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from hyper.commands import cli
from hyper.commands import fibers as fibers_job
from hyper.core.collective import on_rank0
from hyper.core.io import write_json, write_series
from hyper.core.log import info
from hyper.core.params import InputError, as_attributes
from hyper.fem import fiberdata, fibers, laplace, meshstats, pennate
from hyper.fem import geometry as geo
from hyper.fem import meshing as hm
from hyper.runs import plot, presets

ARRAYS = ("x", "tets", "facets", "tags")  # what `build` returns besides numbers
# --fibers-smoothing (mm): on TA_VHF_Left (docs/convergence.md) 2 mm brings the 8k-cell fibres
# within 2.5° (95th percentile) of the 64k-cell field; 3 mm gains 0.3° more
FIBERS_SMOOTHING_MM = 2.0
METHODS = ("stokes", "laplace", "pennate")
# The Laplace fibres converge with the mesh where the paper's Stokes fibres do not (the wide
# muscles: docs/convergence.md, "Laplace fibres"); `--method stokes` gives the paper's flow.
DEFAULT_METHOD = "laplace"
# The Laplace flow is solved on a mesh of the surface with this many times --cells and carried
# onto the mesh's nodes: a coarse mesh's end patches are coarse, and on VM_VHM_Left the 8k
# mesh's own field is 4.0° (95th percentile) from the 256k one, 9.7° at the end nodes, where
# the 32k flow carried onto it is 1.4° (docs/convergence.md, "The converged field")
FLOW_CELLS_FACTOR = 4
FIGURE_LABEL = {"stokes": "Stokes fibres", "laplace": "Laplace fibres", "pennate": "pennate fibres"}


def parser() -> cli.Parser:
    p = cli.Parser("mesh", hm.__doc__)
    p.add_argument("surface", type=Path, reads=True, help="the muscle's closed surface (STL, binary or ASCII)")
    p.add_argument("--output", type=cli.output(folder=True, replaces=True), required=True,
                   help="the folder to write, meshes/NAME/; NAME is the "
                   "geometry's identifier")
    p.add_argument("--unit", choices=tuple(hm.UNITS_MM), default="mm", help="length unit of the STL")
    p.add_argument("--cells", type=cli.integer(200, hm.MAX_CELLS), default=hm.DEFAULT_CELLS, help="target cell count")
    p.add_argument("--gmsh-budget", type=cli.positive("seconds"), metavar="SECONDS", help="wall time of gmsh's "
                   f"tries, after which the job stops with an error (default {hm.GMSH_BUDGET_S:g} s and "
                   f"{hm.GMSH_BUDGET_S_PER_CELL:g} s a cell)")
    p.add_argument("--end-band", type=cli.number(above=0, below=0.5), default=hm.END_BAND,
                   help="an end: the facets within this share of "
                   "the length from an extreme along the axis")
    p.add_argument("--end-rule", choices=hm.END_RULES, default=hm.END_RULES[0],
                   help="surface: the band measured along the STL's own principal axis (ends of one shape at "
                        "any --cells); vertices: along the mesh vertices' (hyper mesh before; the shipped new "
                        "meshes)")
    cli.vector_option(p, "--axis", help="the muscle's long axis (the first principal axis of the STL surface, or "
                      "of the mesh vertices under --end-rule vertices, by default)")
    cli.vector_option(p, "--origin-toward", default=hm.ORIGIN_TOWARD,
                      help="the origin (tag 1) is the end further along this direction")
    p.add_argument("--flow-cells", type=cli.integer(0, hm.MAX_CELLS), metavar="N",
                   help="solve the fibres' flow (Laplace or Stokes) on a second mesh of the surface at N cells "
                        "(finer than --cells) and interpolate it onto this mesh's nodes: fibres nearer the converged "
                        "field (python -m hyper.bench convergence --fibres-limit); 0: on this mesh (default: "
                        f"{FLOW_CELLS_FACTOR} x --cells with --method laplace, this mesh with --method stokes)")
    p.add_argument("--fibers-smoothing", type=cli.number(0, 50), default=FIBERS_SMOOTHING_MM,
                   metavar="MM", help="--method stokes: the Stokes velocity smoothed over this length before its "
                   "direction is taken (hyper.fem.fibers.smoothed: the fibres then converge with the mesh on the strap "
                   "muscles); 0: none, the paper's")
    p.add_argument("--method", choices=METHODS, default=DEFAULT_METHOD,
                   help="the mesh's fibres: the potential flow between the ends (laplace: hyper.fem.laplace, "
                        "converges with the mesh where Stokes does not), the paper's Stokes flow, or "
                        "pennate fibres between --origin and --insertion (hyper.fem.pennate; patch syntax: "
                        "hyper fibers --help)")
    p.add_argument("--origin", default=pennate.DEFAULT_ORIGIN, metavar="PATCH",
                   help="pennate: the origin aponeurosis, tagged on the mesh and recorded in its fibre file")
    p.add_argument("--insertion", default=pennate.DEFAULT_INSERTION, metavar="PATCH",
                   help="pennate: the insertion aponeurosis")
    p.add_argument("--force", action="store_true", help="replace an existing output folder")
    p.add_argument("--fibers", metavar="FILE", help=f"the mesh's fibres from data instead of its Stokes fibres: "
                   f"{presets.DATA_HELP} (the surface's frame); stored as the folder's {fibers.FILE_NAME}, which "
                   "runs on the mesh then use, compared with the Stokes fibres, with a picture fibers.png")
    cli.fibre_data_options(p)
    return p


def build(args) -> dict:
    """Read, check, mesh and tag on rank 0 (`hyper.fem.meshing`'s docstring, steps 1-4); the arrays in mm."""
    path = args.surface
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    start = time.perf_counter()
    points, triangles = hm.read_stl(path)
    hm.check_size(path, points, args.unit)
    hm.check_surface(path, points, triangles)
    checked = time.perf_counter()
    points_mm = points * hm.UNITS_MM[args.unit]
    hm.check_meshable(path, points_mm, triangles, args.cells)
    x, tets = hm.tetrahedralize(points_mm, triangles, args.cells, args.axis, args.gmsh_budget)
    x, offset = hm.fill_surface(x, tets, hm.enclosed_volume(points_mm, triangles))
    tets, quality = hm.check_quality(x, tets)
    quality["surface_offset_mm"] = offset
    facets = hm.boundary_facets(tets)
    frame = hm.surface_frame(points_mm, triangles) if args.end_rule == "surface" else None
    tags, rule = hm.find_ends(x, facets, band=args.end_band, axis=args.axis, origin_toward=args.origin_toward,
                              frame=frame)
    areas = hm.facet_areas(x, facets)
    return {"x": x, "tets": tets, "facets": facets, "tags": tags, "rule": rule, "quality": quality,
            "surface_triangles": len(triangles), "check_s": checked - start,
            "mesh_s": time.perf_counter() - checked,
            "end_area_mm2": [float(areas[tags == 1].sum()), float(areas[tags == 2].sum())],
            "sha256": hashlib.sha256(path.read_bytes()).hexdigest()}


def flow_mesh(comm, args, path: Path, cells: int) -> geo.Geometry:
    """The surface meshed again at ``cells`` (rank 0, by the same steps and end rule),
    written to ``path`` and loaded: the mesh the fibres' flow is solved on."""
    built = error = None
    if comm.rank == 0:
        try:
            built = build(argparse.Namespace(**{**vars(args), "cells": cells}))
        except InputError as err:
            error = f"--flow-cells {cells}: {err}"
    error = comm.bcast(error, root=0)
    if error is not None:
        raise InputError(error)
    if comm.rank == 0:
        path.parent.mkdir()
    arrays = [built[k] for k in ARRAYS] if comm.rank == 0 else [None] * len(ARRAYS)
    hm.write_xdmf(comm, path, *arrays)
    return geo.load_file(path, comm, name=path.stem, scale=geo.MM)


def end_to_end_fibres(comm, args, geometry: geo.Geometry, flow_path: Path):
    """(a0, speed, method, parameters) of the flow from end to end that ``args.method`` asks
    for: Laplace, or Stokes on this mesh or on --flow-cells' (meshed at ``flow_path``). The
    pennate fibres and fibres from data replace these afterwards, which are then only their
    statistics."""
    cells = flow_cells(args)
    if args.method == "laplace" and args.fibers is None:  # fibres from data are compared with Stokes'
        params = laplace.LaplaceParams()
        if not cells:
            return *laplace.compute(geometry, params), laplace.method(params), params
        flow = flow_mesh(comm, args, flow_path, cells)
        a0, speed = fibers.carried_over(*laplace.compute(flow, params), geometry, params.min_speed)
        return a0, speed, laplace.method(params) + fibers.TRANSFERRED_METHOD.format(cells=flow.num_cells()), params
    params = fibers.StokesParams(smoothing_m=args.fibers_smoothing * geo.MM)
    if not cells:
        return *fibers.compute(geometry, params), fibers.stokes_method(params), params
    flow = flow_mesh(comm, args, flow_path, cells)
    a0, speed = fibers.compute_transferred(geometry, flow, params)
    return a0, speed, fibers.stokes_method(params) + fibers.TRANSFERRED_METHOD.format(cells=flow.num_cells()), params


def flow_cells(args) -> int:
    """The cells of the mesh the end-to-end flow is solved on (0: the mesh itself): --flow-cells,
    else FLOW_CELLS_FACTOR x --cells for the Laplace fibres of a surface."""
    if args.flow_cells is not None:
        return args.flow_cells
    if args.method == "laplace" and args.fibers is None:
        return min(FLOW_CELLS_FACTOR * args.cells, hm.MAX_CELLS)
    return 0


def run(comm, args) -> int:
    out = args.output
    name = out.name
    if out.suffix or not name:
        raise InputError(f"--output {out}: expected a folder, meshes/NAME/")
    if out.exists() and not args.force:
        raise InputError(f"--output {out}: exists; give --force to replace it")
    source = presets.data_source(args, ())
    if args.method != "pennate" and (args.origin, args.insertion) != (pennate.DEFAULT_ORIGIN,
                                                                      pennate.DEFAULT_INSERTION):
        raise InputError("--origin and --insertion are the attachments of --method pennate")
    if args.method == "pennate" and source is not None:
        raise InputError("--method pennate and --fibers FILE: the fibres come from one or the other")
    if args.method == "laplace" and args.fibers is None and args.fibers_smoothing != FIBERS_SMOOTHING_MM:
        raise InputError("--fibers-smoothing: the Stokes flow's (--method stokes); the Laplace fibres are smoothed "
                         f"over {laplace.LaplaceParams().smoothing_m * 1e3:g} mm")
    # the patches parsed before any meshing: a bad one writes nothing
    patches = (pennate.parse(args.origin, "--origin"), pennate.parse(args.insertion, "--insertion")) \
        if args.method == "pennate" else None
    built = error = None
    if comm.rank == 0:
        try:
            built = build(args)
        except InputError as err:
            error = str(err)
    error = comm.bcast(error, root=0)
    if error is not None:
        raise InputError(error)
    # The arrays stay on rank 0, which hands the cells to DOLFINx; every rank gets the rest.
    arrays = {k: built.pop(k) for k in ARRAYS} if comm.rank == 0 else dict.fromkeys(ARRAYS)
    built = comm.bcast(built, root=0)
    stage = out.with_name(name + ".partial")
    if comm.rank == 0:
        shutil.rmtree(stage, ignore_errors=True)
        stage.mkdir(parents=True)
    comm.barrier()
    try:
        start = time.perf_counter()
        hm.write_xdmf(comm, stage / f"{name}.xdmf", *(arrays[k] for k in ARRAYS))
        geometry = geo.load_file(stage / f"{name}.xdmf", comm, name=name, scale=geo.MM)
        a0, speed, method, params = end_to_end_fibres(comm, args, geometry, stage / "flow" / f"{name}.xdmf")
        stats = {**fibers.statistics(geometry, a0, speed), "solve_s": time.perf_counter() - start}
        # only the Stokes fibres are written here (the other kinds' store functions gather their own)
        data = fibers.gather_nodal(a0, speed) if args.method == "stokes" and source is None else None
        row = meshstats.statistics(geometry)
        field = None
        if source is not None:
            a0, field = fiberdata.make(geometry, source, a0)
            sha = on_rank0(comm, lambda: hashlib.sha256(source.path.read_bytes()).hexdigest())
            fiberdata.store(stage / fibers.FILE_NAME, geometry, a0, field, source, sha, mesh=f"{name}/{name}.xdmf")
            fibers_job.picture(geometry, a0, field, stage / "fibers.png", f"{name}: fibres from {source.path.name}")
        if patches is not None:
            result = pennate.compute(geometry, *patches)
            a0 = result.a0
            architecture = pennate.statistics(result)
            pennate.store(stage / fibers.FILE_NAME, result, architecture, mesh=f"{name}/{name}.xdmf")
            info(comm, f"{name}: pennate fibres, pennation angle mean {architecture['pennation_deg_mean']:.1f}°, "
                       f"5/50/95 % {architecture['pennation_deg_p5']:.1f}/{architecture['pennation_deg_p50']:.1f}/"
                       f"{architecture['pennation_deg_p95']:.1f}°")
        if args.method == "laplace" and source is None:
            laplace.store(stage / fibers.FILE_NAME, geometry, a0, speed, params, method, mesh=f"{name}/{name}.xdmf",
                          solve_s=stats["solve_s"])
        cells = fibers.cell_fibers(geometry, a0)
        if comm.rank == 0 and source is None and args.method == "stokes":
            write_series(stage / fibers.FILE_NAME, data,
                         attrs={"geometry": name, "mesh": f"{name}/{name}.xdmf", "method": method,
                                "element": fibers.ELEMENT, "reference": "Varvik et al. 2021; MODEL.md §5",
                                "inflow_tag": 1, "outflow_tag": 2, "lateral_tag": 3, "coordinates": "m",
                                "ranks": comm.size, **stats},
                         groups={"parameters": as_attributes(params)})
        flow_target = flow_cells(args)
        if comm.rank == 0:
            shutil.rmtree(stage / "flow", ignore_errors=True)
            record = {"source": str(args.surface), "source_sha256": built["sha256"], "unit": args.unit,
                      "mesher": f"gmsh {hm.gmsh_version()}", "cells_target": args.cells,
                      **({"flow_cells_target": flow_target} if flow_target else {}),
                      "surface_triangles": built["surface_triangles"], "ends": built["rule"],
                      "fibres_method": "data" if source is not None else args.method,
                      # the Stokes flow's, where one was solved (fibres from data are compared with it)
                      **({"fibers_smoothing_mm": args.fibers_smoothing}
                         if args.method == "stokes" or source is not None else {}),
                      "end_area_mm2": built["end_area_mm2"], "quality": built["quality"],
                      "statistics": {k: v for k, v in row.items() if k != "geometry"},
                      "fibers": {k: float(v) for k, v in stats.items()},
                      **({} if patches is None else {"pennate": {"origin": args.origin, "insertion": args.insertion,
                                                                 **{k: float(v) for k, v in architecture.items()}}}),
                      **({} if field is None else {"fibers_from_data": {"source": str(source.path),
                                                                        "source_sha256": sha,
                                                                        "method": fiberdata.method(source, field),
                                                                        **field.report}}),
                      "check_s": built["check_s"], "mesh_s": built["mesh_s"]}
            write_json(stage / "mesh.json", record)
            axis = np.asarray(built["rule"]["axis"])
            plot.save(figure(name, arrays["x"], arrays["facets"], arrays["tags"], cells[0], cells[1], axis,
                             FIGURE_LABEL[args.method] if field is None else "fibres from data"), stage / f"{name}.png",
                      dpi=110)
            if out.exists():
                shutil.rmtree(out)
            os.replace(stage, out)
    finally:
        if comm.rank == 0:
            shutil.rmtree(stage, ignore_errors=True)
        comm.barrier()
    q = built["quality"]
    # the end-to-end flow's statistics (pennate fibres and fibres from data report their own above)
    flow = "Laplace" if args.method == "laplace" and source is None else "Stokes"
    info(comm, f"{name}: {row['cells']} cells, {row['vertices']} vertices, min dihedral angle "
               f"{q['min_dihedral_deg']:.1f}°; volume {row['volume_cm3']:.2f} cm³, CSA0 {row['csa0_cm2']:.2f} cm², "
               f"length {row['length_cm']:.2f} cm; ends {built['end_area_mm2'][0]:.0f} and "
               f"{built['end_area_mm2'][1]:.0f} mm²; {flow} fibres (--method {args.method}"
               f"{f', the flow on a {flow_target}-cell mesh of the surface: --flow-cells' if flow_target else ''}) "
               f"within 30° of the axis "
               f"{100 * stats['share_within_30deg']:.1f} %; checks {built['check_s']:.1f} s, mesh "
               f"{built['mesh_s']:.1f} s, fibres {stats['solve_s']:.1f} s")
    if field is not None:
        info(comm, f"{name}: fibres from {source.path}: {fiberdata.summary(field)}")
    info(comm, f"wrote {out}/")
    return cli.EXIT_OK


def figure(name: str, x_mm, facets, tags, centroid_m, fiber, axis, what: str = "Stokes fibres"):
    """Left: the surface seen across its axis, ends coloured; right: fibre glyphs on the mid-slab."""
    from matplotlib.collections import LineCollection, PolyCollection

    plt = plot.pyplot()
    centre = x_mm.mean(axis=0)
    across = np.linalg.svd((x_mm - centre) - np.outer((x_mm - centre) @ axis, axis), full_matrices=False)[2][0]
    depth = np.cross(axis, across)
    basis = np.vstack([axis, across, depth])
    p = (x_mm - centre) @ basis.T
    # As high as the muscle's side view needs: a fixed height left most of a long muscle's picture blank.
    aspect = np.ptp(p[:, 1]) / np.ptp(p[:, 0])
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 1.4 + 5.6 * aspect), layout="constrained")
    corners = p[facets]
    order = np.argsort(corners[:, :, 2].mean(axis=1))  # far facets first: the near ones cover them
    colours = np.array(["#c0392b", "#1f5f99", "#cccccc"])[tags[order] - 1]
    left.add_collection(PolyCollection(corners[order][:, :, :2], facecolors=colours, edgecolors="0.5",
                                       linewidths=0.1))
    left.autoscale()
    left.set_aspect("equal")
    left.set_title("surface: red origin (1), blue insertion (2), grey lateral (3)", fontsize=10)
    q = (centroid_m * 1e3 - centre) @ basis.T
    d = fiber @ basis.T
    slab = np.abs(q[:, 2]) < 0.08 * np.ptp(q[:, 2])
    glyph = 0.012 * np.ptp(q[:, 0])
    uv = d[slab][:, :2] / np.maximum(np.linalg.norm(d[slab][:, :2], axis=1), 1e-12)[:, None] * glyph
    angle = np.degrees(np.arccos(np.clip(np.abs(d[slab][:, 0]), 0.0, 1.0)))
    cmap, norm = plt.get_cmap("viridis"), plt.Normalize(0.0, 45.0)
    right.add_collection(LineCollection(np.stack([q[slab][:, :2] - uv, q[slab][:, :2] + uv], axis=1),
                                        colors=cmap(norm(angle)), linewidths=1.0))
    right.set_xlim(left.get_xlim())
    right.set_ylim(left.get_ylim())
    right.set_aspect("equal")
    right.set_title(f"{what} on the mid-slab ({slab.sum()} cells), colour: angle to the axis (0-45°)",
                    fontsize=10)
    for ax in (left, right):
        ax.set_xlabel("along the axis, toward the origin (mm)")
    left.set_ylabel("across (mm)")
    fig.suptitle(name)
    return fig


main = cli.entry(parser, run, locks=lambda args: [args.output])

if __name__ == "__main__":
    sys.exit(main())
