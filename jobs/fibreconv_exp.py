# ruff: noqa: E402, E501, E702
# (the experiment as it was run for docs/convergence.md; kept to rerun its numbers, not as library code)
"""Experiment of issue 32 item 2 (docs/convergence.md, "Why the fibres change"). Run from the
repository root, 1 core:

    FC_WORK=results/fibreconv python jobs/fibreconv_build.py TA_VHF_Left \
        ../shared/surfaces/VHF_Left_Muscle_TibialisAnterior_smooth.stl 4000,8000,16000,32000,64000
    FC_WORK=results/fibreconv python jobs/fibreconv_exp.py TA_VHF_Left \
        ../shared/surfaces/VHF_Left_Muscle_TibialisAnterior_smooth.stl --cells 8000,16000,32000,64000 \
        [--rule band3|stl|stlv] [--filter MM] [--normals vertex|stl] [--sigma MM]

(GM_VHF_Left: its surface VHF_Left_Muscle_GastrocnemiusMedial_smooth.stl, and `0,0,1` as the
build's fourth argument, the origin's direction.) build: gmsh meshes as `hyper mesh` makes
them, with the vertex rule's tags; exp: re-tag (band3 the vertex rule, stlv the STL's axis
with all three vertices in the band, stl the STL's axis and extent with facet centroids),
solve the Stokes fibres, smooth them (--filter l, `fibers.smoothed`), and print the angle of
each level's field to the finest one at the level's nodes (mean, p95, max)."""
import argparse
import math
import os
import time
from pathlib import Path

import numpy as np

WORK = os.environ.get('FC_WORK', 'results/fibreconv')
import dolfinx_solver  # noqa
import ufl
from dolfinx import fem
from mpi4py import MPI

from hyper.commands.bench.convergence import angles, unit
from hyper.fem import fibers
from hyper.fem import geometry as geo
from hyper.fem import meshing as hm

p = argparse.ArgumentParser()
p.add_argument("name"); p.add_argument("stl"); p.add_argument("--cells", default="4000,8000,16000,32000")
p.add_argument("--rule", default="band3", choices=("band3", "stl", "stlv"))
p.add_argument("--normals", default="vertex", choices=("vertex", "stl"))
p.add_argument("--degree", type=int, default=2)
p.add_argument("--tag", default="")
p.add_argument("--sigma", type=float, default=0.0, help="Gaussian smoothing of STL normals (mm)")
p.add_argument("--filter", type=float, default=0.0, help="Helmholtz filter length of the velocity (mm)")
a = p.parse_args()
comm = MPI.COMM_WORLD
pts, tris = hm.read_stl(Path(a.stl))
# STL frame: area-weighted surface covariance axis, extremes of the STL points
cov = hm.surface_covariance(pts, tris)
axis_stl = np.linalg.eigh(cov)[1][:, -1]
areas = hm.facet_areas(pts, tris)
centre_stl = (areas[:, None] * pts[tris].mean(axis=1)).sum(0) / areas.sum()
# STL vertex normals (area weighted)
c = pts[tris]
an = 0.5 * np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
vn = np.zeros_like(pts)
for i in range(3):
    np.add.at(vn, tris[:, i], an)
vn /= np.linalg.norm(vn, axis=1)[:, None]
from scipy.spatial import cKDTree

tree = cKDTree(pts)
if a.sigma > 0:
    vw = np.zeros(len(pts))
    for i in range(3):
        np.add.at(vw, tris[:, i], areas / 3)
    pairs = tree.query_ball_point(pts, 3 * a.sigma)
    sm = np.zeros_like(vn)
    for k, nb in enumerate(pairs):
        nb = np.asarray(nb); w = vw[nb] * np.exp(-0.5 * (np.linalg.norm(pts[nb] - pts[k], axis=1) / a.sigma) ** 2)
        sm[k] = (vn[nb] * w[:, None]).sum(0)
    vn = sm / np.linalg.norm(sm, axis=1)[:, None]

def stl_normal(x):
    d, i = tree.query(x, k=6)
    w = 1.0 / np.maximum(d, 1e-9) ** 2
    n = (vn[i] * w[..., None]).sum(1)
    return n / np.linalg.norm(n, axis=1)[:, None]

def tag(x, facets, tags0, toward):
    if a.rule == "band3":
        return tags0
    axis = axis_stl if axis_stl @ toward > 0 else -axis_stl
    along_pts = (pts - centre_stl) @ axis
    hi, lo = along_pts.max(), along_pts.min()
    width = hm.END_BAND * (hi - lo)
    cen = x[facets].mean(axis=1)
    s = (cen - centre_stl) @ axis
    if a.rule == "stlv":
        s3 = (x[facets] - centre_stl) @ axis
        s = np.where((s3 >= hi - width).all(1), hi, np.where((s3 <= lo + width).all(1), lo, 0.5 * (hi + lo)))
    corners = x[facets]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    side = np.abs(normal @ axis) < math.sin(math.radians(hm.PARALLEL_DEG))
    t = np.full(len(facets), 3, dtype=np.int32)
    t[(s >= hi - width) & ~side] = 1
    t[(s <= lo + width) & ~side] = 2
    return t

