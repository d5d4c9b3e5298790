# ruff: noqa: E402, E501, E702
# (the experiment as it was run for docs/convergence.md; kept to rerun its numbers, not as library code)
"""The end-to-end potential flow's fibres at degree 1 and 2 (docs/convergence.md): on the meshes
of a finished convergence study, φ with -Δφ = 0, uniform flux -1/|Γ1| into the origin end and
+1/|Γ2| out of the insertion end, none elsewhere, in P1 or P2; a0 = the L2 projection of ∇φ onto
vector P1, unit at the nodes; each level against the finest at the level's nodes, beside the
stored Stokes fibres of the same levels. 1 core:

    python jobs/fibres_laplace.py results/bench/convergence_64k/convergence/VL_VHM_Left --degrees 1,2
    python jobs/fibres_laplace.py results/bench/convergence_full/convergence/*   # a table row per muscle
"""
import argparse
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401
import numpy as np
import ufl
from dolfinx import fem
from dolfinx.fem.petsc import LinearProblem
from mpi4py import MPI

from hyper.commands.bench import convergence as cv
from hyper.fem import fibers

p = argparse.ArgumentParser()
p.add_argument("folders", type=Path, nargs="+"); p.add_argument("--degrees", default="2")
p.add_argument("--min-cells", type=int, default=8000, help="levels from this target up")
a = p.parse_args()
comm = MPI.COMM_SELF
k = 0


def laplace(g, degree):
    global k
    k += 1
    mesh = g.mesh
    V = fem.functionspace(mesh, ("Lagrange", degree))
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    ds = ufl.Measure("ds", domain=mesh, subdomain_data=g.facet_tags)
    one = fem.Constant(mesh, 1.0)
    area = [fem.assemble_scalar(fem.form(one * ds(t))) for t in (1, 2)]
    index_map = V.dofmap.index_map
    local = np.arange(index_map.size_local + index_map.num_ghosts, dtype=np.int32)
    pinned = local[index_map.local_to_global(local) == 0]
    bc = fem.dirichletbc(np.float64(0.0), pinned, V)
    L = (-1.0 / area[0]) * v * ds(1) + (1.0 / area[1]) * v * ds(2)
    phi = LinearProblem(ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx, L, bcs=[bc], petsc_options_prefix=f"lp{k}_",
                        petsc_options={"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"}).solve()
    V1 = fem.functionspace(mesh, ("Lagrange", 1, (3,)))
    w, z = ufl.TrialFunction(V1), ufl.TestFunction(V1)
    grad = LinearProblem(ufl.inner(w, z) * ufl.dx, ufl.inner(ufl.grad(phi), z) * ufl.dx, petsc_options_prefix=f"lg{k}_",
                         petsc_options={"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"}).solve()
    return cv.unit(grad)


rows = []
for study in a.folders:
    folders = sorted((f for f in study.iterdir() if f.is_dir() and int(f.name.rsplit("_c", 1)[1]) >= a.min_cells),
                     key=lambda f: int(f.name.rsplit("_c", 1)[1]))
    levels = [cv.load_level(comm, f) for f in folders]
    kinds = {"stokes": [fibers.load(g, f / fibers.FILE_NAME) for g, f in zip(levels, folders)]}
    for degree in map(int, a.degrees.split(",")):
        t = time.perf_counter()
        kinds[f"laplace P{degree}"] = [laplace(g, degree) for g in levels]
        print(f"{study.name}: laplace P{degree} {time.perf_counter() - t:.0f} s for {len(levels)} levels", flush=True)
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
