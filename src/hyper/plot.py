"""Figures: one place that picks matplotlib's file backend and saves atomically.

Jobs run on clusters without a screen, so the backend is Agg, chosen here once,
before pyplot is first imported; `save` writes through `hyper.io.atomic_path`, so a
killed job never leaves half a PNG that looks whole.
"""

from __future__ import annotations

from pathlib import Path


def pyplot():
    """matplotlib.pyplot on the Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig, path: str | Path, *, dpi: int = 150) -> Path:
    """Write ``fig`` to ``path`` (format from its suffix) atomically and close it."""
    from hyper import io

    path = Path(path)
    with io.atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".") or "png")
    pyplot().close(fig)
    return path


def growth_series(results: dict[str, dict], path: str | Path, data=(), errors=None) -> Path:
    """CSA, volume and kM against time for several protocols (the paper's Fig. 4C–E),
    with measured CSA courses (``data``: `hyper.measured.Measured`) and each protocol's
    RMSE against them (``errors``: protocol -> `hyper.measured.Comparison`) where given."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8), constrained_layout=True)
    for name, s in results.items():
        weeks = s["t"] / 168.0
        error = (errors or {}).get(name)
        label = name if error is None else f"{name} (RMSE {error.rmse_pp:.2f} pp)"
        axes[0].plot(weeks, 100 * (s["csa_ratio"] - 1), label=label)
        axes[1].plot(weeks, 100 * (s["volume_ratio"] - 1), label=name)
        axes[2].plot(weeks, s["kM"], label=name)
    for i, measured in enumerate(data):
        axes[0].plot(measured.t / 168.0, 100 * (measured.csa_ratio - 1), "k" + "osD^v"[i % 5], ms=4, mfc="none",
                     label=measured.label)
    axes[0].set_ylabel("CSA change (%)")
    axes[1].set_ylabel("volume change (%)")
    axes[2].set_ylabel("kM (1/h)")
    for ax in axes:
        ax.set_xlabel("time (weeks)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    return save(fig, path)
