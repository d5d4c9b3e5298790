# ruff: noqa: E402, E501, E702
# (the experiment as it was run for docs/convergence.md; kept to rerun its numbers, not as library code)
"""The end-to-end potential flow's fibres at degree 1 and 2 (docs/convergence.md): on the meshes
of a finished convergence study, φ with -Δφ = 0, uniform flux -1/|Γ1| into the origin end and
+1/|Γ2| out of the insertion end, none elsewhere, in P1 or P2; a0 = the projection of ∇φ onto
vector P1 (L2, or smoothed over l: `hyper.fem.laplace`), unit at the nodes; each level against the
finest at the level's nodes, beside the stored Stokes fibres of the same levels (their kinds and
shares within 30° of the axis printed as a table row per muscle). 1 core:

    python jobs/fibres_laplace.py results/bench/convergence_64k/convergence/VL_VHM_Left --degrees 1,2
    python jobs/fibres_laplace.py results/bench/convergence_full/convergence/*   # a table row per muscle
    python jobs/fibres_laplace.py results/bench/convergence_64k/convergence/* --smoothing 0,2
"""
import argparse
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

from hyper.commands.bench import convergence as cv
from hyper.fem import fibers
from hyper.fem import laplace as lp

p = argparse.ArgumentParser()
p.add_argument("folders", type=Path, nargs="+"); p.add_argument("--degrees", default="2")
p.add_argument("--smoothing", default="0", help="lengths l (mm) of the gradient's projection, comma-separated")
p.add_argument("--stokes", action=argparse.BooleanOptionalAction, default=True, help="the stored Stokes fibres too")
p.add_argument("--min-cells", type=int, default=8000, help="levels from this target up")
a = p.parse_args()
comm = MPI.COMM_SELF


rows = []
for study in a.folders:
    folders = sorted((f for f in study.iterdir() if f.is_dir() and int(f.name.rsplit("_c", 1)[1]) >= a.min_cells),
                     key=lambda f: int(f.name.rsplit("_c", 1)[1]))
    levels = [cv.load_level(comm, f) for f in folders]
    kinds = {"stokes": [fibers.load(g, f / fibers.FILE_NAME) for g, f in zip(levels, folders)]} if a.stokes else {}
    for degree in map(int, a.degrees.split(",")):
        for ell in map(float, a.smoothing.split(",")):
            t = time.perf_counter()
            params = lp.LaplaceParams(degree=degree, smoothing_m=ell * 1e-3)
            kinds[f"laplace P{degree} l={ell:g}"] = [lp.compute(g, params)[0] for g in levels]
            print(f"{study.name}: laplace P{degree} l = {ell:g} mm {time.perf_counter() - t:.0f} s for {len(levels)} "
                  "levels", flush=True)
    row = {"muscle": study.name}
    for kind, fields in kinds.items():
        row[kind] = [cv.angles(a0, cv.unit(fibers.transferred(fields[-1], g)))["p95_deg"]
                     for g, a0 in zip(levels[:-1], fields[:-1])]
        row[kind + " share"] = [fibers.aligned_share(g, a0, fibers.principal_axis(g)) for g, a0 in zip(levels, fields)]
    rows.append(row)
    print(f"| {study.name} | {' / '.join(str(g.num_cells()) for g in levels)} | "
          + " | ".join(" / ".join(f"{d:.1f}" for d in row[kind]) for kind in kinds) + " | "
          + " | ".join(" / ".join(f"{100 * s:.1f}" for s in row[kind + ' share']) for kind in kinds) + " |", flush=True)
    del levels, kinds
print(f"| within 3° (p95) at the first level, of {len(rows)} | | "
      + " | ".join(str(sum(r[k][0] <= 3.0 for r in rows)) for k in rows[0] if k != "muscle" and not k.endswith("share")) + " |")
