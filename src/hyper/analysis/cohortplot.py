"""The cohort's figures (rank 0, from the complete files): ratios.png, the final CSA and
volume change by muscle and protocol (Fig. 6C–D analog), and shape.png, the grown shape
of one geometry per protocol (Fig. 6A analog)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hyper.analysis.cohortstats import PAPER_MWF_INCREASE, group, group_statistics, percent
from hyper.runs import plot

PICTURE_SCALE = 10.0  # displacement amplification of the shape picture (the paper's Fig. 6A)
SHAPE_GEOMETRY = "BFLH_VHF_Left"  # the paper's Fig. 6A


def ratio_figure(rows: list[dict], path: Path) -> None:
    """Final CSA and volume change per muscle and protocol: mean ± standard error over the
    members (bars), each member (dots), and the paper's mwf range (grey band)."""
    plt = plot.pyplot()
    groups = list(dict.fromkeys(group(r) for r in rows))
    names = list(dict.fromkeys(r["protocol"] for r in rows))
    width = 0.8 / len(names)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), layout="constrained")
    for ax, quantity, title in ((axes[0], "csa", "mid-belly CSA"), (axes[1], "volume", "volume")):
        stats = group_statistics(rows, quantity)
        if "mwf" in names:
            lo, hi = PAPER_MWF_INCREASE[quantity]
            ax.axhspan(lo, hi, color="0.85", zorder=0, label="paper, mwf")
        for j, name in enumerate(names):
            x = np.arange(len(groups)) + (j - (len(names) - 1) / 2) * width
            cells = [stats.get((g, name), {"mean": np.nan, "se": np.nan}) for g in groups]
            ax.bar(x, [c["mean"] for c in cells], width * 0.9, yerr=[np.nan_to_num(c["se"]) for c in cells],
                   capsize=3, label=name, zorder=2, color=plot.protocol_colour(name))
            for xi, g in zip(x, groups):
                values = [percent(r, quantity) for r in rows
                          if group(r) == g and r["protocol"] == name and r["status"] == "done"]
                ax.plot([xi] * len(values), values, "k.", ms=3, zorder=3)
        ax.set_xticks(range(len(groups)), groups)
        ax.set_ylabel(f"{title} change (%)")
        members = max((sum(group(r) == g and r["protocol"] == n for r in rows) for g in groups for n in names),
                      default=0)
        ax.set_title(f"final {title}: mean ± standard error, dots: members" if members > 1
                     else f"final {title} (one member per bar: no spread)")
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=8)
    plot.save(fig, path, dpi=140)
    plt.close(fig)


def section_figure(rows: list[dict], path: Path) -> None:
    """The final CSA change along each muscle: one line per geometry over the fraction of its
    length (`hyper.analysis.cohortsummary.section_rows`), one panel per protocol."""
    plt = plot.pyplot()
    names = list(dict.fromkeys(r["protocol"] for r in rows))
    geometries = list(dict.fromkeys(r["geometry"] for r in rows))
    fig, axes = plt.subplots(1, len(names), figsize=(4.6 * len(names), 3.8), layout="constrained", squeeze=False,
                             sharey=True)
    for ax, name in zip(axes[0], names):
        for g in geometries:
            mine = [r for r in rows if r["protocol"] == name and r["geometry"] == g]
            if mine:
                ax.plot([100 * r["section"] for r in mine], [r["csa_change_percent"] for r in mine], ".-", label=g)
        ax.set_title(name)
        ax.set_xlabel("position along the principal axis (% of the length)")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("final CSA change (%)")
    axes[0][-1].legend(fontsize=7)
    plot.save(fig, path, dpi=140)
    plt.close(fig)


def final_fields(xdmf: Path) -> dict:
    """Mesh and the last snapshot of u and det Ḡ from a run's XDMF output (its .h5)."""
    import h5py

    def hours(name: str) -> float:
        return float(name.replace("_", "."))  # DOLFINx names a snapshot by its time, "." as "_"

    with h5py.File(Path(xdmf).with_suffix(".h5"), "r") as f:
        mesh = f["Mesh"][next(iter(f["Mesh"]))]  # one mesh, named after the mesh read
        last = max(f["Function/u"], key=hours)
        return {"x": mesh["geometry"][()], "cells": mesh["topology"][()].astype(np.int64),
                "u": f["Function/u"][last][()], "detGbar": f["Function/detGbar"][last][()].ravel(),
                "t": hours(last)}


def boundary_faces(x: np.ndarray, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The faces of a tetrahedral mesh that belong to one cell only, numbered so that
    their normals (b - a) × (c - a) point out of the mesh, and their cells."""
    local = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
    faces = cells[:, local].reshape(-1, 3)
    _, inverse, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True, return_counts=True)
    once = counts[inverse.ravel()] == 1
    faces, owner = faces[once], np.repeat(np.arange(len(cells)), 4)[once]
    opposite = cells.ravel()[np.flatnonzero(once)]  # local face i is opposite local vertex i
    a, b, c = (x[faces[:, i]] for i in range(3))
    inward = np.einsum("ij,ij->i", np.cross(b - a, c - a), x[opposite] - a) > 0
    faces[inward] = faces[inward][:, ::-1]
    return faces, owner


def shape_figure(fields: dict[str, dict], path: Path, title: str) -> None:
    """The grown shape per protocol (``fields``: protocol -> final_fields), displacement
    amplified PICTURE_SCALE×, long axis upright, boundary faces coloured by |u|."""
    from matplotlib import cm, colors
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    plt = plot.pyplot()
    first = next(iter(fields.values()))
    # Upright frame from the reference vertices: the first principal axis vertical.
    x0 = first["x"]
    centre = x0.mean(axis=0)
    _, vectors = np.linalg.eigh(np.cov((x0 - centre).T))
    frame = vectors[:, ::-1][:, [1, 2, 0]]  # (second, third, first) axis -> (x, y, z)
    top = max(float(np.linalg.norm(f["u"], axis=1).max()) for f in fields.values()) * 1e3
    norm = colors.Normalize(0.0, top)
    fig = plt.figure(figsize=(2.4 * len(fields) + 1.2, 6), layout="constrained")
    for k, (name, f) in enumerate(fields.items()):
        faces, _ = boundary_faces(f["x"], f["cells"])
        y = (f["x"] + PICTURE_SCALE * f["u"] - centre) @ frame * 1e2  # cm
        speed = np.linalg.norm(f["u"], axis=1)[faces].mean(axis=1) * 1e3  # mm
        ax = fig.add_subplot(1, len(fields), k + 1, projection="3d")
        ax.add_collection3d(Poly3DCollection(y[faces], facecolors=cm.viridis(norm(speed)), linewidths=0,
                                             shade=True, lightsource=colors.LightSource(azdeg=225, altdeg=45)))
        lo, hi = y.min(axis=0), y.max(axis=0)
        ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), zlim=(lo[2], hi[2]), xticks=[], yticks=[])
        ax.set_box_aspect(hi - lo)  # equal scales on the three axes
        ax.view_init(elev=15, azim=-60)
        ax.set_title(f"{name}, day {f['t'] / 24:.0f}\nmean det Ḡ {f['detGbar'].mean():.4f}", fontsize=10)
    fig.colorbar(cm.ScalarMappable(norm=norm, cmap="viridis"), ax=fig.axes, shrink=0.6, label="|u| (mm)")
    fig.suptitle(f"{title}: grown shape, displacement ×{PICTURE_SCALE:g} (axis: cm along the muscle)")
    plot.save(fig, path, dpi=140)
    plt.close(fig)

