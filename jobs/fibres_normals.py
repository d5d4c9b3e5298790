# ruff: noqa: E402, E501, E702
# (the experiment as it was run for docs/convergence.md; kept to rerun its numbers, not as library code)
"""Does the slip direction make the Stokes fibres of a wide muscle move with the mesh?
(docs/convergence.md, "Why the male VL's fibres do not converge"). The meshes of a finished
convergence study (`--output DIR`), each level's Stokes fibres (l = 2 mm, as `hyper mesh`)
with the slip condition along the vertex normal (the stored method) and along a normal
smoothed over SIGMA mm (a Gaussian of the facets' area normals of the same end or lateral
surface, facets facing the other way left out), against the finest level of the same
variant at the level's nodes. Run from the repository root, 1 core:

    python jobs/fibres_normals.py results/bench/convergence_64k/convergence/VL_VHM_Left 0 3 6
"""
import argparse
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401
import numpy as np
from dolfinx.mesh import entities_to_geometry
from mpi4py import MPI
from scipy.spatial import cKDTree

from hyper.commands.bench import convergence as cv
from hyper.fem import fibers
from hyper.fem import geometry as geo

p = argparse.ArgumentParser()
p.add_argument("folder", type=Path); p.add_argument("sigmas", type=float, nargs="+")
p.add_argument("--levels", default="")
a = p.parse_args()
comm = MPI.COMM_SELF
vertex = fibers.vertex_normal


def smoothed_normal(sigma_m):
    def normal(space, ds):
        n = vertex(space, ds)
        if sigma_m == 0:
            return n
        mesh = space.mesh
        tags = ds.subdomain_data()
        facets = tags.find(ds.subdomain_id())
        X = mesh.geometry.x[entities_to_geometry(mesh, 2, facets)]
        area_normal = 0.5 * np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0])
        centre = X.mean(axis=1)
        values = n.x.array.reshape(-1, 3)
        xdof = space.tabulate_dof_coordinates()
        on = np.flatnonzero(np.linalg.norm(values, axis=1) > 0)
        # orient each facet as the vertex normals of its corners say (outward)
        tree_dof = cKDTree(xdof[on])
        _, k = tree_dof.query(X.reshape(-1, 3))
        mean_vn = values[on[k]].reshape(-1, 3, 3).sum(axis=1)
        area_normal *= np.sign(np.einsum("ij,ij->i", area_normal, mean_vn))[:, None]
        tree = cKDTree(centre)
        for i, near in zip(on, tree.query_ball_point(xdof[on], 3 * sigma_m)):
            near = np.asarray(near, dtype=int)
            w = np.exp(-0.5 * (np.linalg.norm(centre[near] - xdof[i], axis=1) / sigma_m) ** 2)
            w *= area_normal[near] @ values[i] > 0
            s = (area_normal[near] * w[:, None]).sum(axis=0)
            values[i] = s / np.linalg.norm(s)
        n.x.scatter_forward()
        return n
    return normal


folders = sorted((f for f in a.folder.iterdir() if f.is_dir()), key=lambda f: int(f.name.rsplit("_c", 1)[1]))
if a.levels:
    folders = [f for f in folders if f.name.rsplit("_c", 1)[1] in a.levels.split(",")]
levels = [cv.load_level(comm, f) for f in folders]
params = fibers.StokesParams(smoothing_m=2.0 * geo.MM)
for sigma in a.sigmas:
    fibers.vertex_normal = smoothed_normal(sigma * geo.MM)
    fields = []
    for g in levels:
        t = time.perf_counter()
        a0, speed = fibers.compute(g, params)
        st = fibers.statistics(g, a0, speed)
        fields.append(a0)
        print(f"sigma {sigma:g} mm, {g.num_cells()} cells: speed {st['min_speed']:.3f}-{st['max_speed']:.2f}, "
              f"within 30 deg {st['share_within_30deg']:.4f} ({time.perf_counter() - t:.0f} s)", flush=True)
    for g, a0 in zip(levels[:-1], fields[:-1]):
        r = cv.angles(a0, cv.unit(fibers.transferred(fields[-1], g)))
        print(f"sigma {sigma:g} mm, {g.num_cells()} against {levels[-1].num_cells()} cells: mean {r['mean_deg']:.2f}, "
              f"p95 {r['p95_deg']:.2f}, max {r['max_deg']:.1f} deg", flush=True)
