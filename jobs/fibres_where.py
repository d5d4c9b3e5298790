# ruff: noqa: E402, E501, E702
# (the experiment as it was run for docs/convergence.md; kept to rerun its numbers, not as library code)
"""Where two meshes' fibres differ (docs/convergence.md, "All 30 surfaces"): the surface of a
muscle meshed at A and B cells as `hyper mesh` does, each flow smoothed over l, B's field at
A's nodes; the angle's 95th percentile over the end nodes (tags 1, 2), the other surface
nodes and the interior, and over tenths of the length. Run from the repository root, 1 core:

    python jobs/fibres_where.py ST_VHF_Left 16000 32000 2 [--surfaces ../shared/surfaces]
"""
import argparse
import shutil
from pathlib import Path

import numpy as np
from mpi4py import MPI

from hyper.commands.bench import convergence as cv
from hyper.fem import fibers

p = argparse.ArgumentParser()
p.add_argument("muscle"); p.add_argument("a", type=int); p.add_argument("b", type=int); p.add_argument("l", type=float)
p.add_argument("--surfaces", type=Path, default=Path("../shared/surfaces"))
a = p.parse_args()
comm = MPI.COMM_SELF
name, stl, extra = cv.source(a.muscle, a.surfaces)
scratch = Path(f"results/fibres_where/{name}")
shutil.rmtree(scratch, ignore_errors=True); scratch.mkdir(parents=True)
ga, fa, _ = cv.fibre_level(comm, stl, extra, a.a, scratch, (a.l,))
gb, fb, _ = cv.fibre_level(comm, stl, extra, a.b, scratch, (a.l,))
x, y = fa[a.l][0], cv.unit(fibers.transferred(fb[a.l][0], ga))
n = x.function_space.dofmap.index_map.size_local
u, v = x.x.array.reshape(-1, 3)[:n], y.x.array.reshape(-1, 3)[:n]
deg = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", u, v)), 0, 1)))
# nodes by where they lie (a P1 cell's dofs are its vertices, in the same order)
mesh = ga.mesh
dofs = x.function_space.dofmap.list
X = x.function_space.tabulate_dof_coordinates()[:n]
tag = np.zeros(n, dtype=int)
ft = ga.facet_tags
mesh.topology.create_connectivity(2, 0)
f2v = mesh.topology.connectivity(2, 0)
v2dof = np.zeros(mesh.topology.index_map(0).size_local + mesh.topology.index_map(0).num_ghosts, dtype=int)
mesh.topology.create_connectivity(3, 0)
c2v = mesh.topology.connectivity(3, 0)
for c in range(len(dofs)):
    v2dof[c2v.links(c)] = dofs[c]
for t in (3, 1, 2):  # ends last: a rim node counts as an end's
    for f in ft.find(t):
        d = v2dof[f2v.links(f)]; tag[d[d < n]] = t
axis = np.linalg.svd(X - X.mean(0), full_matrices=False)[2][0]
s = (X - X.mean(0)) @ axis; s = (s - s.min()) / np.ptp(s)
top = deg >= np.percentile(deg, 95)
print(f"{name} {a.a} vs {a.b}, l = {a.l:g} mm: mean {deg.mean():.2f}, p95 {np.percentile(deg, 95):.2f}, max {deg.max():.1f}")
for t, what in ((1, "origin end"), (2, "insertion end"), (3, "lateral surface"), (0, "interior")):
    m = tag == t
    print(f"  {what}: {m.sum()} nodes, p95 {np.percentile(deg[m], 95):.2f}, share of the worst 5 %: {top[m].sum() / top.sum():.2f}")
print("  by tenth of the length (0 = one tip): p95 " + " ".join(f"{np.percentile(deg[(s >= k / 10) & (s <= (k + 1) / 10)], 95):.1f}" for k in range(10)))
shutil.rmtree(scratch, ignore_errors=True)
