"""Spatial convergence of a muscle's headline numbers: meshes of one surface at several
resolutions, and which of fibres and mechanics carries the error.

    python -m hyper.bench convergence [MUSCLE] [--cells 4000 8000 16000 32000] [--quick]
    python -m hyper.bench convergence --all [ID …] [--quick] (every muscle, one table)
    python -m hyper.bench convergence --fibres-only ID … (the fixed-geometry fibre check)
    python -m hyper.bench convergence --fibres-limit [ID …] (the shipped fibres to the converged field)
    python -m hyper.bench convergence --spatial-table DIR … (fidelity's table, no runs)

MUSCLE: a shipped or meshed geometry id whose surface is known (the 12 paper muscles:
their Visible Human STL in --surfaces, origin at the shipped tag 1; the meshed ones: the
source their mesh.json records), or an STL file (mm). Each level is the surface meshed by
`hyper mesh --cells N` (kept under OUTPUT/convergence/NAME/ and reused), with its fibres
(--fibres-method: Laplace, `hyper.fem.laplace`, hyper mesh's default; or the paper's Stokes
fibres; a study kept before the option is a Stokes one). Per level, with two fibre fields:

    own      the level's own fibres (what a run on that mesh uses)
    finest   the finest level's fibres interpolated onto the level's nodes (unit there):
             only the mechanics' resolution changes between levels

the 9-week `mwf` CSA gain (the exact cut) and volume gain (%, default settings and
parameters), and the end force at full activation α = 1 (the headline of `hyper
contraction`; α in 6 steps, each halved up to twice where Newton fails; a failure is
recorded; with --quick own fibres only); the fibre field's angle to the finest field at
the level's nodes (mean and 95th percentile, °).

From the three finest levels of each series, with h = (V / cells)^(1/3): the observed
order p solving (f1 - f2) / (f2 - f3) = (h1^p - h2^p) / (h2^p - h3^p) (none where the
changes alternate in sign, p falls outside 0.3-6 or the limit lies further from f3 than
f1 does: the levels are not asymptotic), the Richardson limit
f3 + (f3 - f2) / ((h2/h3)^p - 1), and each level's estimated error |f - limit| as a
fraction of the growth (|f - limit| / limit for the force); without an order, the
finest levels' spread |f3 - f2| stands for the finest level's error, and |f - f3| + that
for the others. The error of the own-fibre series less that of the finest-fibre series
is the fibres' share.

The runs of a study (per level: growth with each fibre field, the end force) are farmed
over the ranks (`hyper.runs.farm`, longest first), each on one rank: `mpirun -n 2` gives
the numbers of one rank in about half the time.

--all [ID …]: the study of every muscle with a surface (or those named), each kept under
OUTPUT/convergence_all/ and reused, and one table of their finest levels (with --quick,
the default 8000 cells): gains, estimated errors, whether both gains are within
GROWTH_GOAL of the growth (convergence_all.json, .png).

--spatial-table DIR …: no runs; from the kept `--all` studies under the folders, each
muscle's estimated error at the default resolution (8000 cells) taken from its study with
the finest levels, printed as a table and as the lines of `hyper.runs.fidelity.SURFACE_STUDIES`
(OUTPUT/spatial_table.json, and .png: the error with the own and with the finest fibres).

--fibres-limit [ID …]: each shipped geometry's fibres (its fibre file: what a `--geometry`
run reads) against the converged field of its shape at its nodes. A mesh made from a
surface (the 19 of `make new-meshes`): the surface meshed as `hyper mesh` does (its end
rule) at --reference-cells (64000 and 128000), each level's Laplace fibres solved on it. A
paper fTetWild mesh, whose end patches are the paper's tags and no rule on a surface's:
its own polyhedron, refined uniformly once and twice. The finest field is the reference;
the change between the two finest levels stands for the finest's own distance to the limit,
and the sum with the fibres' angle bounds theirs (the 95th percentile, °; the goal
FIBRES_GOAL_DEG). For the meshed ones also the flow on the mesh itself (hyper mesh before
--flow-cells became its default). Each geometry a job on one rank, kept under
OUTPUT/fibres_limit/ and reused (fibres_limit.json, .png).

--fibres-only ID …: the Stokes fibres of each geometry at the default Taylor–Hood P2-P1
against P3-P2 on the same mesh (the same polyhedron, one order higher): mean, 95th
percentile and largest angle at the nodes, and the seconds and peak memory of the P3
solve; this bounds the discretisation error of the fibre field at the mesh's own geometry.

Writes OUTPUT/convergence_NAME.json and .png (or convergence_fibres.json).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import resource
import shutil
import sys
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np
from dolfinx import fem
from mpi4py import MPI

from hyper.commands import cli
from hyper.commands import mesh as mesh_job
from hyper.commands.bench import common
from hyper.commands.bench import mesh as mesh_bench
from hyper.core import io
from hyper.core.log import info
from hyper.core.params import InputError
from hyper.fem import fiberread as fr
from hyper.fem import fibers, laplace
from hyper.fem import geometry as geo
from hyper.fem import meshing as hm
from hyper.fem.coupled import GrowthSettings, build_model
from hyper.fem.mechanics import MechanicsProblem, SolverError
from hyper.model import protocols
from hyper.model.failure import GrowthFailure
from hyper.runs import contraction, farm, fidelity, plot

PROTOCOL = "mwf"
CELLS = (4000, 8000, 16000, 32000)
QUICK_CELLS = (1000, 2000, 4000, 8000)
ALPHAS = (0.1, 0.2, 0.35, 0.55, 0.8, 1.0)
MAX_HALVINGS = 2  # of an α step whose Newton solve fails (a failure costs minutes; more rarely help)
VARIANTS = ("own", "finest")
# the CSA gain on the vertices' plane (the feedback's), on the solid's plane (`coupled.PlaneSection`)
QUANTITIES = ("csa_gain_pct", "csa_solid_gain_pct", "volume_gain_pct", "end_force_n")
ORDER_RANGE = (0.3, 6.0)  # observed orders outside it are taken as no order
FIBRES_GOAL_DEG = 3.0  # issue 32: the default mesh's fibres within 3° (95th percentile) of the converged field
GROWTH_GOAL = 5e-3  # issue 32: the default mesh's CSA and volume gains within 0.5 % of the growth of their limit


# ---------------------------------------------------------------------------- source


def source(muscle: str, surfaces: Path) -> tuple[str, Path, list[str]]:
    """(name, STL, extra `hyper mesh` options) of ``muscle``: an STL path or a geometry id."""
    path = Path(muscle)
    if path.suffix.lower() == ".stl":
        if not path.is_file():
            raise InputError(f"{path}: no such file")
        return path.stem.split("_smooth")[0], path, []
    if muscle in geo.ANATOMICAL:
        stl = surfaces / f"{Path(geo.GEOMETRIES[muscle]).parent.name}.stl"
        if not stl.is_file():
            raise InputError(f"{muscle}: no surface {stl} (the right BFLH of the female has none); give --surfaces")
        return muscle, stl, ["--origin-toward", *map(str, mesh_bench.shipped(muscle)["toward"])]
    if muscle in geo.MESHED:
        record = json.loads((geo.MESHES_DIR / muscle / "mesh.json").read_text())
        stl = Path(record["source"])
        stl = stl if stl.is_absolute() else geo.MESHES_DIR.parent / stl
        if not stl.is_file():
            stl = surfaces / Path(record["source"]).name
        if not stl.is_file():
            raise InputError(f"{muscle}: its source surface {record['source']} is not found; give --surfaces")
        return muscle, stl, ["--origin-toward", *map(str, record["ends"]["origin_toward"])]
    raise InputError(f"{muscle!r}: expected an STL file or a geometry id with a surface "
                     f"({', '.join(geo.ANATOMICAL[:3])}, …, or one of meshes/)")


def level_mesh(comm, name: str, stl: Path, extra: list[str], cells: int, root: Path, force: bool,
               method: str) -> Path:
    """The folder of `hyper mesh STL --cells CELLS --method METHOD`, made once (reused unless
    ``force``; a record without a method is an older Stokes one)."""
    folder = root / f"{name}_c{cells}"
    record = folder / "mesh.json"
    done = comm.bcast(record.is_file() and made_as(json.loads(record.read_text()), cells, method)
                      if comm.rank == 0 else None, root=0)
    if done and not force:
        return folder
    # each level's fibres solved on the level itself (the "finest" variant carries the finest's)
    status = mesh_job.main([str(stl), "--output", str(folder), "--force", "--cells", str(cells),
                            "--method", method, "--flow-cells", "0", *extra], comm=comm)
    if status != cli.EXIT_OK:
        raise InputError(f"{name}: hyper mesh --cells {cells} failed (exit {status})")
    return folder


def fibres_method(record: dict) -> str:
    """The fibres of a level's mesh.json or a kept study: one written before --fibres-method is a Stokes one."""
    return record.get("fibres_method", "stokes")


def made_as(record: dict, cells: int, method: str) -> bool:
    return record.get("cells_target") == cells and fibres_method(record) == method


def load_level(comm, folder: Path) -> geo.Geometry:
    return geo.load_file(folder / f"{folder.name}.xdmf", comm, name=folder.name, scale=geo.MM)


