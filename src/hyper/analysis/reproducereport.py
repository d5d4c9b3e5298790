"""The text of ``hyper reproduce``'s REPORT.md: per family of cases a table of the
paper's or the original code's number, hyper with the original code's switches and
hyper's default, and the attribution of each headline number to the switches, from the
numbers `hyper.analysis.reproduce.collect` reads back."""

from __future__ import annotations

import math

import numpy as np

from hyper.analysis.reproduce import (
    BOX_FIGURE_GEOMETRY,
    CONTRACTIONS,
    INDEPENDENT_BOX,
    ORIGINAL_DN,
    ORIGINAL_GROWTH_DT,
    ORIGINAL_REACTION_N,
    PAPER_MWF,
    PAPER_PEAK_H,
    SWITCHES,
    applies,
    attribution_dt,
    base_key,
    slug,
)
from hyper.core.log import hms
from hyper.model import protocols


def pct(x) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:+.2f} %"


def num(x, fmt: str) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


def table(head: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(head) + " |", "|" + "---|" * len(head), *("| " + " | ".join(r) + " |" for r in rows), ""]


def get(d: dict | None, key: str):
    return None if d is None else d.get(key)


def signaling_section(data: dict) -> list[str]:
    sig = data["signaling"]
    if not sig:
        return []
    orig, dflt = sig.get("rk45-original", {}), sig.get("rk4", {})
    rows = []
    for p in protocols.PAPER:
        paper = num(ORIGINAL_DN.get(p), ".6f") + (" (original)" if p in ORIGINAL_DN else "")
        if p == "every3days":
            paper = "agrees with converged to 3e-5 (original)"
        rows.append(
            [f"ΔN at 9 weeks, {p}", paper, num(get(orig.get(p), "dN"), ".6f"), num(get(dflt.get(p), "dN"), ".6f")]
        )
    for state, label in (("igf1", "IGF1"), ("akt", "AKT")):
        rows.append(
            [
                f"{label} peak after the first mwf session (h)",
                f"about {PAPER_PEAK_H:g} (paper)",
                num(get(orig.get("mwf"), f"{state}_peak_h"), ".2f"),
                num(get(dflt.get("mwf"), f"{state}_peak_h"), ".2f"),
            ]
        )
    for col in (orig, dflt):
        col["_order"] = (
            all(p in col for p in protocols.PAPER) and col["mwf"]["dN"] > col["every3days"]["dN"] > col["weekly"]["dN"]
        )
    rows.append(["ΔN: mwf > every3days > weekly", "yes (paper)", yesno(orig["_order"]), yesno(dflt["_order"])])
    rows.append(
        ["N0", "1.000768 (original)", num(get(orig.get("mwf"), "N0"), ".6f"), num(get(dflt.get("mwf"), "N0"), ".6f")]
    )
    out = [
        "## Signaling (no mesh)",
        "",
        "hyper original: `--signaling-method rk45-original` (SciPy RK45, rtol 1e-3, "
        "atol 1e-6, max_step 0.05 h, restarted at session starts and ends, N0 = 1.000768); default: RK4 at "
        "0.05 h, converged to 4e-7.",
        "",
    ]
    out += table(["quantity", "paper / original", "hyper, original", "hyper, default"], rows)
    d0, d1 = get(dflt.get("mwf"), "dN"), get(orig.get("mwf"), "dN")
    if d0 is not None and d1 is not None:
        out += [
            f"Attribution (ΔN mwf): default {d0:.6f}; `--signaling-method rk45-original` alone {d1:.6f} "
            f"({100 * (d1 / d0 - 1):+.3f} %). The N0 offset does not change ΔN (f does not depend on N "
            "inside [Nmin, Nmax]).",
            "",
        ]
    return out


def yesno(flag) -> str:
    return "yes" if flag else "**no**"


