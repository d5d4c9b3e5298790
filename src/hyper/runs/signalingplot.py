"""The signaling figure: the paper's Fig. 3A–E analog, protocols overlaid."""

from __future__ import annotations

import numpy as np

from hyper.model.protocols import WEEK, Protocol
from hyper.runs.plot import protocol_colour, pyplot

STYLES = {"weekly": (0, (4, 2))}  # dashed: weekly and mwf coincide until the second session
LABELS = {
    "mwf": "MWF: 3×/week, 1 h, I = 0.8",
    "every3days": "every 3 days: 4 h, I = 0.2",
    "weekly": "weekly: 1 h, I = 0.8",
    "daily15": "daily ×15: 1 h, I = 0.8",
    "rest": "rest",
}
PANELS = (
    ("igf1", "A", "IGF1"),
    ("akt", "B", "AKT"),
    ("foxo", "C", "FOXO"),
    ("mtor", "D", "mTOR"),
    ("N", "E", "myofibrils N"),
)


def figure_protocols(runs: dict, protocols: dict[str, Protocol], params, insets: dict | None = None):
    """Five panels (IGF1, AKT, FOXO, mTOR, N) over the protocols' time span, one line per
    protocol, with 24-hour insets of IGF1 and AKT after the first session start, and a
    sixth panel showing the sessions. ``runs[name]`` holds the series ``t, igf1, ..., N``;
    ``insets[name]`` the same over the first day, t in hours after the first session start.
    Returns the matplotlib Figure (Agg)."""
    plt = pyplot()
    from matplotlib.ticker import MaxNLocator

    end = max(p.end for p in protocols.values())
    weeks = end / WEEK
    fig, axes = plt.subplots(3, 2, figsize=(12, 10.5), constrained_layout=True)
    panels = axes.ravel()
    for (key, letter, label), ax in zip(PANELS, panels):
        for name, series in runs.items():
            ax.plot(series["t"] / WEEK, series[key], color=protocol_colour(name), ls=STYLES.get(name, "-"), lw=0.9,
                    label=LABELS.get(name, name))
        ax.set_title(f"{letter}   {label}", loc="left", fontweight="bold")
        ax.set_xlim(0, weeks)
        ax.set_xticks(np.arange(0, np.floor(weeks) + 1))
        ax.set_xlabel("time (weeks)")
        ax.set_ylabel(f"{label} (normalized)")
        ax.grid(alpha=0.25)
    for key, ax, theta, name in (("foxo", panels[2], params.thetaF, "θF"), ("mtor", panels[3], params.thetaM, "θM")):
        if np.ndim(theta) == 0:
            ax.axhline(theta, color="k", ls="--", lw=0.8)
            ax.annotate(f"threshold {name} = {theta:g}", (0.99, theta), xycoords=("axes fraction", "data"),
                        xytext=(0, -11 if key == "foxo" else 3), textcoords="offset points", ha="right", fontsize=8)
    nax = panels[4]
    nax.axhline(1.0, color="k", ls=":", lw=0.8)
    for name, series in runs.items():
        nax.annotate(f"{series['N'][-1]:.4f}", (series["t"][-1] / WEEK, series["N"][-1]), xytext=(-4, 4),
                     textcoords="offset points", ha="right", fontsize=8, color=protocol_colour(name))
    # IGF1 and AKT spike for about a day after each session: show the first one up close
    if insets:
        for key, ax in (("igf1", panels[0]), ("akt", panels[1])):
            # room above the spikes for the inset
            lo, hi = ax.get_ylim()
            ticks = [t for t in MaxNLocator(4, steps=[1, 2, 5, 10]).tick_values(lo, hi) if lo <= t <= hi]
            ax.set_ylim(lo, lo + (hi - lo) / 0.45)
            ax.set_yticks(ticks)
            inset = ax.inset_axes([0.52, 0.5, 0.46, 0.46])
            for name, series in insets.items():
                if series is not None:
                    inset.plot(series["t"], series[key], color=protocol_colour(name), ls=STYLES.get(name, "-"),
                               lw=1.0)
            inset.set_xlim(0, 24)
            inset.set_xticks([0, 6, 12, 18, 24])
            inset.tick_params(labelsize=7)
            inset.set_xlabel("hours after the first session start", fontsize=7, labelpad=1)
            inset.grid(alpha=0.25)
            # the first session itself (what the axis counts from), one band a protocol, and
            # the delay tau_d after which its stimulus reaches IGF1
            sessions = [(name, p.sessions[0].duration) for name, p in protocols.items() if p.sessions]
            for j, (name, duration) in enumerate(sessions):
                inset.axvspan(0.0, duration, ymin=0.06 * j, ymax=0.06 * (j + 1), color=protocol_colour(name), alpha=0.6,
                              lw=0)
            if sessions:
                tau_d = float(np.mean(params.tau_d))
                inset.axvline(tau_d, color="k", ls=":", lw=0.8)
                inset.annotate("bands: session\ndotted: +τd, the\nstimulus at IGF1", (tau_d, 0.97),
                               xycoords=("data", "axes fraction"), xytext=(-3, 0), textcoords="offset points",
                               ha="right", va="top", fontsize=6)
    sax = panels[5]
    for k, (name, protocol) in enumerate(protocols.items()):
        bars = [(s.start / WEEK, s.duration / WEEK) for s in protocol.sessions]
        sax.broken_barh(bars, (k - 0.35, 0.7), color=protocol_colour(name))
        for s in protocol.sessions:
            sax.plot([s.start / WEEK] * 2, [k - 0.35, k + 0.35], color=protocol_colour(name), lw=1.2)
    sax.set_yticks(range(len(protocols)), [LABELS.get(n, n) for n in protocols], fontsize=8)
    sax.set_ylim(-0.7, len(protocols) - 0.3)
    sax.invert_yaxis()
    sax.set_xlim(0, weeks)
    sax.set_xticks(np.arange(0, np.floor(weeks) + 1))
    sax.set_xlabel("time (weeks)")
    sax.set_title("F   sessions", loc="left", fontweight="bold")
    sax.grid(axis="x", alpha=0.25)
    handles, labels = panels[4].get_legend_handles_labels()
    panels[4].legend(handles, labels, loc="upper left", fontsize=8, frameon=False)
    fig.suptitle("Signaling response to exercise protocols (IGF1–AKT–FOXO–mTOR, RK4)", fontsize=12)
    return fig
