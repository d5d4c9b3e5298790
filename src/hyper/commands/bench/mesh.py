"""hyper mesh against the shipped meshes: each Visible Human surface that a shipped mesh
was made from (fTetWild, by the paper) is meshed again by `hyper mesh`, timed, and both
meshes are compared with the surface itself (the STL, the fair target: the shipped mesh is
not exactly its volume either) and with each other:

    time        STL -> checked surface -> tetrahedra -> tags -> Stokes fibres (1 rank)
    cells, min dihedral angle (both meshes)
    volume      of each mesh against the STL's enclosed volume
    CSA, length by the solid's frame (hyper.meshstats csa_solid, length_solid): the cut by
                the plane through the volume's centroid, normal to its principal axis of
                inertia, and the extent along that axis; the STL's by its own frame
                (``section.surface_solid_moments``, ``section.surface_cut_area``)
    CSA0        the simulation's (meshstats csa0: the plane of the vertices' mean and
                principal axis, MODEL.md §4), new against shipped, and the shipped mesh's
                CSA0 against its csa_solid (how far the vertex plane is from the shape's)
    CSA at the shipped plane   the new mesh cut by the shipped mesh's CSA0 plane
    CSA0 vs STL the new mesh's CSA0 against the STL's CSA by its solid's frame
    vertex plane of each mesh: how far (mm) along the solid's axis the CSA0 plane lies from
                the centroid, and its tilt (°) from the inertia axis
    end areas   of tags 1 and 2, new / shipped
    fibre angle volume-weighted mean over the shipped cells of the angle between the two
                fields (the new field taken at the nearest new cell centroid)
    --growth    the 9-week `mwf` growth on both meshes (1 rank, the default settings and
                parameters, each with its Stokes fibres): CSA (the simulation's plane) and
                volume increase in percentage points, and the CSA increase measured on the
                solid's plane at the end of the same run

The origin is put at the shipped tag 1 (``--origin-toward`` from the shipped tag-2 end
to the tag-1 end), so both flows enter at the same end. Writes results/bench/mesh.json
and the meshes under results/bench/mesh/ (not meshes/: they are a check, not geometries).

    python -m hyper.bench mesh [--geometries TA_VHF_Left …] [--growth]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np

from hyper.commands import cli
from hyper.commands import mesh as mesh_job
from hyper.core import io
from hyper.core.log import info
from hyper.core.params import InputError
from hyper.fem import fibers, meshstats, section
from hyper.fem import geometry as geo
from hyper.fem import meshing as hm
from hyper.fem.coupled import GrowthSettings, build_model
from hyper.model import protocols
from hyper.model.material import MaterialParams

SURFACES = Path(__file__).resolve().parents[4].parent / "shared" / "surfaces"
GROWTH_PROTOCOL = "mwf"


def shipped(name: str) -> dict:
    """Cells, dihedral angle, end centroids and areas of a shipped mesh, from its file (mm)."""
    import h5py


    with h5py.File((geo.MESHES_DIR / geo.GEOMETRIES[name]).with_suffix(".h5"), "r") as f:
        x = f["Mesh/Grid/geometry"][()]
        tets = f["Mesh/Grid/topology"][()]
        facets = f["MeshTags/ft_small/topology"][()]
        tags = f["MeshTags/ft_small/Values"][()].ravel()
    tets, quality = hm.check_quality(x, tets)
    area = hm.facet_areas(x, facets)
    centroid = [np.average(x[facets[tags == t]].mean(axis=1), axis=0, weights=area[tags == t]) for t in (1, 2)]
    return {"cells": len(tets), "min_dihedral_deg": quality["min_dihedral_deg"],
            "end_area_mm2": [float(area[tags == t].sum()) for t in (1, 2)], "toward": centroid[0] - centroid[1]}


def csa_at_shipped_plane(old: geo.Geometry, new: geo.Geometry) -> float:
    """(new mesh's cut area / shipped CSA0) - 1, both cut by the shipped mesh's CSA0 plane."""

    origin, normal = section.principal_plane(section.global_vertices(old.mesh))
    shipped_area = section.CutSection(old.mesh, origin, normal).area0()
    return section.CutSection(new.mesh, origin, normal).area0() / shipped_area - 1


def vertex_plane(geometry: geo.Geometry) -> dict:
    """Where the simulation's CSA0 plane (the vertices' mean and principal axis, MODEL.md §4)
    lies against the solid's (centroid, inertia axis): the distance of its origin along the
    solid's axis (mm) and the angle between the two normals (°)."""

    origin, normal = section.principal_plane(section.global_vertices(geometry.mesh))
    solid_origin, solid_normal = section.solid_plane(geometry.mesh)
    return {"offset_mm": float(abs((origin - solid_origin) @ solid_normal)) / geo.MM,
            "tilt_deg": float(np.degrees(np.arccos(min(1.0, abs(float(normal @ solid_normal))))))}