def idealized_section(data: dict, quick: bool) -> list[str]:
    runs = data["runs"]
    if "idealized_mwf_default" not in runs:
        return []
    dt = ORIGINAL_GROWTH_DT  # the original column's step, in --quick too (hyper.analysis.reproduce)
    orig_demo = runs.get(f"idealized_demo15_original_dt{dt:g}")
    orig_mwf = runs.get(f"idealized_mwf_original_dt{dt:g}")
    rows = []
    for label, o, d in (
        ("15-day demo (360 h)", orig_demo, runs.get("idealized_demo15_default")),
        ("9 weeks of mwf", orig_mwf, runs.get("idealized_mwf_default")),
    ):
        paper = "not recorded here" if "demo" in label else "CSA, V grow; kM < kM0 = 0.01 1/h (paper)"
        rows.append([f"{label}: CSA", paper, pct(get(o, "csa")), pct(get(d, "csa"))])
        rows.append([f"{label}: volume", paper, pct(get(o, "volume")), pct(get(d, "volume"))])
        rows.append([f"{label}: kM (1/h)", paper, num(get(o, "kM"), ".5f"), num(get(d, "kM"), ".5f")])
    out = [
        "## The idealized shape",
        "",
        f"hyper original: every switch of MODEL.md §9 (`--settings original`, on this shape with "
        f"`--ends tags --fibers original`) at Δtg = {dt:g} h, the original's step"
        + (" (--quick too)" if quick else "")
        + "; default: one growth step per period (168 h).",
        "",
    ]
    out += table(["quantity", "paper / original", f"hyper, original (Δtg = {dt:g} h)",
                  "hyper, default (Δtg = 168 h)"], rows)
    rows = [
        [
            "default (one step per period)",
            pct(get(runs.get("idealized_mwf_default"), "csa")),
            pct(get(runs.get("idealized_mwf_default"), "volume")),
            "–",
        ]
    ]
    if dt != 168.0:
        base = runs.get(base_key(dt))
        rows.append([f"default at Δtg = {dt:g} h", pct(get(base, "csa")), pct(get(base, "volume")), "–"])
    total = 0.0
    for switch in SWITCHES:
        if applies(switch, "idealized"):
            step = attribution_dt(switch, quick)
            r, base = runs.get(f"idealized_mwf_dt{step:g}_{slug(switch.option)}"), runs.get(base_key(step))
            effect = None if r is None or base is None else r["csa"] - base["csa"]
            total += effect or 0.0
            rows.append(
                [
                    f"`{switch.option}` alone (Δtg = {step:g} h)",
                    pct(get(r, "csa")),
                    pct(get(r, "volume")),
                    "–" if effect is None else f"{effect:+.3f} points",
                ]
            )
    base = runs.get(base_key(dt))
    if orig_mwf and base:
        rows.append(
            [
                f"all switches (hyper, original; Δtg = {dt:g} h)",
                pct(orig_mwf["csa"]),
                pct(orig_mwf["volume"]),
                f"{orig_mwf['csa'] - base['csa']:+.3f} points (the single effects sum to {total:+.3f})",
            ]
        )
    out += [
        "Attribution, idealized mwf at 9 weeks (headline: the CSA increase): each switch alone, its effect "
        "against the default at the same growth step:",
        "",
    ]
    out += table(["run", "CSA", "volume", "effect on CSA"], rows)
    return out