orig_vn = fibers.vertex_normal
def stl_vertex_normal(space, ds):
    n = orig_vn(space, ds)
    vals = n.x.array.reshape(-1, 3)
    on = np.linalg.norm(vals, axis=1) > 0
    xx = space.tabulate_dof_coordinates() / geo.MM
    vals[on] = stl_normal(xx[on])
    return n
if a.normals == "stl":
    fibers.vertex_normal = stl_vertex_normal

levels = []
for cells in map(int, a.cells.split(",")):
    d = np.load(f"{WORK}/{a.name}_{cells}.npz")
    tags = tag(d["x"], d["facets"], d["tags"], d["toward"])
    ar = hm.facet_areas(d["x"], d["facets"])
    path = Path(f"{WORK}/m/{a.name}_{cells}_{a.rule}.xdmf")
    path.parent.mkdir(exist_ok=True)
    hm.write_xdmf(comm, path, d["x"], d["tets"], d["facets"], tags)
    g = geo.load_file(path, comm, name=path.stem, scale=geo.MM)
    t = time.perf_counter()
    sf = fibers.StokesFibers(g, fibers.StokesParams(degree=a.degree))
    if a.filter > 0:
        u = sf.solve()
        V1 = sf.V1
        w, v = ufl.TrialFunction(V1), ufl.TestFunction(V1)
        ell2 = fem.Constant(g.mesh, (a.filter * geo.MM) ** 2)
        from dolfinx.fem.petsc import LinearProblem
        pr = LinearProblem((ufl.inner(w, v) + ell2 * ufl.inner(ufl.grad(w), ufl.grad(v))) * ufl.dx,
                           ufl.inner(u, v) * ufl.dx, petsc_options_prefix=f"flt{cells}_",
                           petsc_options={"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"})
        a0, speed = fibers.normalized(pr.solve(), 1e-6, "x")
    else:
        a0, speed = sf.fibers()
    st = fibers.statistics(g, a0, speed)
    print(f"{cells}: {g.num_cells()} cells, ends {ar[tags==1].sum():.1f} {ar[tags==2].sum():.1f} mm2, "
          f"min speed {st['min_speed']:.3f}, 30deg {st['share_within_30deg']:.4f}, {time.perf_counter()-t:.0f}s", flush=True)
    levels.append((cells, g, a0))
finest = levels[-1][2]
def p1_at(field, gfine, xq):
    """P1 field of gfine evaluated at points xq (m): containing tet among k nearest, else best."""
    from scipy.spatial import cKDTree
    m = gfine.mesh
    X = m.geometry.x
    T = m.geometry.dofmaps[0]
    # map geometry dofs -> P1 dofs
    V = field.function_space
    D = V.dofmap.list
    C = X[T]
    tree = cKDTree(C.mean(axis=1))
    _, cand = tree.query(xq, k=24)
    best = np.full(len(xq), -1); bestq = np.full(len(xq), -np.inf); bestlam = np.zeros((len(xq), 4))
    for j in range(cand.shape[1]):
        c = cand[:, j]
        A = C[c, 1:] - C[c, :1]
        lam123 = np.linalg.solve(np.transpose(A, (0, 2, 1)), (xq - C[c, 0])[..., None])[..., 0]
        lam = np.concatenate([1 - lam123.sum(1, keepdims=True), lam123], axis=1)
        q = lam.min(axis=1)
        better = q > bestq
        best[better] = c[better]; bestq[better] = q[better]; bestlam[better] = lam[better]
    lam = np.clip(bestlam, 0, None); lam /= lam.sum(1, keepdims=True)
    vals = field.x.array.reshape(-1, 3)[D[best]]
    return (vals * lam[..., None]).sum(1), bestq
def transfer(field, gfine, g):
    out = fem.Function(fem.functionspace(g.mesh, ("Lagrange", 1, (3,))))
    xq = out.function_space.tabulate_dof_coordinates()
    v, q = p1_at(field, gfine, xq)
    out.x.array[:] = v.ravel()
    return out
res = {}
for cells, g, a0 in levels[:-1]:
    r = angles(a0, unit(transfer(finest, levels[-1][1], g)))
    res[cells] = r
    print(f"{cells} vs {levels[-1][0]}: mean {r['mean_deg']:.2f} p95 {r['p95_deg']:.2f} max {r['max_deg']:.1f}", flush=True)
# store nodal fields for cross-variant comparisons
for cells, g, a0 in levels:
    np.savez(f"{WORK}/f_{a.name}_{cells}_{a.rule}_{a.normals}_p{a.degree}{a.tag}_s{a.sigma:g}_f{a.filter:g}.npz",
             x=g.mesh.geometry.x, a0=a0.x.array.reshape(-1, 3))
