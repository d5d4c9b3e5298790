# ruff: noqa: E402, E501, E702
# (the experiment as it was run for docs/convergence.md; kept to rerun its numbers, not as library code)
"""Where a coarse mesh's Laplace fibres leave the converged field, and what brings them back
(docs/convergence.md, "The converged field"): the surface of a muscle meshed as `hyper mesh`
does at each of CELLS (the first is the mesh measured), each level's Laplace fibres, and at the
first level's nodes the 95th-percentile angle between every pair of levels, each field either
the level's own (the first) or carried onto the first's nodes (what `hyper mesh --flow-cells`
does); the first level's own field against the finest over its end nodes, its other surface
nodes and its interior; and the first mesh refined uniformly once and twice (its own polyhedron),
the discretisation error at fixed shape. Meshes are kept under results/fibres_limit_exp/NAME/
and reused. Run from the repository root, 1 core:

    python jobs/fibres_limit_exp.py VM_VHM_Left 8000 32000 64000 128000 256000 [--surfaces ../shared/surfaces]
"""
import argparse
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401
import numpy as np
from dolfinx import fem
from mpi4py import MPI

from hyper.commands import mesh as mesh_job
from hyper.commands.bench import convergence as cv
from hyper.fem import fibers
from hyper.fem import geometry as geo
from hyper.fem import laplace as lp

p = argparse.ArgumentParser()
p.add_argument("muscle"); p.add_argument("cells", type=int, nargs="+")
p.add_argument("--surfaces", type=Path, default=Path("../shared/surfaces"))
a = p.parse_args()
comm = MPI.COMM_SELF
name, stl, extra = cv.source(a.muscle, a.surfaces)
root = Path(f"results/fibres_limit_exp/{name}"); root.mkdir(parents=True, exist_ok=True)
levels = {}
for cells in a.cells:
    path = root / f"c{cells}" / f"c{cells}.xdmf"
    t = time.perf_counter()
    if path.is_file():
        g = cv.load_level(comm, path.parent)
    else:
        options = mesh_job.parser().parse_args([str(stl), "--output", str(root / "unused"), "--cells", str(cells), *extra])
        g = mesh_job.flow_mesh(comm, options, path, cells)
    meshed = time.perf_counter()
    levels[cells] = (g, lp.compute(g))
    print(f"{name} {cells}: {g.num_cells()} cells, mesh {meshed - t:.1f} s, Laplace {time.perf_counter() - meshed:.1f} s", flush=True)
first = a.cells[0]
g0 = levels[first][0]
at = {c: (levels[c][1][0] if c == first else fibers.carried_over(*levels[c][1], g0, lp.LaplaceParams().min_speed)[0]) for c in a.cells}
print(f"p95 angle (°) at the {first}-cell mesh's nodes, row level against column level (the first's own flow, the others carried):")
for i, c in enumerate(a.cells):
    print(f"  {c}: " + "  ".join(f"{d}: {cv.angles(at[c], at[d])['p95_deg']:.2f}" for d in a.cells[i + 1:]))
x, y = at[first].x.array.reshape(-1, 3), at[a.cells[-1]].x.array.reshape(-1, 3)
angle = np.degrees(np.arccos(np.clip(np.abs((x * y).sum(1)) / np.linalg.norm(y, axis=1), 0, 1)))
V = at[first].function_space
ends = np.unique(np.concatenate([fem.locate_dofs_topological(V, 2, g0.facet_tags.find(t)) for t in g0.ends]))
lateral = np.setdiff1d(np.unique(fem.locate_dofs_topological(V, 2, g0.facet_tags.find(g0.lateral))), ends)
inner = np.setdiff1d(np.arange(len(angle)), np.union1d(ends, lateral))
worst = angle > np.percentile(angle, 95)
for label, nodes in (("end nodes", ends), ("other surface nodes", lateral), ("interior nodes", inner)):
    print(f"  the {first}-cell field to the {a.cells[-1]}-cell one over its {label} ({len(nodes)}): p95 "
          f"{np.percentile(angle[nodes], 95):.2f}°, mean {angle[nodes].mean():.2f}°; {100 * worst[nodes].sum() / worst.sum():.0f} % of the worst 5 %")
fine, fields = g0, [levels[first][1][0]]
for k in (1, 2):
    t = time.perf_counter()
    fine = geo.refine(fine)
    fields.append(cv.unit(fibers.transferred(lp.compute(fine)[0], g0)))
    print(f"  refined {k}x: {fine.num_cells()} cells, {time.perf_counter() - t:.0f} s", flush=True)
print(f"fixed shape: the {first}-cell field to its mesh refined twice: p95 {cv.angles(fields[0], fields[2])['p95_deg']:.2f}°, "
      f"once against twice {cv.angles(fields[1], fields[2])['p95_deg']:.2f}°")
