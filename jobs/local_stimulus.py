"""Where a muscle grows under the local stimulus (--stimulus local) against the global one: the
stimulus factor of the cells in a longitudinal slice, the final det Ḡ − 1 of those in the mid-belly
slab, the CSA change along the muscle (the regional sections) and the volume-weighted mean
det Ḡ − 1 from the axis to the surface; writes docs/local-stimulus.png (or OUT) from two results of `hyper grow`
with their fields files (docs/local-mechanosensing.md has the commands).
    python jobs/local_stimulus.py GLOBAL.h5 LOCAL.h5 [OUT.png]"""

import sys
from pathlib import Path

import h5py
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt

SLABS = 20  # along the principal axis
RINGS = 10  # from the axis to the surface
SLICE = 3e-3  # m, half the thickness of the longitudinal slice shown


def fields(result: Path) -> dict:
    """The mesh's cell centroids and volumes, the stimulus factor (ones without) and the last det Ḡ."""
    with h5py.File(result.with_name(result.stem + "_fields.h5")) as f:
        x = f["Mesh/Grid/geometry"][()]
        cells = f["Mesh/Grid/topology"][()]
        det = f["Function/detGbar"]
        last = max(det, key=float)
        out = {"det": det[last][()].ravel(), "t": float(last)}
        out["factor"] = (f["Function/stimulus_factor"][sorted(f["Function/stimulus_factor"], key=float)[0]][()].ravel()
                         if "stimulus_factor" in f["Function"] else np.ones(len(cells)))
    p = x[cells]
    out["centroid"] = p.mean(axis=1)
    out["volume"] = np.abs(np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))) / 6
    return out


def series(result: Path) -> dict:
    with h5py.File(result) as f:
        return {"sections": f["csa_ratio_sections"][-1], "fractions": f.attrs["section_fractions"],
                "csa": f["csa_ratio"][-1], "volume": f["volume_ratio"][-1], "geometry": f.attrs["geometry"],
                "wall_s": float(f.attrs["wall_s"])}


def main(glob_path: Path, local_path: Path, out: Path) -> None:
    runs = {"global": (fields(glob_path), series(glob_path)), "local": (fields(local_path), series(local_path))}
    local = runs["local"][0]
    # the principal axes of the cells' centroids (volume-weighted): the side view and the slabs
    c = local["centroid"] - np.average(local["centroid"], axis=0, weights=local["volume"])
    _, _, axes = np.linalg.svd(c * np.sqrt(local["volume"])[:, None], full_matrices=False)
    along, across = c @ axes[0], c @ axes[1]
    depth = c @ axes[2]
    s = (along - along.min()) / np.ptp(along)  # 0 … 1 along the muscle
    # the distance from the axis over the largest one in the cell's slab: 0 the core, 1 the surface
    r = np.hypot(across, depth)
    slab = np.minimum((s * SLABS).astype(int), SLABS - 1)
    rho = r / np.array([r[slab == k].max() for k in range(SLABS)])[slab]
    fig, ax = plt.subplots(2, 2, figsize=(11, 8), layout="constrained")
    cut = np.abs(depth) < SLICE  # a longitudinal slice through the axis
    im = ax[0, 0].scatter(1e3 * along[cut], 1e3 * across[cut], c=local["factor"][cut], s=6, cmap="viridis")
    ax[0, 0].set_aspect("equal")
    ax[0, 0].set(xlabel="along the principal axis (mm)", ylabel="across (mm)",
                 title=f"cells within {1e3 * SLICE:g} mm of the axial plane")
    fig.colorbar(im, ax=ax[0, 0], label="stimulus factor $s_c$", shrink=0.8)
    mid = np.abs(s - 0.5) < 0.5 / SLABS  # the mid-belly slab
    im = ax[0, 1].scatter(1e3 * across[mid], 1e3 * depth[mid], c=100 * (local["det"][mid] - 1), s=14, cmap="magma")
    ax[0, 1].set_aspect("equal")
    ax[0, 1].set(xlabel="across (mm)", ylabel="depth (mm)", title="mid-belly slab (45–55 % of the length)")
    fig.colorbar(im, ax=ax[0, 1], label=r"det $\bar G$ − 1 (%), local", shrink=0.8)
    edges = np.linspace(0.0, 1.0, RINGS + 1)
    ring = np.minimum((rho * RINGS).astype(int), RINGS - 1)
    for name, style in (("global", "o--"), ("local", "s-")):
        f, res = runs[name]
        label = f"{name}: mid-belly CSA {100 * (res['csa'] - 1):+.2f} %, V {100 * (res['volume'] - 1):+.2f} %"
        ax[1, 0].plot(100 * res["fractions"], 100 * (res["sections"] - 1), style, label=label)
        mean = [np.average(f["det"][ring == k] - 1, weights=f["volume"][ring == k]) for k in range(RINGS)]
        ax[1, 1].plot(0.5 * (edges[1:] + edges[:-1]), 100 * np.array(mean), style, label=name)
    ax[1, 0].set_xlabel("section (% of the length)")
    ax[1, 0].set_ylabel("CSA change (%)")
    ax[1, 0].legend(fontsize=8)
    ax[1, 1].set_xlabel("distance from the axis / the largest in its slab (0: core, 1: surface)")
    ax[1, 1].set_ylabel(r"volume-weighted mean det $\bar G$ − 1 (%)")
    ax[1, 1].legend(fontsize=8)
    for a in ax[1]:
        a.grid(alpha=0.3)
    g = runs["local"][1]["geometry"]
    fig.suptitle(f"{g}, mwf, t = {local['t']:g} h: local mechanosensing against the global stimulus")
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")
    for name, (f, r) in runs.items():
        d = f["det"] - 1
        print(f"{name}: CSA {100 * (r['csa'] - 1):+.3f} %, V {100 * (r['volume'] - 1):+.3f} %, det Ḡ − 1 per cell "
              f"{100 * d.min():.3f} … {100 * d.max():.3f} %, sections {np.round(100 * (r['sections'] - 1), 2)}, "
              f"factor {f['factor'].min():.3f} … {f['factor'].max():.3f}, wall {r['wall_s']:.1f} s")


if __name__ == "__main__":
    args = [Path(a) for a in sys.argv[1:]]
    main(args[0], args[1], args[2] if len(args) > 2 else Path("docs/local-stimulus.png"))
