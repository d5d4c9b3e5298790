"""hyper mesh against the shipped meshes: each Visible Human surface that a shipped mesh
was made from (fTetWild, by the paper) is meshed again by `hyper mesh`, timed, and compared:

    time        STL -> checked surface -> tetrahedra -> tags -> Stokes fibres (1 rank)
    cells, min dihedral angle (both meshes)
    volume, CSA0, length   relative difference (hyper.meshstats' definitions; CSA0's plane
                is each mesh's own: through the mean of its vertices, normal to their
                principal axis, so it moves with the vertex distribution)
    CSA at the shipped plane   the new mesh cut by the shipped mesh's CSA0 plane
    end areas   of tags 1 and 2, new / shipped
    fibre angle volume-weighted mean over the shipped cells of the angle between the two
                fields (the new field taken at the nearest new cell centroid)

The origin is put at the shipped tag 1 (``--origin-toward`` from the shipped tag-2 end
to the tag-1 end), so both flows enter at the same end. Writes results/bench/mesh.json
and the meshes under results/bench/mesh/ (not meshes/: they are a check, not geometries).

    python -m hyper.bench mesh [--geometries TA_VHF_Left …]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np

from hyper import cli
from hyper import geometry as geo
from hyper.params import InputError

SURFACES = Path(__file__).resolve().parents[3].parent / "shared" / "surfaces"


def shipped(name: str) -> dict:
    """Cells, dihedral angle, end centroids and areas of a shipped mesh, from its file (mm)."""
    import h5py

    from hyper import mesh as hm

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


def csa_at_shipped_plane(comm, name: str, new_folder: Path) -> float:
    """(new mesh's cut area / shipped CSA0) - 1, both cut by the shipped mesh's CSA0 plane."""
    from hyper import section

    old = geo.load(name, comm)
    origin, normal = section.principal_plane(section.global_vertices(old.mesh))
    new = geo.load_file(new_folder / f"{new_folder.name}.xdmf", comm, name=new_folder.name, scale=geo.MM)
    shipped_area = section.CutSection(old.mesh, origin, normal).area0()
    return section.CutSection(new.mesh, origin, normal).area0() / shipped_area - 1


def fibre_angle(comm, name: str, new_folder: Path) -> float:
    """Mean angle (°) between the shipped fibres and the new ones, weighted by the shipped cells' volume."""
    from scipy.spatial import cKDTree

    from hyper import fibers

    old = geo.load(name, comm)
    old_cells = fibers.cell_fibers(old, fibers.load(old))
    new = geo.load_file(new_folder / f"{new_folder.name}.xdmf", comm, name=new_folder.name, scale=geo.MM)
    new_cells = fibers.cell_fibers(new, fibers.load(new, new_folder / fibers.FILE_NAME))
    _, nearest = cKDTree(new_cells[0]).query(old_cells[0])
    cosine = np.abs(np.einsum("ij,ij->i", old_cells[1], new_cells[1][nearest]))
    return float(np.degrees(np.average(np.arccos(np.clip(cosine, 0.0, 1.0)), weights=old_cells[2])))


def parser() -> cli.Parser:
    p = cli.Parser("bench mesh", __doc__)
    made = [n for n in geo.ANATOMICAL if (SURFACES / f"{Path(geo.GEOMETRIES[n]).parent.name}.stl").is_file()]
    p.add_argument("--geometries", nargs="+", metavar="ID", default=made, help="shipped meshes with a surface")
    p.add_argument("--surfaces", type=Path, default=SURFACES, help="folder of the STL surfaces")
    p.add_argument("--output", type=Path, default=Path("results/bench"), help="folder for mesh.json and the meshes")
    return p


def run(comm, args) -> int:
    from hyper import mesh as hm
    from hyper import meshstats
    from hyper.io import atomic_path
    from hyper.log import info

    rows = []
    for name in args.geometries:
        if name not in geo.ANATOMICAL:
            raise InputError(f"--geometries: {name!r} is not a shipped anatomical mesh")
        surface = args.surfaces / f"{Path(geo.GEOMETRIES[name]).parent.name}.stl"
        old = shipped(name)
        folder = args.output / "mesh" / name
        start = time.perf_counter()
        status = hm.main([str(surface), "--output", str(folder), "--force",
                          "--origin-toward", *map(str, old["toward"])], comm=comm)
        seconds = time.perf_counter() - start
        if status != cli.EXIT_OK:
            raise InputError(f"{name}: hyper mesh failed (exit {status})")
        record = json.loads((folder / "mesh.json").read_text())
        new = record["statistics"]
        ref = meshstats.statistics(geo.load(name, comm))
        row = {"geometry": name, "seconds": seconds, "cells": new["cells"], "cells_shipped": old["cells"],
               "min_dihedral_deg": record["quality"]["min_dihedral_deg"],
               "min_dihedral_deg_shipped": old["min_dihedral_deg"],
               **{f"{k}_diff": new[k] / ref[k] - 1 for k in ("volume_cm3", "csa0_cm2", "length_cm")},
               "csa_shipped_plane_diff": csa_at_shipped_plane(comm, name, folder),
               "end_area_ratio": [a / b for a, b in zip(record["end_area_mm2"], old["end_area_mm2"])],
               "fibre_angle_deg": fibre_angle(comm, name, folder)}
        rows.append(row)
        info(comm, f"{name:<15} {seconds:5.1f} s {row['cells']:>6}/{old['cells']:<5} cells, dihedral "
                   f"{row['min_dihedral_deg']:4.1f}/{old['min_dihedral_deg']:4.1f}°  volume "
                   f"{100 * row['volume_cm3_diff']:+5.2f} %  CSA0 {100 * row['csa0_cm2_diff']:+5.2f} %  length "
                   f"{100 * row['length_cm_diff']:+5.2f} %  CSA at shipped plane "
                   f"{100 * row['csa_shipped_plane_diff']:+5.2f} %  ends x{row['end_area_ratio'][0]:.2f} "
                   f"x{row['end_area_ratio'][1]:.2f}  fibres {row['fibre_angle_deg']:.1f}°")
    if comm.rank == 0:
        with atomic_path(args.output / "mesh.json") as tmp:
            tmp.write_text(json.dumps({"rows": rows}, indent=2) + "\n")
    info(comm, f"wrote {args.output / 'mesh.json'}")
    return cli.EXIT_OK


main = cli.entry(parser, run)

if __name__ == "__main__":
    sys.exit(main())
