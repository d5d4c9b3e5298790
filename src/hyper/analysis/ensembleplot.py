"""An ensemble's figures (the paper's Fig. 7): the states' cell mean ± spread (7A), CSA,
volume and kM against the uniform case (7B), and maps of the final N, det Ḡ and |u| (7C)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hyper.model import signaling
from hyper.runs import plot


def figures(uniform: dict, samples: dict[str, dict], folder: Path, title: str) -> list[Path]:
    """Fig. 7A (states), 7B (CSA, volume, kM) and 7C (maps of N, det Ḡ, |u|)."""
    plt = plot.pyplot()
    paths = [folder / "fig7a_states.png", folder / "fig7b_growth.png", folder / "fig7c_maps.png"]
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    names = {"igf1": "IGF1", "akt": "AKT", "foxo": "FOXO", "mtor": "mTOR", "N": "N"}

    fig, axes = plt.subplots(1, 5, figsize=(18, 3.6), constrained_layout=True)
    for ax, state in zip(axes, signaling.STATES):
        for i, (key, s) in enumerate(samples.items()):
            w = s["t"] / 168.0
            ax.fill_between(w, s[state] - s[f"{state}_std"], s[state] + s[f"{state}_std"],
                            color=colors[i % len(colors)], alpha=0.25, lw=0)
            ax.plot(w, s[state], color=colors[i % len(colors)], lw=0.8, label=key)
        ax.plot(uniform["t"] / 168.0, uniform[state], "k--", lw=1.0, label="uniform")
        ax.set_title(names[state])
        ax.set_xlabel("time (weeks)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"{title}: cell mean ± std across cells")
    plot.save(fig, paths[0], dpi=130)

    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8), constrained_layout=True)
    for key, label, scale in (("csa_ratio", "CSA change (%)", 100), ("volume_ratio", "volume change (%)", 100),
                              ("kM", "kM (1/h)", None)):
        ax = axes[["csa_ratio", "volume_ratio", "kM"].index(key)]
        for i, (name, s) in enumerate(samples.items()):
            y = scale * (s[key] - 1) if scale else s[key]
            ax.plot(s["t"] / 168.0, y, color=colors[i % len(colors)], lw=0.8, label=name)
        mean = np.mean([s[key] for s in samples.values()], axis=0)
        t = next(iter(samples.values()))["t"] / 168.0
        ax.plot(t, scale * (mean - 1) if scale else mean, color="C3", lw=2, alpha=0.6, label="ensemble mean")
        ax.plot(uniform["t"] / 168.0, scale * (uniform[key] - 1) if scale else uniform[key], "k--", lw=1.2,
                label="uniform")
        ax.set_ylabel(label)
        ax.set_xlabel("time (weeks)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(title)
    plot.save(fig, paths[1], dpi=130)

    first = next(iter(samples.values()))
    x = first["final_x"]
    centred = x - x.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    q = centred @ vt.T  # principal coordinates: long axis first
    spacing = (np.ptp(x, axis=0).prod() / len(x)) ** (1 / 3)
    slab = np.abs(q[:, 2]) < spacing
    fig, axes = plt.subplots(1, 3, figsize=(15, 5), constrained_layout=True)
    for ax, (key, label) in zip(axes, (("final_N", "N"), ("final_detGbar", "det Ḡ"), ("final_u", "|u| (mm)"))):
        v = first[key] * (1e3 if key == "final_u" else 1.0)
        sc = ax.scatter(1e3 * q[slab, 0], 1e3 * q[slab, 1], c=v[slab], s=12, cmap="viridis")
        fig.colorbar(sc, ax=ax, shrink=0.8)
        ax.set_title(f"{label}, {next(iter(samples))}")
        ax.set_aspect("equal")
        ax.set_xlabel("first principal axis (mm)")
    axes[0].set_ylabel("second principal axis (mm)")
    fig.suptitle(f"{title}: cells within {1e3 * spacing:.1f} mm of the principal plane, t = {first['t'][-1]:g} h")
    plot.save(fig, paths[2], dpi=130)
    return paths