# ---------------------------------------------------------------------- fibre fields


def unit(a0: fem.Function) -> fem.Function:
    values = a0.x.array.reshape(-1, 3)
    values /= np.linalg.norm(values, axis=1)[:, None]
    return a0


def angles(a: fem.Function, b: fem.Function) -> dict:
    """Angle (°) between two vector P1 fields of one space at its owned nodes, as lines
    (a fibre and its reverse are one direction): mean, 95th percentile, largest."""
    n = a.function_space.dofmap.index_map.size_local
    x, y = a.x.array.reshape(-1, 3)[:n], b.x.array.reshape(-1, 3)[:n]
    cosine = np.abs(np.einsum("ij,ij->i", x, y)) / (np.linalg.norm(x, axis=1) * np.linalg.norm(y, axis=1))
    local = np.degrees(np.arccos(np.clip(cosine, 0.0, 1.0)))
    comm = a.function_space.mesh.comm
    every = np.concatenate(comm.allgather(local))
    return {"mean_deg": float(every.mean()), "p95_deg": float(np.percentile(every, 95)),
            "max_deg": float(every.max())}


# ----------------------------------------------------------------------- the numbers


def growth(geometry: geo.Geometry, a0: fem.Function) -> dict:
    """The 9-week `mwf` CSA (cut) and volume gains (%), default settings, and the wall time."""
    start = time.perf_counter()
    model = build_model(geometry, a0, protocols.named(PROTOCOL), settings=GrowthSettings())
    *_, last = model.run()
    return {"csa_gain_pct": 100.0 * (last.csa_ratio - 1.0), "volume_gain_pct": 100.0 * (last.volume_ratio - 1.0),
            "csa_solid_gain_pct": 100.0 * (last.extra["csa_ratio_solid"] - 1.0),
            "growth_s": time.perf_counter() - start}


def end_force(geometry: geo.Geometry, a0: fem.Function) -> dict:
    start = time.perf_counter()
    problem = MechanicsProblem(geometry, a0)
    try:
        for alpha in ALPHAS:
            contraction.advance(problem, alpha, MAX_HALVINGS)
    except SolverError as err:  # some coarse gmsh meshes of the TA buckle near α = 0.9
        return {"end_force_n": None, "end_force_failed": str(err), "force_s": time.perf_counter() - start}
    return {"end_force_n": problem.end_force(), "force_s": time.perf_counter() - start}


def shown_force(numbers: dict) -> str:
    if "end_force_n" not in numbers:
        return "not asked"
    if numbers["end_force_n"] is None:
        return "failed"
    return f"{numbers['end_force_n']:.5f} N ({numbers['force_s']:.0f} s)"


def observed(h: list[float], f: list[float]) -> float | None:
    """The order p of f = f* + C h^p through the last three points, by bisection; None
    where the changes alternate in sign or no p in ORDER_RANGE fits."""
    (h1, h2, h3), (f1, f2, f3) = h[-3:], f[-3:]
    d1, d2 = f1 - f2, f2 - f3
    if d1 == 0.0 or d2 == 0.0 or (d1 > 0) != (d2 > 0):
        return None
    ratio = d1 / d2

    def misfit(p):
        return (h1**p - h2**p) / (h2**p - h3**p) - ratio

    lo, hi = ORDER_RANGE
    if misfit(lo) * misfit(hi) > 0:
        return None
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if misfit(lo) * misfit(mid) > 0 else (lo, mid)
    return 0.5 * (lo + hi)


def estimate(h: list[float], f: list[float], relative_to_growth: bool) -> dict:
    """Order, Richardson limit and each level's estimated error (module docstring)."""
    p = observed(h, f) if len(f) >= 3 else None
    if p is not None:
        limit = f[-1] + (f[-1] - f[-2]) / ((h[-2] / h[-1]) ** p - 1.0)
        if abs(limit - f[-1]) > abs(f[-1] - f[-3]):  # further out than the levels spread: not asymptotic
            p = None
    if p is not None:
        errors = [abs(v - limit) for v in f]
    else:
        limit = f[-1]
        spread = abs(f[-1] - f[-2])
        errors = [abs(v - f[-1]) + spread for v in f]
    scale = abs(limit)  # a gain in % is itself the growth
    return {"values": list(f), "order": p, "limit": limit,
            "errors": [e / scale for e in errors], "error_of": "the growth" if relative_to_growth else "the force"}


def study(comm, args) -> dict:
    name, stl, extra = source(args.muscle, args.surfaces)
    cells = sorted(args.cells if args.cells else (QUICK_CELLS if args.quick else CELLS))
    if len(cells) < 3:
        raise InputError("--cells: at least three resolutions (four or more for a check of the order)")
    root = args.output / "convergence" / name
    start = time.perf_counter()
    asked, folders, dropped = list(cells), [], {}
    for n in asked:
        try:
            folders.append(level_mesh(comm, name, stl, extra, n, root, args.force, args.fibres_method))
        except InputError as err:  # a thin muscle cannot be meshed at the coarsest sizes
            if folders:  # a finer level failing where a coarser one worked is no thin muscle: stop
                raise
            dropped[n] = str(err)
            info(comm, f"{name}: level {n} dropped: {err}")
    cells = [n for n in asked if n not in dropped]
    if len(cells) < 3:
        raise InputError(f"{name}: only {len(cells)} of the levels {asked} could be meshed; give finer --cells")
    results = farm.run(comm, level_jobs(cells, args), lambda sub, job: level_job(sub, folders, job),
                       label=f"convergence {name} ({args.fibres_method} fibres)")
    failed = [r for r in results if r.status != "done"]
    if failed:
        raise InputError(f"{failed[0].key}: {farm.summary_line(results)}: {failed[0].error.strip().splitlines()[-1]}; "
                         "take finer levels (--cells)")
    rows = []
    for i, (n, folder) in enumerate(zip(cells, folders)):
        done = {r.key.split("/", 1)[1]: r for r in results if r.key.split("/")[0] == str(i)}
        row = {"cells_target": n, **done["own/growth"].result.pop("level"),
               "fibre_angle_to_finest": (done["finest/growth"].result.pop("fibre_angle_to_finest")
                                         if "finest/growth" in done else {"mean_deg": 0.0, "p95_deg": 0.0,
                                                                          "max_deg": 0.0})}
        for variant in VARIANTS:
            if variant == "finest" and i == len(cells) - 1:
                row[variant] = row["own"]  # the same field
                continue
            row[variant] = {**done[f"{variant}/growth"].result,
                            **(done[f"{variant}/force"].result if f"{variant}/force" in done else {})}
        row["wall_s"] = sum(r.wall_s for r in done.values())  # the level's jobs, wherever they ran
        rows.append(row)
        a = row["fibre_angle_to_finest"]
        info(comm, f"{folder.name}: {row['cells']} cells, h {row['h_mm']:.2f} mm; fibres to the finest: mean "
                   f"{a['mean_deg']:.2f}°, p95 {a['p95_deg']:.2f}°; "
                   + "; ".join(f"{v}: CSA {row[v]['csa_gain_pct']:+.4f} %, V {row[v]['volume_gain_pct']:+.4f} % "
                               f"({row[v]['growth_s']:.0f} s), force {shown_force(row[v])}" for v in VARIANTS)
                   + f" ({row['wall_s']:.0f} s of jobs)")
    return {"benchmark": "convergence", "muscle": name, "surface": str(stl), "fibres_method": args.fibres_method,
            "protocol": PROTOCOL,
            "quick": bool(args.quick), "ranks": comm.size, "machine": common.machine(), "cells_asked": asked,
            "dropped_levels": dropped, "levels": rows,
            "estimates": estimates_of(rows), "wall_s": comm.allreduce(time.perf_counter() - start, op=MPI.MAX),
            "jobs": [{"key": r.key, "rank": r.group, "wall_s": r.wall_s} for r in results],
            "versions": io.versions()}


def level_jobs(cells: list[int], args) -> list[farm.Job]:
    """The study's independent runs, farmed over the ranks (each on one): per level the
    growth with its own and with the finest fibres (the finest level: own only), and the
    end force where asked (--quick: own fibres only). Costs: cells, the force about four
    growths (measured on ST_VHM_Right's quick study)."""
    jobs = []
    for i, n in enumerate(cells):
        for variant in VARIANTS:
            if variant == "finest" and i == len(cells) - 1:
                continue
            jobs.append(farm.Job(f"{i}/{variant}/growth", cost=float(n), payload=(i, variant, "growth")))
            if args.force_at_full_activation and not (args.quick and variant == "finest"):
                jobs.append(farm.Job(f"{i}/{variant}/force", cost=4.0 * n, payload=(i, variant, "force")))
    return jobs


