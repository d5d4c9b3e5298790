"""Fibres from data at issue 34's size: a 128³ NIfTI image onto a 31 104-cell mesh (budget:
30 s on one core).

The mesh: a box 40 × 40 × 200 mm (12 × 12 × 36 cubes of 6 tetrahedra, ends tagged 1 and 2,
the side 3). The images: 128³ voxels of 1.72 mm over the box and a margin of 10 mm, the
tissue the voxels inside the box and one voxel beyond; a fanning field (the pennation angle growing linearly
from -20° to 20° across the box's width) as the primary eigenvector (3 components) and as
a diffusion tensor (6, eigenvalues 1.7e-3 and 0.4e-3 mm²/s), gzipped, written before the
clock starts. Timed: `hyper.fem.fiberdata.make` whole (reading and decompressing the
image, sampling the 6253 nodes, filling, signs, the report), and the reading alone; the
recovered field against the exact one (mean and 95th percentile of the angle at the
nodes) says the timed work is the real one. Writes results/bench/fiberdata.json and
fiberdata.png.

    python -m hyper.bench fiberdata [--voxels 128] [--repeat 3]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx)
import numpy as np
from dolfinx import mesh as dmesh

from hyper.commands import cli
from hyper.commands.bench import common
from hyper.core import io
from hyper.core.log import info
from hyper.fem import fiberdata
from hyper.fem import fiberread as fr
from hyper.fem import geometry as geo
from hyper.runs import plot

BOX_M = (0.04, 0.04, 0.2)
CUBES = (12, 12, 36)
MARGIN_M = 0.01
BUDGET_S = 30.0  # issue 34


def box(comm) -> geo.Geometry:
    """The bench's box, its ends (z = 0, z = 0.2 m) and side tagged."""
    mesh = dmesh.create_box(comm, [np.zeros(3), np.array(BOX_M)], list(CUBES), dmesh.CellType.tetrahedron)
    mesh.topology.create_connectivity(2, 3)
    facets = dmesh.exterior_facet_indices(mesh.topology)
    midpoints = dmesh.compute_midpoints(mesh, 2, facets)
    tags = np.full(len(facets), 3, dtype=np.int32)
    tags[np.isclose(midpoints[:, 2], 0.0)] = 1
    tags[np.isclose(midpoints[:, 2], BOX_M[2])] = 2
    order = np.argsort(facets)
    return geo.Geometry("box", mesh, dmesh.meshtags(mesh, 2, facets[order], tags[order]), ends=(1, 2), lateral=3)


def fanning(x_m: np.ndarray) -> np.ndarray:
    theta = np.radians(20.0) * (2.0 * x_m[:, 0] / BOX_M[0] - 1.0)
    return np.column_stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)])


