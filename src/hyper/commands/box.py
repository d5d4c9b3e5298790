"""``hyper box``: the original code's box CSA of a stored growth run (`hyper.fem.boxsection`)."""

from __future__ import annotations

import sys
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np
from dolfinx import fem
from mpi4py import MPI

from hyper.commands import cli
from hyper.core import io
from hyper.core.log import info
from hyper.core.params import InputError
from hyper.fem import geometry as geo
from hyper.fem.boxsection import OUTSIDE, BoxSection
from hyper.runs import runspec

JOB = """hyper box: the original code's box CSA (hyper.box, MODEL.md §9) of a stored growth
run, re-measured on its saved displacement snapshots by each rule for the box nodes
outside the muscle ("extrapolate", what DOLFINx 0.11 does and the original got; "zero",
what MODEL.md §9 says).

    hyper box results/grow/BFLH_VHF_Left_mwf.h5
    hyper box results/mine/my_muscle_mwf.h5 --mesh my_muscle.xdmf --mesh-unit mm --output box.h5

RESULT.h5 is a grow or cohort result; its snapshots are RESULT_fields.xdmf's u (every
--snapshot-every hours of the run, and its last state), on the result's built-in
geometry or --mesh. The snapshots hold u in P1, the nodal values of the run's P2
displacement, so "extrapolate" re-measures the run's own csa_ratio_box (shown beside it)
to about 1e-4, not exactly. --output writes the series (t, csa_ratio_box_extrapolate,
csa_ratio_box_zero) to an HDF5 file.
"""


def parser() -> cli.Parser:
    p = cli.Parser("box", JOB)
    p.add_argument("result", type=Path, metavar="RESULT.h5", reads=lambda r: [r, *runspec.Outputs(r).snapshots],
                   help="a growth result file, with its RESULT_fields.xdmf beside it")
    p.add_argument("--mesh", type=Path, reads=True, help="the run's own XDMF mesh, where it ran on one (grow --mesh)")
    p.add_argument("--mesh-unit", default="m", choices=tuple(runspec.MESH_UNITS), help="length unit of --mesh")
    p.add_argument("--output", type=cli.output(folder=False, suffixes=(".h5",)),
                   help="an HDF5 file for the re-measured series (none: the table alone)")
    return p


def matched_rows(space, nodes) -> np.ndarray:
    """For each local node of the Lagrange ``space``, the row of ``nodes`` (n, 3), a
    snapshot's mesh points, at its position. InputError where they are not the same mesh.
    Collective."""
    from scipy.spatial import cKDTree

    distance, rows = cKDTree(nodes).query(space.tabulate_dof_coordinates())
    far = space.mesh.comm.allreduce(float(distance.max(initial=0.0)), op=MPI.MAX)
    if far > 1e-9 * np.ptp(nodes, axis=0).max():
        raise InputError(f"the snapshots' mesh is not the run's: a node is {far:g} m from every snapshot node "
                         "(another geometry, a refined mesh, or --mesh-unit)")
    return rows