def level_job(comm, folders: list[Path], job: farm.Job) -> dict:
    """One of `level_jobs` on ``comm``: the growth numbers (with the level's size and, for
    the finest fibres, their angle to its own) or the end force."""
    i, variant, what = job.payload
    folder = folders[i]
    geometry = load_level(comm, folder)
    own = fibers.load(geometry, folder / fibers.FILE_NAME)
    a0 = own
    out = {}
    if variant == "finest":
        finest = fibers.load(load_level(comm, folders[-1]), folders[-1] / fibers.FILE_NAME)
        a0 = unit(fibers.transferred(finest, geometry))
    if what == "force":
        return end_force(geometry, a0)
    if variant == "finest":
        out["fibre_angle_to_finest"] = angles(own, a0)
    try:
        out.update(growth(geometry, a0))
    except GrowthFailure as err:
        raise InputError(f"{folder.name} ({variant} fibres): {err}") from None
    if variant == "own":
        volume = geometry.reference_volume()
        out["level"] = {"cells": geometry.num_cells(), "vertices": geometry.mesh.topology.index_map(0).size_global,
                        "h_mm": (volume / geometry.num_cells()) ** (1 / 3) / geo.MM, "volume_m3": volume}
    return out


def estimates_of(rows: list[dict]) -> dict:
    """`estimate` of every quantity and fibre field with three levels or more that have it."""
    estimates = {}
    for q in QUANTITIES:
        for v in VARIANTS:
            kept = [(r["h_mm"], r[v][q]) for r in rows if r[v].get(q) is not None]
            if len(kept) >= 3:
                estimates.setdefault(q, {})[v] = {**estimate(*map(list, zip(*kept)), q != "end_force_n"),
                                                   "h_mm": [k[0] for k in kept]}
    for q in estimates:
        if "finest" not in estimates[q]:
            continue
        own, fine = estimates[q]["own"], estimates[q]["finest"]
        own["fibres_share"] = [max(0.0, a - b) for a, b in zip(own["errors"], fine["errors"])]
    return estimates


def fibre_check(comm, name: str) -> dict:
    """The stored (or computed) P2 Stokes fibres of ``name`` against P3-P2 on the same mesh."""
    geometry = geo.load(name, comm)
    path = fibers.fiber_path(name, kind="stokes")
    p2 = fibers.load(geometry, path) if io.is_complete(path) else fibers.compute(geometry)[0]
    start = time.perf_counter()
    p3, speed = fibers.compute(geometry, fibers.StokesParams(degree=3))
    seconds = comm.allreduce(time.perf_counter() - start, op=MPI.MAX)
    rss = comm.allreduce(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, op=MPI.MAX) / 1024
    return {"geometry": name, "cells": geometry.num_cells(), **angles(p2, p3), "p3_solve_s": seconds,
            "peak_rss_mb": rss, "p3_min_speed": fibers.statistics(geometry, p3, speed)["min_speed"]}


# ----------------------------------------------------------------------- --fibres-all


def fibre_muscles(surfaces: Path) -> list[str]:
    """The paper's muscles whose Visible Human surface is in ``surfaces``, and the new ones
    (their mesh.json names the surface)."""
    return [name for name in geo.ANATOMICAL if (surfaces / f"{Path(geo.GEOMETRIES[name]).parent.name}.stl").is_file()
            ] + list(geo.NEW)


def surface_mesh(comm, stl: Path, extra: list[str], cells: int, scratch: Path) -> geo.Geometry:
    """The surface meshed as `hyper mesh STL --cells CELLS EXTRA` does, written under ``scratch``."""
    options = mesh_job.parser().parse_args([str(stl), "--output", str(scratch / "unused"), "--cells", str(cells),
                                           *extra])
    return mesh_job.flow_mesh(comm, options, scratch / f"c{cells}" / f"c{cells}.xdmf", cells)


def fibre_level(comm, stl: Path, extra: list[str], cells: int, scratch: Path, smoothings: tuple[float, ...]):
    """The surface meshed as `hyper mesh --cells CELLS` does, its Stokes flow solved once and
    smoothed over each length of ``smoothings`` (mm): (geometry, {l: (a0, speed)}, timings)."""
    start = time.perf_counter()
    geometry = surface_mesh(comm, stl, extra, cells, scratch)
    meshed = time.perf_counter()
    stokes = fibers.StokesFibers(geometry)
    u = stokes.solve()
    solved = time.perf_counter()
    fields, smoothing_s = {}, {}
    for length in smoothings:
        begin = time.perf_counter()
        fields[length] = fibers.normalized(fibers.smoothed(u, stokes.V1, length * geo.MM), stokes.params.min_speed,
                                           geometry.name)
        smoothing_s[f"{length:g}"] = time.perf_counter() - begin
    del stokes, u
    times = {"cells": geometry.num_cells(), "mesh_s": meshed - start, "stokes_s": solved - meshed,
             "smoothing_s": smoothing_s,
             "min_speed": {f"{k:g}": fibers.statistics(geometry, *v)["min_speed"] for k, v in fields.items()}}
    return geometry, fields, {k: comm.allreduce(v, op=MPI.MAX) if isinstance(v, float) else v
                              for k, v in times.items()}


def fibre_errors(comm, muscle: str, args) -> dict:
    """The fibres of ``muscle`` at --cells (own flow, and the flow of each --flow-cells mesh
    carried over) against the finest --reference-cells field at the same smoothing, at the
    default mesh's nodes; the coarser references against the finest at theirs."""
    name, stl, extra = source(muscle, args.surfaces)
    smoothings = tuple(args.fibres_smoothing)
    references = sorted(args.reference_cells)
    scratch = args.output / "fibres_all" / f"{name}.scratch"
    if comm.rank == 0:
        shutil.rmtree(scratch, ignore_errors=True)
        scratch.mkdir(parents=True)
    comm.barrier()
    start = time.perf_counter()
    levels, timings = {}, {}
    for cells in sorted({args.fibres_cells, *args.flow_cells, *references}):
        geometry, fields, t = fibre_level(comm, stl, extra, cells, scratch, smoothings)
        levels[cells], timings[str(cells)] = (geometry, fields), t
        info(comm, f"{name}: {cells} cells ({t['cells']}): mesh {t['mesh_s']:.1f} s, Stokes {t['stokes_s']:.1f} s")
    rows, carried = [], {}
    for length in smoothings:
        finest_geometry, finest_fields = levels[references[-1]]
        finest = finest_fields[length][0]
        default_geometry = levels[args.fibres_cells][0]
        cases = [("own", args.fibres_cells)] + [("flow", n) for n in sorted(args.flow_cells) if n < references[-1]] \
            + [("own", n) for n in references[:-1]]
        for fibres_of, cells in cases:
            begin = time.perf_counter()
            if fibres_of == "flow":
                a0 = fibers.carried_over(*levels[cells][1][length], default_geometry,
                                         fibers.StokesParams().min_speed)[0]
                at = default_geometry
            else:
                a0, at = levels[cells][1][length][0], levels[cells][0]
            transfer_s = time.perf_counter() - begin
            if (length, at.num_cells()) not in carried:  # the flow's cases share the default mesh's
                carried[length, at.num_cells()] = unit(fibers.transferred(finest, at))
            reference = carried[length, at.num_cells()]
            rows.append({"smoothing_mm": length, "fibres": fibres_of, "cells_target": cells,
                         "at_cells": at.num_cells(), "reference_cells_target": references[-1],
                         "reference_cells": finest_geometry.num_cells(), **angles(a0, reference),
                         "carry_s": comm.allreduce(transfer_s, op=MPI.MAX)})
    if comm.rank == 0:
        shutil.rmtree(scratch, ignore_errors=True)
    return {"muscle": name, "surface": str(stl), "options": extra, "levels": timings, "rows": rows,
            "wall_s": comm.allreduce(time.perf_counter() - start, op=MPI.MAX)}


# ---------------------------------------------------------------------------- chart


def chart(path: Path, result: dict) -> None:
    plt = plot.pyplot()
    rows = result["levels"]
    h = np.array([r["h_mm"] for r in rows])
    fig, axes = plt.subplots(1, 5, figsize=(21, 4.0))
    labels = {"csa_gain_pct": "CSA gain (%)", "csa_solid_gain_pct": "CSA gain on the solid's plane (%)",
              "volume_gain_pct": "volume gain (%)", "end_force_n": "end force α = 1 (N)"}
    for ax, q in zip(axes, QUANTITIES):
        for v, style in zip(VARIANTS, ("o-", "s--")):
            e = result["estimates"].get(q, {}).get(v)
            if e is None:
                continue
            order = f", order {e['order']:.2f}" if e["order"] is not None else ", no order"
            ax.plot(e["h_mm"], e["values"], style, label=f"{v} fibres{order}")
            ax.axhline(e["limit"], ls=":", lw=1, color=ax.lines[-1].get_color())
        ax.set_xscale("log")
        ax.invert_xaxis()
        ax.set_xlabel("h = (V / cells)^(1/3) (mm)")
        ax.set_ylabel(labels[q])
        ax.legend(fontsize=8)
    a = axes[4]
    a.plot(h[:-1], [r["fibre_angle_to_finest"]["mean_deg"] for r in rows[:-1]], "o-", label="mean")
    a.plot(h[:-1], [r["fibre_angle_to_finest"]["p95_deg"] for r in rows[:-1]], "s-", label="95th percentile")
    a.set_xscale("log")
    a.set_yscale("log")
    a.invert_xaxis()
    a.set_xlabel("h (mm)")
    a.set_ylabel("fibre angle to the finest field (°)")
    a.legend(fontsize=8)
    fig.suptitle(f"{result['muscle']}: {PROTOCOL} 9 weeks against mesh size (dotted: Richardson limits)")
    fig.tight_layout()
    plot.save(fig, path, dpi=120)