def fibre_angle(old: geo.Geometry, new: geo.Geometry, new_fibres: Path) -> float:
    """Mean angle (°) between the shipped fibres and the new ones, weighted by the shipped cells' volume."""
    from scipy.spatial import cKDTree


    old_cells = fibers.cell_fibers(old, fibers.load(old))
    new_cells = fibers.cell_fibers(new, fibers.load(new, new_fibres))
    _, nearest = cKDTree(new_cells[0]).query(old_cells[0])
    cosine = np.abs(np.einsum("ij,ij->i", old_cells[1], new_cells[1][nearest]))
    return float(np.degrees(np.average(np.arccos(np.clip(cosine, 0.0, 1.0)), weights=old_cells[2])))


def surface(path: Path) -> dict:
    """Volume (mm³), CSA (mm²) and length (mm) of an STL by its solid's frame."""

    points, triangles = hm.read_stl(path)
    moments = section.surface_solid_moments(points, triangles)
    origin, normal = section.inertia_plane(*moments)
    return {"volume_mm3": moments[0], "csa_solid_mm2": section.surface_cut_area(points, triangles, origin, normal),
            "length_solid_mm": float(np.ptp(points @ normal))}


def growth(geometry, a0, protocol: str = GROWTH_PROTOCOL) -> dict:
    """Percent increase of the CSA (the simulation's plane), the volume and the CSA on the
    solid's plane after ``protocol`` on ``geometry`` (default settings and parameters)."""
    from dolfinx import fem


    model = build_model(geometry, a0, protocols.named(protocol), material=MaterialParams(),
                         settings=GrowthSettings())
    *_, last = model.run()
    # The displacement alone, to measure Nanson's area on another plane of the same run.
    space, dofs = model.problem.w.function_space.sub(0).collapse()
    u = fem.Function(space)
    u.x.array[:] = model.problem.w.x.array[dofs]
    solid = section.CutSection(geometry.mesh, *section.solid_plane(geometry.mesh),
                               degree=geometry.quadrature_degree)
    return {"csa_pct": 100 * (last.csa_ratio - 1), "volume_pct": 100 * (last.volume_ratio - 1),
            "csa_solid_pct": 100 * (solid.deformed_area(u) / solid.area0() - 1)}


def parser() -> cli.Parser:
    p = cli.Parser("bench mesh", __doc__)
    made = [n for n in geo.ANATOMICAL if (SURFACES / f"{Path(geo.GEOMETRIES[n]).parent.name}.stl").is_file()]
    p.add_argument("--geometries", nargs="+", metavar="ID", default=made, help="shipped meshes with a surface")
    p.add_argument("--surfaces", type=Path, default=SURFACES, help="folder of the STL surfaces")
    p.add_argument("--output", type=Path, default=Path("results/bench"), help="folder for mesh.json and the meshes")
    p.add_argument("--growth", action="store_true", help=f"also run the 9-week {GROWTH_PROTOCOL!r} growth on both "
                   "meshes (about 30 s each on 1 core)")
    return p