def images(folder: Path, voxels: int) -> tuple[Path, Path]:
    """The eigenvector and the tensor image of the fanning field (rank 0)."""
    import nibabel

    low = -MARGIN_M * np.ones(3)
    spacing = (BOX_M[2] + 2 * MARGIN_M) / (voxels - 1)
    ijk = np.stack(np.meshgrid(*(np.arange(voxels),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    world = low + ijk * spacing
    tissue = np.all((world >= -spacing) & (world <= np.array(BOX_M) + spacing), axis=1)  # one voxel beyond
    a = np.where(tissue[:, None], fanning(world), 0.0)
    d = 0.4e-3 * np.eye(3) + 1.3e-3 * a[:, :, None] * a[:, None, :]
    d[~tissue] = 0.0
    affine = np.diag([spacing * 1e3] * 3 + [1.0])
    affine[:3, 3] = low * 1e3
    paths = folder / "v1.nii.gz", folder / "tensor.nii.gz"
    for path, values in zip(paths, (a, np.stack([d[:, i, j] for i, j in fr.FSL_ORDER], axis=-1))):
        image = nibabel.Nifti1Image(values.reshape(voxels, voxels, voxels, -1).astype(np.float32), affine)
        image.header.set_xyzt_units("mm")
        nibabel.save(image, path)
    return paths


def parser() -> cli.Parser:
    p = cli.Parser("bench fiberdata", __doc__)
    p.add_argument("--voxels", type=cli.integer(16, 256), default=128, help="voxels along each side of the images")
    p.add_argument("--repeat", type=cli.integer(1, 10), default=3, help="timings of each image (the fastest kept)")
    p.add_argument("--output", type=Path, default=Path("results/bench"), help="output folder")
    return p


def run(comm, args) -> int:
    folder = args.output / "fiberdata"
    if comm.rank == 0:
        folder.mkdir(parents=True, exist_ok=True)
        paths = images(folder, args.voxels)
    paths = comm.bcast(paths if comm.rank == 0 else None, root=0)
    geometry = box(comm)
    cases = []
    for path in paths:
        source = fr.Source(path)
        made, read = [], []
        for _ in range(args.repeat):
            comm.barrier()
            start = time.perf_counter()
            a0, field = fiberdata.make(geometry, source)
            made.append(comm.allreduce(time.perf_counter() - start, op=max))
            if comm.rank == 0:
                start = time.perf_counter()
                fiberdata.read(source)
                read.append(time.perf_counter() - start)
        n = a0.function_space.dofmap.index_map.size_local
        x = fiberdata.node_coordinates(a0.function_space)[:n]
        err = np.concatenate(comm.allgather(fiberdata.angles(a0.x.array.reshape(-1, 3)[:n], fanning(x))))
        case = {"image": path.name, "kind": "tensor" if "tensor" in path.name else "vector",
                "voxels": args.voxels, "bytes": path.stat().st_size, "make_s": min(made),
                "read_s": min(read) if read else None, "coverage": field.coverage,
                "error_mean_deg": float(err.mean()), "error_p95_deg": float(np.percentile(err, 95))}
        cases.append(case)
        info(comm, f"{path.name}: {args.voxels}³ voxels onto {geometry.num_cells()} cells, "
                   f"{field.report['nodes']} nodes: {case['make_s']:.2f} s (reading {case['read_s']:.2f} s), "
                   f"coverage {100 * field.coverage:.1f} %, error mean {case['error_mean_deg']:.3f}°, "
                   f"95 % {case['error_p95_deg']:.3f}°; budget {BUDGET_S:g} s: "
                   f"{'within' if case['make_s'] <= BUDGET_S else 'OVER'}")
    result = {"benchmark": "fiberdata", "ranks": comm.size, "cells": geometry.num_cells(), "budget_s": BUDGET_S,
              "cases": cases, "machine": common.machine(), "versions": io.versions()}
    if comm.rank == 0:
        io.write_json(args.output / "fiberdata.json", result)
        chart(args.output / "fiberdata.png", result)
        info(comm, f"wrote {args.output / 'fiberdata.json'} and {args.output / 'fiberdata.png'}")
    return 0


def chart(path: Path, result: dict) -> None:
    plt = plot.pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.2), layout="constrained")
    names = [f"{c['kind']} ({c['voxels']}³)" for c in result["cases"]]
    reading = [c["read_s"] for c in result["cases"]]
    rest = [c["make_s"] - c["read_s"] for c in result["cases"]]
    ax.barh(names, reading, color="0.6", label="reading the image")
    ax.barh(names, rest, left=reading, color="C0", label="sampling, filling, signs, report")
    ax.axvline(result["budget_s"], color="C3", ls="--", label=f"budget {result['budget_s']:g} s")
    ax.set_xlabel(f"seconds onto {result['cells']} cells, {result['ranks']} rank(s)")
    ax.legend(fontsize=8)
    plot.save(fig, path, dpi=110)


main = cli.entry(parser, run)

if __name__ == "__main__":
    sys.exit(main())