def contraction_section(data: dict) -> list[str]:
    c = data["contraction"]
    if not c:
        return []
    o, d = c.get("original"), c.get("default")
    rows = [
        [
            "end force d·∫P N dA (N, headline)",
            "– (not computed by the original)",
            num(get(o, "end_force"), ".4f"),
            num(get(d, "end_force"), ".4f"),
        ],
        ["spring force (N)", "–", num(get(o, "spring_force"), ".4f"), num(get(d, "spring_force"), ".4f")],
        [
            "reaction_force_original ∫(σN)·N dA (N)",
            f"{ORIGINAL_REACTION_N:.7f} (original)",
            num(get(o, "reaction_force_original"), ".7f"),
            num(get(d, "reaction_force_original"), ".7f"),
        ],
    ]
    out = [
        "## Contraction at α = 1 (idealized shape)",
        "",
        "hyper original: `--ends tags --fibers original` (the XDMF's "
        "end tags with their lateral band; P2 fibres not normalised, UFL's estimated surface degree); default: "
        "the flat end disks, P1 unit fibres.",
        "",
    ]
    out += table(["quantity", "paper / original", "hyper, original", "hyper, default"], rows)
    rows = [
        [name, num(get(c.get(name), "end_force"), ".4f"), num(get(c.get(name), "reaction_force_original"), ".7f")]
        for name in CONTRACTIONS
    ]
    out += ["Attribution (each switch alone from the default):", ""]
    out += table(["ends, fibres", "end force (N)", "reaction_force_original (N)"], rows)
    return out


def cohort_rows(data: dict, column: str) -> dict[str, dict]:
    return {
        k[: -len(f"_mwf_{column}")]: v
        for k, v in data["runs"].items()
        if k.endswith(f"_mwf_{column}") and v is not None and "_eps" not in k and not k.startswith("idealized")
    }


def stats(values) -> tuple:
    values = [v for v in values if v is not None]
    return (float(np.mean(values)), float(np.min(values)), float(np.max(values)), len(values)) if values else None


def mmm(s) -> str:
    return "–" if s is None else f"{s[0]:+.2f} % ({s[1]:+.2f}, {s[2]:+.2f}; n = {s[3]})"


def cohort_section(data: dict, quick: bool) -> list[str]:
    orig, dflt = cohort_rows(data, "original"), cohort_rows(data, "default")
    if not dflt and not orig:
        return []
    lo, hi = PAPER_MWF["volume"]
    clo, chi = PAPER_MWF["csa"]
    rows = [
        [
            "volume increase, mean (min, max)",
            f"+{lo:g}–{hi:g} % (paper)",
            mmm(stats(r["volume"] for r in orig.values())),
            mmm(stats(r["volume"] for r in dflt.values())),
        ],
        [
            "CSA increase, the feedback's measure",
            f"+{clo:g}–{chi:g} % (paper)",
            mmm(stats(r["csa"] for r in orig.values())) + " (box)",
            mmm(stats(r["csa"] for r in dflt.values())) + " (cut)",
        ],
        [
            "CSA increase, exact cut",
            "–",
            mmm(stats(r.get("csa_cut") for r in orig.values())),
            mmm(stats(r.get("csa_cut") for r in dflt.values())),
        ],
        [
            "CSA increase, box (the original's measure)",
            f"+{clo:g}–{chi:g} % (paper)",
            mmm(stats(r.get("csa_box") for r in orig.values())),
            mmm(stats(r.get("csa_box") for r in dflt.values())),
        ],
    ]
    vol_gt = [sum(r["volume"] > r["csa"] for r in col.values()) for col in (orig, dflt)]
    rows.append(
        [
            "ΔV > ΔCSA (the feedback's CSA)",
            "yes, all (paper)",
            f"{vol_gt[0]} of {len(orig)}",
            f"{vol_gt[1]} of {len(dflt)}",
        ]
    )
    settings = (
        "the original's switches (`--settings original`, box feedback, the Stokes fibres) at one step "
        "per period (168 h) with the exact increment (--quick: the left-point rule needs short steps)"
        if quick
        else "`--settings original` (box feedback, the Stokes fibres, Δtg = 1 h)"
    )
    out = [
        "## The anatomical cohort under mwf",
        "",
        f"hyper original: {settings}; default: the exact cut feeds back, the Laplace fibres "
        "(hyper.fem.laplace, converged on every muscle: docs/convergence.md), one step per period. "
        "Both runs record both CSA measures.",
        "",
    ]
    out += table(["quantity", "paper / original", "hyper, original", "hyper, default"], rows)
    per = []
    for g in sorted(set(orig) | set(dflt)):
        o, d = orig.get(g), dflt.get(g)
        ref = INDEPENDENT_BOX.get(g)
        per.append(
            [
                g,
                pct(get(d, "csa_cut")),
                pct(get(d, "csa_box")),
                pct(get(d, "volume")),
                pct(get(o, "csa_cut")),
                pct(get(o, "csa_box")),
                pct(get(o, "volume")),
                "–" if ref is None else f"+{ref[0]:.2f} % / +{ref[1]:.2f} %",
            ]
        )
    out += ["Per muscle (default: cut feedback; original: box feedback):", ""]
    out += table(
        [
            "geometry",
            "default CSA cut",
            "default CSA box",
            "default V",
            "original CSA cut",
            "original CSA box",
            "original V",
            "independent box restatement CSA / V (issue #15)",
        ],
        per,
    )
    d = dflt.get(BOX_FIGURE_GEOMETRY)
    o = orig.get(BOX_FIGURE_GEOMETRY)
    if d is not None:
        out += [
            f"Attribution on {BOX_FIGURE_GEOMETRY} (headline: the CSA the paper reports): default cut "
            f"{pct(d.get('csa_cut'))}; the box measure of the same states, no feedback {pct(d.get('csa_box'))}"
            + (
                ""
                if o is None
                else f"; the original's switches with box feedback {pct(o.get('csa_box'))} "
                f"(its exact cut {pct(o.get('csa_cut'))}, volume {pct(o.get('volume'))})"
            )
            + ".",
            "",
        ]
    return out