def run(comm, args) -> int:
    rows = []
    for name in args.geometries:
        if name not in geo.ANATOMICAL:
            raise InputError(f"--geometries: {name!r} is not a shipped anatomical mesh")
        path = args.surfaces / f"{Path(geo.GEOMETRIES[name]).parent.name}.stl"
        old = shipped(name)
        folder = args.output / "mesh" / name
        start = time.perf_counter()
        status = mesh_job.main([str(path), "--output", str(folder), "--force", "--method", "stokes",
                                "--origin-toward", *map(str, old["toward"])], comm=comm)
        seconds = time.perf_counter() - start
        if status != cli.EXIT_OK:
            raise InputError(f"{name}: hyper mesh failed (exit {status})")
        record = json.loads((folder / "mesh.json").read_text())
        new = record["statistics"]
        meshes = {"shipped": geo.load(name, comm),
                  "new": geo.load_file(folder / f"{name}.xdmf", comm, name=name, scale=geo.MM)}
        ref = meshstats.statistics(meshes["shipped"])
        stl = surface(path)
        target = {"volume_cm3": stl["volume_mm3"] / 1e3, "csa_solid_cm2": stl["csa_solid_mm2"] / 1e2,
                  "length_solid_cm": stl["length_solid_mm"] / 10}
        row = {"geometry": name, "seconds": seconds, "cells": new["cells"], "cells_shipped": old["cells"],
               "min_dihedral_deg": record["quality"]["min_dihedral_deg"],
               "min_dihedral_deg_shipped": old["min_dihedral_deg"],
               "surface_offset_mm": record["quality"].get("surface_offset_mm", 0.0),
               "stl": target,
               **{f"{k}_diff": new[k] / target[k] - 1 for k in target},
               **{f"{k}_diff_shipped": ref[k] / target[k] - 1 for k in target},
               **{f"{k}_diff_new_shipped": new[k] / ref[k] - 1 for k in (*target, "csa0_cm2", "length_cm")},
               "csa0_vs_solid_shipped": ref["csa0_cm2"] / ref["csa_solid_cm2"] - 1,
               "csa_shipped_plane_diff": csa_at_shipped_plane(meshes["shipped"], meshes["new"]),
               "csa0_vs_stl": new["csa0_cm2"] / target["csa_solid_cm2"] - 1,
               "vertex_plane": {k: vertex_plane(g) for k, g in meshes.items()},
               "end_area_ratio": [a / b for a, b in zip(record["end_area_mm2"], old["end_area_mm2"])],
               "fibre_angle_deg": fibre_angle(meshes["shipped"], meshes["new"], folder / fibers.FILE_NAME)}
        info(comm, f"{name:<15} {seconds:5.1f} s {row['cells']:>6}/{old['cells']:<5} cells, dihedral "
                   f"{row['min_dihedral_deg']:4.1f}/{old['min_dihedral_deg']:4.1f}°; against the STL (new, shipped): "
                   + "  ".join(f"{label} {100 * row[k + '_diff']:+5.2f} {100 * row[k + '_diff_shipped']:+5.2f} %"
                               for label, k in (("volume", "volume_cm3"), ("CSA", "csa_solid_cm2"),
                                                ("length", "length_solid_cm")))
                   + f"; CSA0 new/shipped {100 * row['csa0_cm2_diff_new_shipped']:+5.2f} %, shipped CSA0/CSA "
                   f"{100 * row['csa0_vs_solid_shipped']:+5.2f} %; ends x{row['end_area_ratio'][0]:.2f} "
                   f"x{row['end_area_ratio'][1]:.2f}  fibres {row['fibre_angle_deg']:.1f}°")
        if args.growth:
            grown = {k: growth(g, fibers.load(g, None if k == "shipped" else folder / fibers.FILE_NAME))
                     for k, g in meshes.items()}
            row["growth"] = {"protocol": GROWTH_PROTOCOL, **grown,
                             "difference_pp": {k: grown["new"][k] - grown["shipped"][k] for k in grown["new"]}}
            d = row["growth"]["difference_pp"]
            info(comm, f"{name:<15} {GROWTH_PROTOCOL}: CSA {grown['shipped']['csa_pct']:+.3f} -> "
                       f"{grown['new']['csa_pct']:+.3f} % ({d['csa_pct']:+.3f} pp), volume "
                       f"{grown['shipped']['volume_pct']:+.3f} -> {grown['new']['volume_pct']:+.3f} % "
                       f"({d['volume_pct']:+.3f} pp), CSA on the solid's plane {grown['shipped']['csa_solid_pct']:+.3f}"
                       f" -> {grown['new']['csa_solid_pct']:+.3f} % ({d['csa_solid_pct']:+.3f} pp)")
        rows.append(row)
    if comm.rank == 0:
        io.write_json(args.output / "mesh.json", {"rows": rows})
    info(comm, f"wrote {args.output / 'mesh.json'}")
    return cli.EXIT_OK


main = cli.entry(parser, run)

if __name__ == "__main__":
    sys.exit(main())