def fibre_chart(path: Path, result: dict) -> None:
    """p95 angle to the reference per muscle, one bar per fibre setting, the goal's line."""
    plt = plot.pyplot()
    muscles = [m["muscle"] for m in result["muscles"]]
    settings = sorted({(r["smoothing_mm"], r["fibres"], r["cells_target"]) for m in result["muscles"]
                       for r in m["rows"] if r["at_cells"] < r["reference_cells"] / 2})
    fig, ax = plt.subplots(figsize=(max(8.0, 0.45 * len(muscles) + 2), 4.5), layout="constrained")
    width = 0.8 / len(settings)
    for k, (length, fibres_of, cells) in enumerate(settings):
        p95 = [next((r["p95_deg"] for r in m["rows"] if (r["smoothing_mm"], r["fibres"], r["cells_target"])
                     == (length, fibres_of, cells)), np.nan) for m in result["muscles"]]
        label = f"{'flow at' if fibres_of == 'flow' else 'own flow,'} {cells} cells, l = {length:g} mm"
        ax.bar(np.arange(len(muscles)) + (k - (len(settings) - 1) / 2) * width, p95, width, label=label)
    ax.axhline(FIBRES_GOAL_DEG, color="k", ls="--", lw=1, label=f"goal {FIBRES_GOAL_DEG:g}°")
    ax.set_xticks(np.arange(len(muscles)), muscles, rotation=70, fontsize=8)
    ax.set_ylabel("fibres to the reference, 95th percentile (°)")
    ax.set_title(f"Stokes fibres at {result['cells']} cells against {result['reference_cells']} cells "
                 "(same smoothing), at the mesh's nodes")
    ax.legend(fontsize=8)
    plot.save(fig, path, dpi=120)


def fibre_cost_s(record: dict, row: dict) -> float:
    """Seconds `hyper mesh` spends on the mesh and its fibres under ``row``'s setting: the
    mesh at --cells, and the flow's mesh, Stokes solve, smoothing and carrying over."""
    own = record["levels"][str(record["settings"]["cells"])]
    flow = record["levels"][str(row["cells_target"])]
    length = f"{row['smoothing_mm']:g}"
    return own["mesh_s"] + (flow["mesh_s"] if row["fibres"] == "flow" else 0.0) + flow["stokes_s"] \
        + flow["smoothing_s"][length] + row["carry_s"]


def fibre_table(result: dict) -> list[str]:
    """The markdown table of docs/convergence.md: per muscle and setting at --cells, mean /
    p95 angle to the reference (°) and the seconds of the mesh with its fibres."""
    cases = sorted({(r["smoothing_mm"], r["fibres"], r["cells_target"]) for m in result["muscles"]
                    for r in m["rows"] if r["cells_target"] == result["cells"] or r["fibres"] == "flow"})
    head = " | ".join(f"l = {length:g} mm, {'flow at ' + str(n) if kind == 'flow' else 'own flow'}"
                      for length, kind, n in cases)
    lines = [f"| muscle | cells | {head} | seconds: {' / '.join(str(i + 1) for i in range(len(cases)))} |",
             "|---|---|" + "---|" * (len(cases) + 1)]
    for m in result["muscles"]:
        rows = {(r["smoothing_mm"], r["fibres"], r["cells_target"]): r for r in m["rows"]}
        cells = m["levels"][str(result["cells"])]["cells"]
        angles_ = " | ".join(f"{rows[c]['mean_deg']:.2f} / {rows[c]['p95_deg']:.2f}" for c in cases)
        seconds = " / ".join(f"{fibre_cost_s(m, rows[c]):.0f}" for c in cases)
        lines.append(f"| {m['muscle']} | {cells} | {angles_} | {seconds} |")
    meeting = [sum(rows["p95_deg"] <= FIBRES_GOAL_DEG for m in result["muscles"] for rows in m["rows"]
                   if (rows["smoothing_mm"], rows["fibres"], rows["cells_target"]) == c) for c in cases]
    lines.append(f"| within {FIBRES_GOAL_DEG:g}° (p95), of {len(result['muscles'])} | | "
                 + " | ".join(map(str, meeting)) + " | |")
    return lines


def kept(comm, path: Path, fits, force: bool) -> dict | None:
    """The record an earlier run kept at ``path`` (read on rank 0, shared) where
    ``fits(record)`` and not ``force``; None: run it anew."""
    record = None
    if comm.rank == 0 and not force and path.is_file():
        record = json.loads(path.read_text())
        record = record if fits(record) else None
    return comm.bcast(record, root=0)


def fibres_all(comm, args) -> int:
    muscles = args.fibres_all or fibre_muscles(args.surfaces)
    for name in muscles:
        if name not in (*geo.ANATOMICAL, *geo.MESHED) and Path(name).suffix.lower() != ".stl":
            raise InputError(f"--fibres-all: {name!r} is not an anatomical or meshed geometry or an STL")
    settings = {"cells": args.fibres_cells, "flow_cells": sorted(args.flow_cells),
                "reference_cells": sorted(args.reference_cells), "smoothing_mm": sorted(args.fibres_smoothing)}
    folder = args.output / "fibres_all"
    records = []
    for muscle in muscles:
        path = folder / f"{source(muscle, args.surfaces)[0]}.json"
        record = kept(comm, path, lambda old: old.get("settings") == settings, args.force)
        if record is None:
            record = {**fibre_errors(comm, muscle, args), "settings": settings, "machine": common.machine(),
                      "peak_rss_mb": comm.allreduce(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
                                                    op=MPI.MAX) / 1024, "versions": io.versions()}
            if comm.rank == 0:
                folder.mkdir(parents=True, exist_ok=True)
                io.write_json(path, record)
        records.append(record)
        for r in record["rows"]:
            info(comm, f"{record['muscle']}: l = {r['smoothing_mm']:g} mm, {r['fibres']} {r['cells_target']} "
                       f"against {r['reference_cells_target']}: mean {r['mean_deg']:.2f}°, p95 {r['p95_deg']:.2f}°")
    result = {"benchmark": "convergence --fibres-all", "goal_p95_deg": FIBRES_GOAL_DEG, **settings,
              "muscles": records, "ranks": comm.size}
    if comm.rank == 0:
        io.write_json(args.output / "fibres_all.json", result)
        fibre_chart(args.output / "fibres_all.png", result)
        print("\n".join(fibre_table(result)))
    info(comm, f"wrote {args.output / 'fibres_all'}.json and .png")
    return cli.EXIT_OK


# ---------------------------------------------------------------------- --fibres-limit

LIMIT_CELLS = (64000, 128000)  # the meshes of a surface the converged field is taken from


def limit_settings(args) -> dict:
    return {"reference_cells": sorted(args.reference_cells), "surfaces": str(args.surfaces),
            "laplace": dataclasses.asdict(laplace.LaplaceParams())}


def limit_job(comm, job: farm.Job) -> dict:
    """One shipped geometry's row of --fibres-limit, written to the job's path."""
    name, settings, path = job.payload
    surface = None
    if name in geo.MESHED:
        _, stl, extra = source(name, Path(settings["surfaces"]))
        rule = json.loads((geo.MESHES_DIR / name / "mesh.json").read_text())["ends"].get("rule", "vertices")
        surface = (stl, ["--end-rule", rule, *extra])
    row = limit_row(comm, geo.load(name, comm), fibers.fiber_path(name), surface, settings["reference_cells"],
                    path.with_suffix(".scratch"))
    row["settings"] = settings
    if comm.rank == 0:
        io.write_json(path, row)
    return row


def limit_row(comm, geometry: geo.Geometry, fibre_file: Path, surface: tuple[Path, list[str]] | None,
              reference_cells: list[int], scratch: Path) -> dict:
    """The fibres of ``fibre_file`` on ``geometry`` against the converged field of its shape
    at its nodes. ``surface`` (STL, `hyper mesh` options): the geometry is a mesh of it, and
    its shape the surface with the ends its rule tags, whose limit is that of ever finer
    meshes of it (``reference_cells``; the flow of `hyper mesh` is one of them). None: a
    paper fTetWild mesh, whose ends are the paper's tags and no rule's, so its shape is its
    own polyhedron, refined uniformly once and twice."""
    start = time.perf_counter()
    levels = []
    if surface is not None:
        stl, options = surface
        shutil.rmtree(scratch, ignore_errors=True)
        scratch.mkdir(parents=True)
        for cells in reference_cells:
            level = surface_mesh(comm, stl, options, cells, scratch)
            levels.append((level.num_cells(), unit(fibers.transferred(laplace.compute(level)[0], geometry))))
            del level
        shutil.rmtree(scratch, ignore_errors=True)
        reference, own = "meshes of its surface", laplace.compute(geometry)[0]
    else:
        fine = geometry
        for _ in range(2):
            fine = geo.refine(fine)
            levels.append((fine.num_cells(), unit(fibers.transferred(laplace.compute(fine)[0], geometry))))
        del fine
        reference, own = "its mesh refined uniformly", None
    finest, shipped = levels[-1][1], fibers.load(geometry, fibre_file)
    row = {"geometry": geometry.name, "cells": geometry.num_cells(), "reference": reference,
           "reference_cells": [n for n, _ in levels], "fibre_file": str(fibre_file),
           "fibres_method": fr.stored_fibres(fibre_file)[1], "fibres": angles(shipped, finest),
           "spread": angles(levels[-2][1], finest), **({} if own is None else {"own_mesh": angles(own, finest)}),
           "wall_s": comm.allreduce(time.perf_counter() - start, op=MPI.MAX)}
    # the finest field's own distance to the limit is taken to be at most its change from the level before
    row["bound_p95_deg"] = row["fibres"]["p95_deg"] + row["spread"]["p95_deg"]
    row["goal_met"] = row["bound_p95_deg"] <= FIBRES_GOAL_DEG
    return row