def heterogeneity_section(data: dict) -> list[str]:
    samples = [v for k, v in data["runs"].items() if "_eps" in k and v is not None]
    uniform = data["runs"].get(f"{BOX_FIGURE_GEOMETRY}_mwf_default")
    if not samples:
        return []
    csa, vol = stats(s["csa"] for s in samples), stats(s["volume"] for s in samples)
    rows = [
        [
            "CSA, mean of the samples",
            "a little below uniform (paper)",
            "not run",
            f"{mmm(csa)}; uniform {pct(get(uniform, 'csa'))}",
        ],
        [
            "volume, mean of the samples",
            "a little below uniform (paper)",
            "not run",
            f"{mmm(vol)}; uniform {pct(get(uniform, 'volume'))}",
        ],
    ]
    return ["## Heterogeneity (ε = 0.01, BFLH_VHF_Left, mwf)", ""] + table(
        ["quantity", "paper", "hyper, original", "hyper, default"], rows
    )


BOX_NOTE = (
    "The box measure's number depends on DOLFINx's `interpolate_nonmatching` extrapolating the muscle's "
    "displacement into box nodes that lie outside the muscle but inside the bounding boxes of its cells "
    "(MODEL.md §9 says u = 0 outside); setting every outside node to 0 instead makes the box read +0.02 % "
    "on BFLH_VHF_Left (its staircase's edge then lies where u = 0, so the in-plane Jacobian integrates to "
    "the reference area whatever the growth). The numbers here are those of the original code's call, which "
    "extrapolates; `hyper box RESULT.h5` re-measures a stored run's snapshots by both rules."
)


def report(data: dict, quick: bool, elapsed: float, command: str) -> str:
    lines = [
        "# hyper against the paper and its original code",
        "",
        f"`{command}` ({'quick' if quick else 'full'} mode): this invocation took {hms(elapsed)} "
        "(runs stored before are reused). "
        "Columns: the paper's claim or the original code's number; hyper with the original code's switches "
        "(MODEL.md §9); hyper's default (converged, physically consistent choices).",
        "",
    ]
    for part in (
        signaling_section(data),
        idealized_section(data, quick),
        contraction_section(data),
        cohort_section(data, quick),
        heterogeneity_section(data),
    ):
        lines += part
    if cohort_rows(data, "default"):
        lines += ["## Notes", "", BOX_NOTE, ""]
    if data["failed"]:
        lines += [f"Failed: {', '.join(data['failed'])} (see the log; rerun the same command to retry them).", ""]
    return "\n".join(lines)