def remeasure(comm, result: Path, mesh_file: Path | None = None, unit: str = "m") -> dict:
    """The box CSA ratio of each saved snapshot of the growth result ``result`` by each
    rule of `OUTSIDE`: ``t`` (h), ``csa_ratio_box_<rule>``, ``recorded`` (the run's
    csa_ratio_box at those times, NaN where it has none), and ``area0`` (m², by rule),
    ``outside_nodes`` (outside, extrapolated), ``geometry``. Collective over ``comm``."""
    with io.reading_h5(result) as f:  # a damaged file: an InputError naming it and what HDF5 found
        complete, geometry = bool(f.attrs.get("complete", False)), str(f.attrs.get("geometry", ""))
    if not complete:
        raise InputError(f"{result}: not a complete result file")
    series = io.read_series(result)
    fields = runspec.Outputs(result).fields
    if not fields.is_file():
        raise InputError(f"{result}: its snapshots {fields} are not there")
    # the snapshots before the mesh: a malformed field file is refused before that work
    nodes, snapshots = io.read_point_field(fields, "u")
    if mesh_file is not None:
        mesh = runspec.MeshFile(mesh_file, unit).load(comm).mesh
    else:
        if geometry not in geo.GEOMETRIES:
            raise InputError(f"{result}: ran on {geometry!r}, not a built-in geometry; give its mesh with --mesh")
        runspec.check_geometry(comm, geometry, option=f"{result}'s geometry")
        mesh = geo.load(geometry, comm).mesh
    u = fem.Function(fem.functionspace(mesh, ("Lagrange", 1, (3,))))  # the snapshots' space
    rows = matched_rows(u.function_space, nodes)
    measures = {rule: BoxSection(mesh, u, outside=rule) for rule in OUTSIDE}
    out = {"t": np.array([t for t, _ in snapshots]), "geometry": geometry,
           "area0": {rule: m.area0() for rule, m in measures.items()},
           "outside_nodes": measures["zero"].outside_nodes}
    ratios = {rule: [] for rule in OUTSIDE}
    for _, values in snapshots:
        u.x.array.reshape(-1, 3)[:] = values[rows]  # owned and ghost nodes alike
        for rule, m in measures.items():
            ratios[rule].append(m.deformed_area() / m.area0())
    for rule in OUTSIDE:
        out[f"csa_ratio_box_{rule}"] = np.array(ratios[rule])
    recorded = np.full(len(out["t"]), np.nan)
    if "csa_ratio_box" in series:
        for i, t in enumerate(out["t"]):
            at = np.flatnonzero(np.isclose(series["t"], t, rtol=0, atol=1e-9 * max(1.0, abs(t))))
            if len(at):
                recorded[i] = series["csa_ratio_box"][at[-1]]
    out["recorded"] = recorded
    return out


def run_job(comm, args) -> int:
    if args.mesh is None and args.mesh_unit != "m":
        raise InputError("--mesh-unit declares the length unit of a --mesh file; there is none")
    m = remeasure(comm, args.result, args.mesh, args.mesh_unit)
    outside, extrapolated = m["outside_nodes"]
    info(comm, f"{args.result} ({m['geometry']}): the staircase is {m['area0']['extrapolate'] * 1e4:.3f} cm²; "
               f"{outside} of its box nodes lie in no muscle cell, {extrapolated} of them inside a muscle cell's "
               "bounding box (extrapolated)")
    info(comm, f"{'t (h)':>8} {'day':>6} {'extrapolate':>12} {'zero':>10} {'run recorded':>13}")
    for i, t in enumerate(m["t"]):
        info(comm, f"{t:8.1f} {t / 24:6.1f} {m['csa_ratio_box_extrapolate'][i]:12.6f} "
                   f"{m['csa_ratio_box_zero'][i]:10.6f} {m['recorded'][i]:13.6f}")
    last = {rule: 100 * (m[f"csa_ratio_box_{rule}"][-1] - 1) for rule in OUTSIDE}
    info(comm, f"at t = {m['t'][-1]:g} h the box reads CSA {last['extrapolate']:+.2f} % (extrapolate), "
               f"{last['zero']:+.2f} % (zero); the run recorded {100 * (m['recorded'][-1] - 1):+.2f} %")
    if args.output is not None and comm.rank == 0:
        names = ("t", "csa_ratio_box_extrapolate", "csa_ratio_box_zero")
        io.write_series(args.output, {name: m[name] for name in names},
                        attrs={"result": str(args.result.resolve()), "geometry": m["geometry"],
                               "outside_nodes": outside, "extrapolated_nodes": extrapolated,
                               **{f"csa0_box_{rule}_m2": area for rule, area in m["area0"].items()}},
                        units={name: "h" if name == "t" else "1" for name in names})
        info(comm, f"wrote {args.output}")
    return cli.EXIT_OK


main = cli.entry(parser, run_job, locks=lambda args: [args.output] if args.output is not None else [])

if __name__ == "__main__":
    sys.exit(main())