def limit_line(row: dict) -> str:
    own = f"; its own mesh's flow {row['own_mesh']['p95_deg']:.2f}°" if "own_mesh" in row else ""
    return (f"{row['geometry']}: fibres {row['fibres']['mean_deg']:.2f}° mean, {row['fibres']['p95_deg']:.2f}° p95 "
            f"from {row['reference']} at {row['reference_cells'][-1]} cells, which moved "
            f"{row['spread']['p95_deg']:.2f}° (p95) from {row['reference_cells'][-2]}: within "
            f"{row['bound_p95_deg']:.2f}° of the converged field{own}")


def limit_markdown(rows: list[dict]) -> list[str]:
    lines = ["| geometry | cells | converged field from | its cells | fibres to it: mean / p95 (°) | "
             "the finest's change, p95 (°) | bound, p95 (°) | flow on the mesh itself, p95 (°) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        bound = f"{r['bound_p95_deg']:.2f}" if r["goal_met"] else f"**{r['bound_p95_deg']:.2f}**"
        own = f"{r['own_mesh']['p95_deg']:.2f}" if "own_mesh" in r else "(the same)"
        lines.append(f"| {r['geometry']} | {r['cells']} | {r['reference']} | "
                     f"{' / '.join(map(str, r['reference_cells']))} | {r['fibres']['mean_deg']:.2f} / "
                     f"{r['fibres']['p95_deg']:.2f} | {r['spread']['p95_deg']:.2f} | {bound} | {own} |")
    lines.append(f"| within {FIBRES_GOAL_DEG:g}° | | | | | | {sum(r['goal_met'] for r in rows)} of {len(rows)} | |")
    return lines


def limit_chart(path: Path, rows: list[dict]) -> None:
    """Per geometry: the fibres' p95 angle to the converged field's estimate, the finest
    level's own change stacked on it, the flow on the mesh itself as a marker; the goal."""
    plt = plot.pyplot()
    x = np.arange(len(rows))
    fibres = np.array([r["fibres"]["p95_deg"] for r in rows])
    spread = np.array([r["spread"]["p95_deg"] for r in rows])
    fig, ax = plt.subplots(figsize=(max(8.0, 0.42 * len(rows) + 2), 4.8), layout="constrained")
    ax.bar(x, fibres, 0.7, label="the shipped fibres to the finest field")
    ax.bar(x, spread, 0.7, bottom=fibres, hatch="//", alpha=0.5, label="+ the finest field's last change (bound)")
    own = [(k, r["own_mesh"]["p95_deg"]) for k, r in enumerate(rows) if "own_mesh" in r]
    if own:
        ax.plot(*zip(*own), "kv", ms=5, label="the flow on the 8k mesh itself (before)")
    ax.axhline(FIBRES_GOAL_DEG, color="k", ls="--", lw=1, label=f"goal {FIBRES_GOAL_DEG:g}°")
    ax.set_xticks(x, [r["geometry"] for r in rows], rotation=70, fontsize=8)
    ax.set_ylabel("angle to the converged field, 95th percentile (°)")
    ax.set_title("Each shipped mesh's Laplace fibres against the converged field of its shape "
                 "(meshed: finer meshes of its surface; paper: its mesh refined)")
    ax.legend(fontsize=8)
    plot.save(fig, path, dpi=120)


def fibres_limit(comm, args) -> int:
    """Each shipped geometry's fibres against the converged field of its shape (--fibres-limit)."""
    names = args.fibres_limit or list(geo.ANATOMICAL + geo.MESHED)
    for name in names:
        if name not in (*geo.ANATOMICAL, *geo.MESHED):
            raise InputError(f"--fibres-limit: {name!r} is not a shipped anatomical or meshed geometry")
        if fibers.stored_kind(fibers.fiber_path(name)) != laplace.KIND:
            raise InputError(f"--fibres-limit: {name}'s fibres are not Laplace fibres: remake them "
                             f"(hyper fibers --method laplace --geometries {name})")
    settings = limit_settings(args)
    if len(set(settings["reference_cells"])) < 2:
        raise InputError("--reference-cells: --fibres-limit needs two or more levels (the finest's change bounds "
                         "its distance to the limit)")
    folder = args.output / "fibres_limit"
    if comm.rank == 0:
        folder.mkdir(parents=True, exist_ok=True)
    paths = {name: folder / f"{name}.json" for name in names}

    def is_done(job: farm.Job) -> bool:
        return not args.force and paths[job.key].is_file() and \
            json.loads(paths[job.key].read_text()).get("settings") == settings

    # the paper meshes' twice refined solve costs about what a surface's two fine meshes do
    jobs = [farm.Job(name, cost=1.0, payload=(name, settings, paths[name])) for name in names]
    start = time.perf_counter()
    results = farm.run(comm, jobs, limit_job, is_done=is_done, label="convergence --fibres-limit")
    failed = [r for r in results if r.status == "failed"]
    rows = [json.loads(paths[r.key].read_text()) for r in results if r.status != "failed"] if comm.rank == 0 else []
    if comm.rank == 0:
        for r in rows:
            info(comm, limit_line(r))
        result = {"benchmark": "convergence --fibres-limit", "goal_p95_deg": FIBRES_GOAL_DEG, "settings": settings,
                  "rows": rows, "failed": {r.key: r.error.strip().splitlines()[-1] for r in failed},
                  "ranks": comm.size, "wall_s": time.perf_counter() - start,
                  # the rows' own seconds on one rank each, kept ones included
                  "rows_s": sum(r["wall_s"] for r in rows), "machine": common.machine(), "versions": io.versions()}
        io.write_json(args.output / "fibres_limit.json", result)
        limit_chart(args.output / "fibres_limit.png", rows)
        print("\n".join(limit_markdown(rows)))
        info(comm, f"{sum(r['goal_met'] for r in rows)} of {len(rows)} shipped meshes' fibres within "
                   f"{FIBRES_GOAL_DEG:g}° (p95) of the converged field ({result['wall_s']:.0f} s; the rows "
                   f"{result['rows_s']:.0f} s on one rank each); wrote "
                   f"{args.output / 'fibres_limit'}.json and .png")
    return cli.EXIT_SOME_FAILED if failed else cli.EXIT_OK


# ------------------------------------------------------------------------------ --all


def studies_all(comm, args) -> int:
    """The study of each muscle (`--all`), each kept under OUTPUT/convergence_all/ and
    reused when its levels are the same (a stopped run goes on where it was), then one
    table of every muscle's finest level (with --quick, the default resolution)."""
    muscles = args.all or fibre_muscles(args.surfaces)
    cells = sorted(args.cells if args.cells else (QUICK_CELLS if args.quick else CELLS))
    folder = args.output / "convergence_all"
    rows = []
    for muscle in muscles:
        name = source(muscle, args.surfaces)[0]
        path = folder / f"{name}.json"
        result = kept(comm, path, lambda record: kept_cells(record) == cells
                      and fibres_method(record) == args.fibres_method, args.force)
        if result is None:
            try:
                result = study(comm, argparse.Namespace(**{**vars(args), "muscle": muscle}))
            except InputError as err:  # one muscle's failure is a row of the table, not the end of it
                info(comm, f"{name}: FAILED {err}")
                rows.append({"muscle": name, "failed": str(err)})
                continue
            if comm.rank == 0:
                folder.mkdir(parents=True, exist_ok=True)
                io.write_json(path, result)
                chart(folder / f"{name}.png", result)
        rows.append(summary_row(result))
        info(comm, summary_line(rows[-1]))
    result = {"benchmark": "convergence --all", "cells": cells, "quick": bool(args.quick), "goal": GROWTH_GOAL,
              "muscles": rows, "ranks": comm.size, "machine": common.machine(), "versions": io.versions()}
    if comm.rank == 0:
        io.write_json(args.output / "convergence_all.json", result)
        all_chart(args.output / "convergence_all.png", result)
        print("\n".join(all_table(result)))
    met = [r for r in rows if r.get("goal_met")]
    info(comm, f"{len(met)} of {len(rows)} muscles within {GROWTH_GOAL:g} of the growth (CSA and volume) at "
               f"{cells[-1]} cells; wrote {args.output / 'convergence_all'}.json and .png")
    return cli.EXIT_OK


def kept_cells(result: dict) -> list[int]:
    """The levels a kept study was asked for (those it dropped included)."""
    return result.get("cells_asked") or [r["cells_target"] for r in result["levels"]]


def summary_row(result: dict) -> dict:
    """A muscle's finest level: its gains, their estimated errors (own fibres, of the
    growth), the end force's, and the fibres' p95 angle one level down."""
    top = result["levels"][-1]
    est = result["estimates"]

    def error(q):
        e = est.get(q, {}).get("own")
        return None if e is None else e["errors"][-1]

    row = {"muscle": result["muscle"], "cells": top["cells"], "h_mm": top["h_mm"],
           "csa_gain_pct": top["own"]["csa_gain_pct"], "volume_gain_pct": top["own"]["volume_gain_pct"],
           "csa_error": error("csa_gain_pct"), "volume_error": error("volume_gain_pct"),
           "csa_order": (est.get("csa_gain_pct", {}).get("own") or {}).get("order"),
           "end_force_n": top["own"].get("end_force_n"), "end_force_error": error("end_force_n"),
           "fibre_p95_deg_below": result["levels"][-2]["fibre_angle_to_finest"]["p95_deg"],
           "wall_s": result["wall_s"], "ranks": result.get("ranks", 1),
           "levels": [r["cells_target"] for r in result["levels"]]}
    row["goal_met"] = bool(row["csa_error"] is not None and row["volume_error"] is not None
                           and max(row["csa_error"], row["volume_error"]) <= GROWTH_GOAL)
    return row


def summary_line(row: dict) -> str:
    if "failed" in row:
        return f"{row['muscle']}: FAILED {row['failed']}"
    return (f"{row['muscle']}: {row['cells']} cells, CSA {row['csa_gain_pct']:+.4f} % (error {row['csa_error']:.1e}), "
            f"V {row['volume_gain_pct']:+.4f} % ({row['volume_error']:.1e}), fibres p95 one level down "
            f"{row['fibre_p95_deg_below']:.1f}°, {'meets' if row['goal_met'] else 'misses'} {GROWTH_GOAL:g} "
            f"({row['wall_s']:.0f} s)")


def all_table(result: dict) -> list[str]:
    """The markdown table of docs/convergence.md: each muscle's finest level."""
    lines = ["| muscle | cells | CSA gain (%) | its estimated error (of the growth), order | volume gain (%) | "
             "its error | fibres one level down: p95 to the finest (°) | goal | study (s, ranks) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in result["muscles"]:
        if "failed" in r:
            lines.append(f"| {r['muscle']} | failed: {r['failed']} | | | | | | | |")
            continue
        order = f"{r['csa_order']:.2f}" if r["csa_order"] is not None else "none"
        fewer = r.get("levels", result["cells"])[0] != result["cells"][0]  # too thin for the coarsest
        name = f"{r['muscle']} (levels from {r['levels'][0]})" if fewer else r["muscle"]
        lines.append(f"| {name} | {r['cells']} | {r['csa_gain_pct']:.4f} | {r['csa_error']:.1e}, {order} | "
                     f"{r['volume_gain_pct']:.4f} | {r['volume_error']:.1e} | {r['fibre_p95_deg_below']:.1f} | "
                     f"{'met' if r['goal_met'] else 'missed'} | {r['wall_s']:.0f}, {r['ranks']} |")
    met = sum(bool(r.get("goal_met")) for r in result["muscles"])
    lines.append(f"| within {result['goal']:g} of the growth | {met} of {len(result['muscles'])} | | | | | | | |")
    return lines


def all_chart(path: Path, result: dict) -> None:
    rows = [r for r in result["muscles"] if "failed" not in r]
    plt = plot.pyplot()
    fig, ax = plt.subplots(figsize=(9, 0.28 * len(rows) + 1.6))
    y = np.arange(len(rows))
    ax.barh(y - 0.2, [r["csa_error"] for r in rows], 0.4, label="CSA gain")
    ax.barh(y + 0.2, [r["volume_error"] for r in rows], 0.4, label="volume gain")
    ax.axvline(result["goal"], color="k", ls="--", lw=1, label=f"goal {result['goal']:g} of the growth")
    ax.set_yticks(y, [r["muscle"] for r in rows], fontsize=7)
    ax.set_xscale("log")
    ax.invert_yaxis()
    ax.set_xlabel("estimated error of the 9-week gain, fraction of the growth")
    ax.set_title(f"{result['cells'][-1]}-cell meshes (levels {', '.join(map(str, result['cells']))}), "
                 f"{sum(r['goal_met'] for r in rows)} of {len(result['muscles'])} meet the goal", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    plot.save(fig, path, dpi=120)


# ----------------------------------------------------------------- --spatial-table


def spatial_rows(folders: list[Path], cells: int) -> list[dict]:
    """Per muscle, the estimated error of the gains at its ``cells``-cell level, from the
    kept `--all` study (under each folder's convergence_all/) with the finest levels that
    has that level: the finer the levels, the nearer the limit the estimate is taken from."""
    best: dict[str, tuple] = {}
    for folder in folders:
        for path in sorted((folder / "convergence_all").glob("*.json")):
            result = json.loads(path.read_text())
            targets = [r["cells_target"] for r in result["levels"]]
            if cells not in targets:
                continue
            rank = (targets[-1], len(targets))
            if result["muscle"] not in best or rank > best[result["muscle"]][0]:
                best[result["muscle"]] = (rank, result, path)
    rows = []
    for muscle, (_, result, path) in sorted(best.items()):
        targets = [r["cells_target"] for r in result["levels"]]
        i = targets.index(cells)
        own = {q: result["estimates"][q]["own"] for q in ("csa_gain_pct", "volume_gain_pct")}
        finest = result["estimates"]["csa_gain_pct"].get("finest")
        solid = result["estimates"].get("csa_solid_gain_pct", {}).get("own")
        rows.append({"muscle": muscle, "cells_target": cells, "cells": result["levels"][i]["cells"], "levels": targets,
                     "csa_gain_pct": result["levels"][i]["own"]["csa_gain_pct"],
                     "csa_error": own["csa_gain_pct"]["errors"][i],
                     "volume_error": own["volume_gain_pct"]["errors"][i],
                     "csa_order": own["csa_gain_pct"]["order"],
                     # the mechanics' part: the same level with the finest level's fibres
                     "csa_error_finest_fibres": finest["errors"][i] if finest else None,
                     # what `hyper mesh --flow-cells FINEST` gives: that level with the finest
                     # fibres, against the own fibres' limit
                     "csa_error_finest_flow": error_to(own["csa_gain_pct"],
                                                       result["levels"][i]["finest"]["csa_gain_pct"]),
                     "fibre_p95_deg": result["levels"][i]["fibre_angle_to_finest"]["p95_deg"],
                     "volume_gain_pct": result["levels"][i]["own"]["volume_gain_pct"],
                     "csa_solid_error": solid["errors"][i] if solid else None,
                     "study": str(path), "study_s": result.get("wall_s"), "ranks": result.get("ranks", 1)})
    return rows


def error_to(e: dict, value: float) -> float:
    """The error of ``value`` as `estimate` ``e`` measures its series' levels: to the
    Richardson limit, or without an order to the finest level plus the finest spread."""
    spread = 0.0 if e["order"] is not None else e["errors"][-1]
    return abs(value - e["limit"]) / abs(e["limit"]) + spread


def spatial_markdown(rows: list[dict]) -> list[str]:
    """The table of docs/convergence.md: each muscle's 8k level, and who carries its error."""
    lines = ["| muscle | study's levels | CSA gain (%) | its error (of the growth) | with the finest fibres (the "
             "mechanics') | with the finest flow, to the own limit | on the solid's plane | volume gain (%) | "
             "its error | fibres: p95 to the finest (°) | spatial error | study (s, ranks) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        mech = "–" if r["csa_error_finest_fibres"] is None else f"{r['csa_error_finest_fibres']:.1e}"
        solid = "–" if r.get("csa_solid_error") is None else f"{r['csa_solid_error']:.1e}"
        angle = "(the finest)" if r["levels"][-1] == r["cells_target"] else f"{r['fibre_p95_deg']:.1f}"
        took = "–" if r.get("study_s") is None else f"{r['study_s']:.0f}, {r['ranks']}"
        lines.append(f"| {r['muscle']} | {r['levels'][0]}–{r['levels'][-1]} | {r['csa_gain_pct']:.4f} | "
                     f"{r['csa_error']:.1e} | {mech} | {r['csa_error_finest_flow']:.1e} | {solid} | "
                     f"{r['volume_gain_pct']:.4f} | {r['volume_error']:.1e} | {angle} | "
                     f"{rounded_up(spatial_error(r)):.2g} | {took} |")
    return lines


def spatial_error(row: dict) -> float:
    """A level's spatial error for fidelity's table: the largest of the CSA and volume
    gains' errors and the CSA gain's with the finest fibres (the mechanics' alone), since
    a small spread of the own-fibre series can be the fibres' and the mechanics' changes
    cancelling (GM_VHF_Right: 1.8e-4 with its own fibres, 5.4e-3 with the finest)."""
    return max(e for e in (row["csa_error"], row["volume_error"], row["csa_error_finest_fibres"]) if e is not None)


def spatial_literal(row: dict) -> str:
    """A row as the line of `hyper.runs.fidelity.SURFACE_STUDIES`: its `spatial_error`,
    two digits rounded up, and the study's levels."""
    return f'    "{row["muscle"]}": ({rounded_up(spatial_error(row)):.2g}, {tuple(row["levels"])}),'


def rounded_up(error: float) -> float:
    """Two significant digits, rounded up (a table's error never understates the measured)."""
    digits = 10.0 ** (math.floor(math.log10(error)) - 1)
    return math.ceil(error / digits - 1e-9) * digits  # 0.0024 / 1e-4 is 24.000000000000004


def spatial_chart(path: Path, rows: list[dict]) -> None:
    """Each muscle's 8k level: the CSA gain's error with its own fibres and with the
    finest level's (the mechanics' alone), against the goal."""
    plt = plot.pyplot()
    fig, ax = plt.subplots(figsize=(9, 0.28 * len(rows) + 1.6))
    y = np.arange(len(rows))
    ax.barh(y - 0.27, [r["csa_error"] for r in rows], 0.27, label="own fibres (what a run on that mesh has)")
    ax.barh(y, [r["csa_error_finest_fibres"] or np.nan for r in rows], 0.27,
            label="the finest level's fibres: the mechanics' part")
    ax.barh(y + 0.27, [r.get("csa_solid_error") or np.nan for r in rows], 0.27,
            label="own fibres, the solid's plane (where measured)")
    ax.axvline(GROWTH_GOAL, color="k", ls="--", lw=1, label=f"goal {GROWTH_GOAL:g} of the growth")
    ax.set_yticks(y, [f"{r['muscle']} ({r['levels'][-1] // 1000}k)" for r in rows], fontsize=7)
    ax.set_xscale("log")
    ax.invert_yaxis()
    ax.set_xlabel(f"estimated error of the 9-week CSA gain at {rows[0]['cells_target']} cells, fraction of the growth")
    ax.set_title("which carries the error: fibres or mechanics (finest level of each study in brackets)", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    plot.save(fig, path, dpi=120)


def spatial_table(comm, args) -> int:
    rows = spatial_rows(args.spatial_table, hm.DEFAULT_CELLS)
    if not rows:
        raise InputError(f"--spatial-table: no kept study with a {hm.DEFAULT_CELLS}-cell level under "
                         + ", ".join(f"{f}/convergence_all" for f in args.spatial_table))
    if comm.rank == 0:
        args.output.mkdir(parents=True, exist_ok=True)
        io.write_json(args.output / "spatial_table.json", {"benchmark": "convergence --spatial-table",
                                                          "cells": hm.DEFAULT_CELLS, "muscles": rows})
        spatial_chart(args.output / "spatial_table.png", rows)
        print("\n".join(spatial_markdown(rows)))
        print("\n".join(spatial_literal(r) for r in rows))
    info(comm, f"{len(rows)} muscles; wrote {args.output / 'spatial_table'}.json and .png")
    return cli.EXIT_OK


# -------------------------------------------------------------------------- --shipped


def study_of(folders: list[Path], muscle: str, method: str) -> dict | None:
    """The kept `--all` study of ``muscle`` with ``method`` fibres under the folders with the
    finest levels (as `spatial_rows` takes it), or None."""
    best = None
    for folder in folders:
        path = folder / "convergence_all" / f"{muscle}.json"
        if not path.is_file():
            continue
        result = json.loads(path.read_text())
        if fibres_method(result) != method:
            continue
        rank = (result["levels"][-1]["cells_target"], len(result["levels"]))
        if best is None or rank > best[0]:
            best = (rank, result)
    return None if best is None else best[1]


def shipped_job(comm, job: farm.Job) -> dict:
    """One shipped geometry's 9-week growth with its ``method`` fibres (the files a run reads)."""
    name, method = job.payload
    geometry = geo.load(name, comm)
    return {"cells": geometry.num_cells(), **growth(geometry, fibers.fiber_field(geometry, method))}


def shipped(comm, args) -> int:
    """Each shipped geometry's 9-week gains with its fibres made on the shipped mesh, against
    the limit of the kept `--all` study of its surface (--studies): the error a `--geometry`
    run carries, measured on the mesh it runs on (the 12 paper muscles' fTetWild meshes are
    not the study's levels; the 19 others are its 8000-cell level)."""
    names = args.shipped or list(geo.ANATOMICAL + geo.MESHED)
    for name in names:
        if name not in (*geo.ANATOMICAL, *geo.MESHED):
            raise InputError(f"--shipped: {name!r} is not a shipped anatomical or meshed geometry")
    studies = {}
    for name in names:
        muscle = _muscle_with_study(name, args.studies, args.fibres_method)
        studies[name] = (muscle, study_of(args.studies, muscle, args.fibres_method) if muscle else None)
    jobs = [farm.Job(name, cost=1.0, payload=(name, args.fibres_method)) for name in names]
    start = time.perf_counter()
    results = farm.run(comm, jobs, shipped_job, label=f"convergence --shipped ({args.fibres_method} fibres)")
    rows = []
    for r in results:
        muscle, study = studies[r.key]
        if r.status != "done":
            rows.append({"geometry": r.key, "failed": r.error.strip().splitlines()[-1]})
            continue
        row = {"geometry": r.key, **r.result, "study_muscle": muscle}
        if study is not None:
            est = study["estimates"]
            row.update({"study_levels": [lv["cells_target"] for lv in study["levels"]],
                        "csa_limit_pct": est["csa_gain_pct"]["own"]["limit"],
                        "volume_limit_pct": est["volume_gain_pct"]["own"]["limit"],
                        "csa_error": error_to(est["csa_gain_pct"]["own"], row["csa_gain_pct"]),
                        "volume_error": error_to(est["volume_gain_pct"]["own"], row["volume_gain_pct"]),
                        # the older Stokes studies did not measure it
                        "csa_solid_error": (error_to(est["csa_solid_gain_pct"]["own"], row["csa_solid_gain_pct"])
                                            if "csa_solid_gain_pct" in est else None),
                        # the study's level of this very mesh (the meshed geometries' 8k level)
                        "same_mesh": any(lv["cells"] == row["cells"] for lv in study["levels"])})
            row["goal_met"] = max(row["csa_error"], row["volume_error"]) <= GROWTH_GOAL
        rows.append(row)
        info(comm, shipped_line(row))
    result = {"benchmark": "convergence --shipped", "fibres_method": args.fibres_method, "goal": GROWTH_GOAL,
              "studies": [str(f) for f in args.studies], "rows": rows, "ranks": comm.size,
              "wall_s": comm.allreduce(time.perf_counter() - start, op=MPI.MAX), "machine": common.machine(),
              "versions": io.versions()}
    stem = args.output / f"shipped_{args.fibres_method}"
    if comm.rank == 0:
        args.output.mkdir(parents=True, exist_ok=True)
        io.write_json(stem.with_suffix(".json"), result)
        print("\n".join(shipped_markdown(result)))
        shipped_chart(stem.with_suffix(".png"), result)
        print("\n".join(f'    "{r["geometry"]}": {rounded_up(max(r["csa_error"], r["volume_error"])):.2g},'
                        for r in rows if "csa_error" in r))
    measured = [r for r in rows if "goal_met" in r]
    info(comm, f"{sum(r['goal_met'] for r in measured)} of {len(measured)} shipped meshes within {GROWTH_GOAL:g} of "
               f"the growth with {args.fibres_method} fibres ({result['wall_s']:.0f} s); wrote {stem}.json and .png")
    return cli.EXIT_OK if all("failed" not in r for r in rows) else cli.EXIT_SOME_FAILED


def _muscle_with_study(name: str, folders: list[Path], method: str) -> str | None:
    """The muscle whose study stands for ``name``: its own, else the other side's (the right
    BFLH of the female has no surface)."""
    return next((m for m in (name, fidelity.other_side(name)) if study_of(folders, m, method) is not None), None)


def shipped_line(row: dict) -> str:
    if "failed" in row:
        return f"{row['geometry']}: FAILED {row['failed']}"
    head = (f"{row['geometry']}: {row['cells']} cells, CSA {row['csa_gain_pct']:+.4f} %, "
            f"V {row['volume_gain_pct']:+.4f} % ({row['growth_s']:.0f} s)")
    if "csa_error" not in row:
        return head + ": no study of its surface"
    whose = "" if row["study_muscle"] == row["geometry"] else f", the study of {row['study_muscle']}"
    return (head + f"; to the limit {row['csa_limit_pct']:.4f} / {row['volume_limit_pct']:.4f} %{whose}: "
            f"{row['csa_error']:.1e} / {row['volume_error']:.1e} of the growth, "
            f"{'meets' if row['goal_met'] else 'misses'} {GROWTH_GOAL:g}")


def shipped_chart(path: Path, result: dict) -> None:
    """Each shipped mesh's errors of the CSA (cut and solid's plane) and volume gains against the goal."""
    rows = [r for r in result["rows"] if "csa_error" in r]
    plt = plot.pyplot()
    fig, ax = plt.subplots(figsize=(9, 0.28 * len(rows) + 1.6))
    y = np.arange(len(rows))
    ax.barh(y - 0.27, [r["csa_error"] for r in rows], 0.27, label="CSA gain (the vertices' plane, fed back)")
    ax.barh(y, [r["csa_solid_error"] or np.nan for r in rows], 0.27, label="CSA gain on the solid's plane")
    ax.barh(y + 0.27, [r["volume_error"] for r in rows], 0.27, label="volume gain")
    ax.axvline(result["goal"], color="k", ls="--", lw=1, label=f"goal {result['goal']:g} of the growth")
    ax.set_yticks(y, [f"{r['geometry']} ({r['cells']})" for r in rows], fontsize=7)
    ax.set_xscale("log")
    ax.invert_yaxis()
    ax.set_xlabel("error of the 9-week gain against its surface's limit, fraction of the growth")
    met = sum(r["goal_met"] for r in rows)
    ax.set_title(f"the shipped meshes with {result['fibres_method']} fibres made on them: {met} of {len(rows)} "
                 "meet the goal", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    plot.save(fig, path, dpi=120)


def solid(row: dict) -> str:
    return "–" if row.get("csa_solid_error") is None else f"{row['csa_solid_error']:.1e}"


def shipped_markdown(result: dict) -> list[str]:
    lines = ["| geometry | cells | CSA gain (%) | the surface's limit | error (of the growth) | on the solid's plane "
             "| volume gain (%) | limit | error | goal |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        if "csa_error" not in r:
            lines.append(f"| {r['geometry']} | {r.get('failed', 'no study of its surface')} | | | | | | | | |")
            continue
        name = r["geometry"] + ("" if r["study_muscle"] == r["geometry"] else f" ({r['study_muscle']}'s study)")
        lines.append(f"| {name} | {r['cells']} | {r['csa_gain_pct']:.4f} | {r['csa_limit_pct']:.4f} | "
                     f"{r['csa_error']:.1e} | {solid(r)} | {r['volume_gain_pct']:.4f} | "
                     f"{r['volume_limit_pct']:.4f} | {r['volume_error']:.1e} | "
                     f"{'met' if r['goal_met'] else 'missed'} |")
    measured = [r for r in result["rows"] if "goal_met" in r]
    lines.append(f"| within {result['goal']:g} of the growth | {sum(r['goal_met'] for r in measured)} of "
                 f"{len(measured)} | | | | | | | | |")
    return lines


# ------------------------------------------------------------------------------ job


def parser() -> cli.Parser:
    p = cli.Parser("bench convergence", __doc__)
    p.add_argument("muscle", nargs="?", default="TA_VHF_Left", help="geometry id or STL file (mm)")
    p.add_argument("--cells", type=cli.integer(200, 100000), nargs="+", metavar="N",
                   help=f"target cells of the levels; {' '.join(map(str, CELLS))} "
                        f"({' '.join(map(str, QUICK_CELLS))} with --quick)")
    p.add_argument("--quick", action="store_true", help="coarser levels: a few minutes on 2 cores")
    p.add_argument("--surfaces", type=Path, default=mesh_bench.SURFACES, help="folder of the STL surfaces")
    p.add_argument("--all", nargs="*", metavar="ID", help="the study of each muscle (every one with a surface by "
                   "default), kept under OUTPUT/convergence_all/ and reused; one table (convergence_all.json, .png)")
    p.add_argument("--fibres-only", nargs="+", metavar="ID", help="only the fixed-geometry fibre check (P2 against "
                   "P3) of these geometries")
    p.add_argument("--fibres-all", nargs="*", metavar="ID", help="only the fibres' resolution: each muscle's "
                   "(all with a surface by default) Stokes fibres at --fibres-cells against --reference-cells "
                   "(fibres_all.json, .png; per muscle under fibres_all/, reused)")
    p.add_argument("--fibres-cells", type=cli.integer(200, 100000), default=hm.DEFAULT_CELLS, metavar="N",
                   help="--fibres-all: the mesh measured (hyper mesh's default)")
    p.add_argument("--flow-cells", type=cli.integer(200, 200000), nargs="*", default=[16000], metavar="N",
                   help="--fibres-all: also the flow solved at N cells and carried onto that mesh (hyper mesh "
                        "--flow-cells)")
    p.add_argument("--fibres-limit", nargs="*", metavar="ID", help="only the fibres: each shipped geometry's (all "
                   "by default) against the converged field of its shape at its nodes, from finer meshes of its "
                   f"surface (--reference-cells, {' '.join(map(str, LIMIT_CELLS))} by default) or, for the paper's "
                   "meshes, its mesh refined once and twice (fibres_limit.json, .png; per geometry under "
                   "fibres_limit/, reused)")
    p.add_argument("--reference-cells", type=cli.integer(200, 400000), nargs="+", metavar="N",
                   help="--fibres-all: the finest is the reference; coarser ones are compared with it too (32000 "
                        "by default); --fibres-limit: the meshes of a surface the converged field is taken from")
    p.add_argument("--fibres-smoothing", type=cli.number(0, 50), nargs="+", default=[2.0, 4.0], metavar="MM",
                   help="--fibres-all: the smoothing lengths (each level's flow smoothed over each)")
    p.add_argument("--spatial-table", nargs="+", type=Path, metavar="DIR", reads=True,
                   help="no runs: from the kept --all studies under each DIR, every muscle's error at the "
                        f"{hm.DEFAULT_CELLS}-cell level (the finest study's), as hyper.runs.fidelity's table")
    p.add_argument("--shipped", nargs="*", metavar="ID",
                   help="each shipped geometry (all by default) with --fibres-method fibres made on its own mesh: "
                        "the 9-week gains against the limit of its surface's kept --all study under --studies "
                        "(shipped_METHOD.json)")
    p.add_argument("--studies", nargs="+", type=Path, default=[Path("results/bench/convergence_laplace")],
                   metavar="DIR", reads=True, help="--shipped: folders of kept --all studies")
    p.add_argument("--replot", type=Path, metavar="JSON", reads=True,
                   help="no runs: the estimates and chart again from a convergence_NAME.json")
    p.add_argument("--fibres-method", choices=("stokes", "laplace"), default=mesh_job.DEFAULT_METHOD,
                   help="the levels' fibres (hyper mesh --method, whose default this is): the potential flow "
                        "between the ends (hyper.fem.laplace), or the paper's Stokes flow")
    p.add_argument("--force", action="store_true", help="mesh the levels again")
    p.add_argument("--no-force-at-full-activation", dest="force_at_full_activation", action="store_false",
                   help="skip the end force at α = 1 (the growth only)")
    p.add_argument("--output", type=Path, default=Path("results/bench"), help="output folder")
    return p


def run(comm, args) -> int:
    if args.spatial_table:
        return spatial_table(comm, args)
    if args.shipped is not None:
        return shipped(comm, args)
    if args.all is not None:
        return studies_all(comm, args)
    if args.fibres_all is not None:
        args.reference_cells = args.reference_cells or [32000]
        return fibres_all(comm, args)
    if args.fibres_limit is not None:
        args.reference_cells = args.reference_cells or list(LIMIT_CELLS)
        return fibres_limit(comm, args)
    if args.fibres_only:
        for name in args.fibres_only:
            if name not in geo.GEOMETRIES or name in ("idealized", "cylinder"):
                raise InputError(f"--fibres-only: {name!r} is not an anatomical or meshed geometry")
        rows = []
        for name in args.fibres_only:
            rows.append(fibre_check(comm, name))
            r = rows[-1]
            info(comm, f"{name}: {r['cells']} cells, P2 against P3: mean {r['mean_deg']:.2f}°, p95 "
                       f"{r['p95_deg']:.2f}°, max {r['max_deg']:.1f}° (P3 {r['p3_solve_s']:.0f} s, "
                       f"{r['peak_rss_mb']:.0f} MB)")
        if comm.rank == 0:
            args.output.mkdir(parents=True, exist_ok=True)
            io.write_json(args.output / "convergence_fibres.json", {"benchmark": "convergence --fibres-only",
                                                                   "rows": rows, "versions": io.versions()})
        info(comm, f"wrote {args.output / 'convergence_fibres.json'}")
        return cli.EXIT_OK
    if args.replot is not None:
        result = json.loads(args.replot.read_text())
        result["estimates"] = estimates_of(result["levels"])
    else:
        result = study(comm, args)
    stem = f"convergence_{result['muscle']}"
    if comm.rank == 0:
        args.output.mkdir(parents=True, exist_ok=True)
        io.write_json(args.output / f"{stem}.json", result)
        chart(args.output / f"{stem}.png", result)
    for q, by_variant in result["estimates"].items():
        for v, e in by_variant.items():
            order = f"order {e['order']:.2f}" if e["order"] is not None else "no order"
            info(comm, f"{q} ({v} fibres): {order}, limit {e['limit']:.5f}, errors of {e['error_of']} "
                       + " ".join(f"{x:.2g}" for x in e["errors"]))
    info(comm, f"{result['wall_s']:.0f} s; wrote {args.output / stem}.json and .png")
    return cli.EXIT_OK


main = cli.entry(parser, run)

if __name__ == "__main__":
    sys.exit(main())
