"""hyper reproduce: the paper's claims and the original code's numbers beside hyper's, switch by switch.

    mpirun -n 2 python -m hyper.reproduce --quick        # 29 runs, about 4 min on 2 cores
    mpirun -n 2 python -m hyper.reproduce                # full: 12 muscles at Δtg = 1 h, heterogeneity
    python -m hyper.reproduce --cases signaling          # one family of cases (no mesh)

For each claim of the paper (MODEL.md §8) and each number of the original code (§9) the
report has three columns: the paper's or the original's value, hyper with the original
code's switches (`--settings original`: every switch of §9; reproduce sets each explicitly too),
and hyper's default. An attribution table per headline number starts from the default
and turns on one switch at a time. Cases (families, --cases):

    signaling     ΔN at 9 weeks for mwf, every3days, weekly; IGF1 and AKT peak times (no mesh)
    idealized     the original's 15-day demo (7 one-hour sessions at 0.8 every 48 h from
                  t = 0, end 360 h) and the 9-week mwf run: CSA, V, kM; the switches alone
    contraction   the activation ramp to α = 1: end force and reaction_force_original
    cohort        the anatomical muscles under mwf: CSA by both measures and volume
    heterogeneity ε = 0.01 per-cell signaling on BFLH_VHF_Left, 5 samples (full mode only)

--quick: the cohort on BFLH_VHF_Left, ST_VHF_Left and TA_VHF_Left, the original column
there at one step per period (168 h) with the exact increment (the left-point rule needs
short steps), the idealized original column at QUICK_GROWTH_DT (its effect measured on
the 15-day demo against Δtg = 1 h), no heterogeneity. Full: the 12 muscles, Δtg = 1 h.

Every coupled run is a job of `hyper.runs.farm` (longest first) and is stored under
OUTPUT/runs/KEY.h5; a rerun skips every run whose result exists with the same digest
(hyper.runs.driver's `RunSpec.digest`), so only the report is rebuilt. Writes OUTPUT/REPORT.md,
OUTPUT/report.json and the figures cohort_ratios.png (Fig. 6C–D analog, both CSA
measures side by side), box_section.png (the box measure's inner and rim facets on
BFLH_VHF_Left at the end of its original-settings run) and idealized_mwf.png.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from argparse import Namespace
from pathlib import Path

import numpy as np
from mpi4py import MPI

from hyper.commands import cli
from hyper.core import io
from hyper.core.log import hms, info
from hyper.core.params import InputError
from hyper.model import protocols, signaling
from hyper.model.protocols import Protocol, Session
from hyper.runs import farm, locks, runspec

CASES = ("signaling", "idealized", "contraction", "cohort", "heterogeneity")
QUICK_CASES = CASES[:-1]
QUICK_MUSCLES = ("BFLH_VHF_Left", "ST_VHF_Left", "TA_VHF_Left")
QUICK_GROWTH_DT = 24.0  # h, the idealized original column's step in --quick (the original: 1 h)
ORIGINAL_GROWTH_DT = 1.0  # h, the original code's growth step (MODEL.md §9)
BOX_FIGURE_GEOMETRY = "BFLH_VHF_Left"
HETEROGENEITY_SAMPLES = 5
HETEROGENEITY_EPSILON = 0.01
CONTRACTION_STEPS = 10

# the original code's numbers (MODEL.md §9) and the paper's claims (§8)
ORIGINAL_DN = {"mwf": 0.091496}  # ΔN over 9 weeks with its RK45
ORIGINAL_REACTION_N = 0.9291244  # N, its ∫(σN)·N dA at α = 1 on the idealized shape
PAPER_MWF = {"volume": (8.0, 9.0), "csa": (3.0, 6.0)}  # %, the anatomical cohort under mwf
PAPER_PEAK_H = 12.0  # h after a session, IGF1 and AKT (about)
# measured with an independent restatement of the original's box method (issue #15):
# sessions skipped, P = Fe S, box feedback, Δtg = 168 h; (CSA %, V %)
INDEPENDENT_BOX = {"BFLH_VHF_Left": (3.99, 8.82), "ST_VHF_Left": (4.86, 8.72), "TA_VHF_Left": (5.14, 8.68)}


@dataclasses.dataclass(frozen=True)
class Switch:
    """One difference of the original code: the option that turns it on, the
    GrowthSettings fields and RunSpec fields it sets, and where it applies."""

    option: str
    settings: dict = dataclasses.field(default_factory=dict)
    spec: dict = dataclasses.field(default_factory=dict)
    where: str = "all"  # all, idealized or anatomical


SWITCHES = (
    Switch("--signaling-method rk45-original", {"signaling_method": "rk45-original"}),
    Switch("--growth-increment left-point", {"growth_increment": "left-point"}),
    Switch("--skip-sessions", {"grow_during_sessions": False}),
    Switch("--fe-stress", {"consistent_stress": False}),
    Switch("--growth-fields dg1", {"growth_fields": "dg1"}),
    Switch("--csa-method box", {"csa_method": "box"}, where="anatomical"),
    Switch("--ends tags", spec={"ends": "tags"}, where="idealized"),
    Switch("--fibers original", spec={"fibers": "original"}, where="idealized"),
)


def applies(switch: Switch, geometry: str) -> bool:
    return switch.where == "all" or (switch.where == "idealized") == (geometry == "idealized")


def demo15() -> Protocol:
    """The original code's demo: 7 one-hour sessions at 0.8 every 48 h from t = 0, to 360 h."""
    return Protocol(tuple(Session(48.0 * k, 1.0, 0.8) for k in range(7)), 360.0, "demo15")


# ------------------------------------------------------------------------- the cases


@dataclasses.dataclass(frozen=True)
class Case:
    """One coupled run of the report: a key, the geometry, protocol, growth settings (as
    GrowthSettings fields over the defaults) and RunSpec fields, and what it is for."""

    key: str
    geometry: str
    protocol: str  # a named protocol or "demo15"
    settings: tuple = ()  # (field, value) pairs over GrowthSettings' defaults
    spec: tuple = ()  # (field, value) pairs of RunSpec
    seed: int | None = None  # per-cell signaling (heterogeneity) with this seed
    picture: bool = False  # keep the box measure's picture at the end

    def protocol_object(self) -> Protocol:
        return demo15() if self.protocol == "demo15" else protocols.named(self.protocol)

    def run_spec(self):
        from hyper.fem.coupled import GrowthSettings
        from hyper.model import heterogeneity
        from hyper.runs import presets

        fields = dict(self.settings)
        preset = fields.pop("preset", "default")
        settings = presets.settings(GrowthSettings, preset, fields)
        extra = dict(self.spec)
        if self.seed is not None:
            extra.update(heterogeneity=heterogeneity.Heterogeneity(epsilon=HETEROGENEITY_EPSILON), seed=self.seed)
        return runspec.RunSpec(self.geometry, self.protocol_object(), signaling.SignalingParams(), settings, **extra)


def original_fields(geometry: str, growth_dt: float, exact: bool = False) -> tuple[tuple, tuple]:
    """(settings, spec) pairs of the original code on ``geometry``: the preset and every
    switch that applies there, at ``growth_dt``; ``exact`` keeps the exact increment."""
    settings = {"preset": "original", "growth_dt": growth_dt}
    spec = {}
    for switch in SWITCHES:
        if applies(switch, geometry):
            settings.update(switch.settings)
            spec.update(switch.spec)
    if exact:
        settings["growth_increment"] = "exact"
    return tuple(settings.items()), tuple(spec.items())


def attribution_dt(switch: Switch, quick: bool) -> float:
    """The growth step (h) of a switch's attribution run: 1 h (the original's) in full mode;
    in --quick one step per period, but QUICK_GROWTH_DT for the left-point rule, which
    needs short steps."""
    if not quick:
        return ORIGINAL_GROWTH_DT
    return QUICK_GROWTH_DT if "growth_increment" in switch.settings else 168.0


def idealized_cases(quick: bool) -> list[Case]:
    """The demo (the original's switches at Δtg = 1 h, and at QUICK_GROWTH_DT in --quick),
    the 9-week mwf run by both columns, and the attribution: each switch alone against
    the default at the same step."""
    dt = QUICK_GROWTH_DT if quick else ORIGINAL_GROWTH_DT
    cases = [Case("idealized_demo15_default", "idealized", "demo15")]
    for step in sorted({ORIGINAL_GROWTH_DT, dt}):
        s, sp = original_fields("idealized", step)
        cases.append(Case(f"idealized_demo15_original_dt{step:g}", "idealized", "demo15", s, sp))
    s, sp = original_fields("idealized", dt)
    cases += [
        Case("idealized_mwf_default", "idealized", "mwf"),
        Case(f"idealized_mwf_original_dt{dt:g}", "idealized", "mwf", s, sp),
    ]
    bases = set()
    for switch in SWITCHES:
        if applies(switch, "idealized"):
            step = attribution_dt(switch, quick)
            bases.add(step)
            cases.append(
                Case(
                    f"idealized_mwf_dt{step:g}_{slug(switch.option)}",
                    "idealized",
                    "mwf",
                    (("growth_dt", step), *switch.settings.items()),
                    tuple(switch.spec.items()),
                )
            )
    cases += [
        Case(f"idealized_mwf_default_dt{step:g}", "idealized", "mwf", (("growth_dt", step),))
        for step in sorted(bases)
        if step != 168.0
    ]
    return cases


def base_key(step: float) -> str:
    return "idealized_mwf_default" if step == 168.0 else f"idealized_mwf_default_dt{step:g}"


def cohort_cases(quick: bool) -> list[Case]:
    from hyper.fem import geometry as geo

    muscles = QUICK_MUSCLES if quick else geo.ANATOMICAL
    s, sp = (
        original_fields("anatomical", 168.0, exact=True) if quick else original_fields("anatomical", ORIGINAL_GROWTH_DT)
    )
    cases = []
    for g in muscles:
        cases.append(Case(f"{g}_mwf_default", g, "mwf"))
        cases.append(Case(f"{g}_mwf_original", g, "mwf", s, sp, picture=g == BOX_FIGURE_GEOMETRY))
    return cases


def heterogeneity_cases() -> list[Case]:
    return [
        Case(f"{BOX_FIGURE_GEOMETRY}_mwf_eps{HETEROGENEITY_EPSILON:g}_seed{k}", BOX_FIGURE_GEOMETRY, "mwf", seed=k)
        for k in range(HETEROGENEITY_SAMPLES)
    ]


def slug(option: str) -> str:
    return option.strip("-").replace(" --", "_").replace(" ", "-")


CONTRACTIONS = {
    "default": ("disks", "auto"),
    "ends-tags": ("tags", "auto"),
    "fibers-original": ("disks", "original"),
    "original": ("tags", "original"),
}


# ------------------------------------------------------------------------- the work


def signaling_numbers(protocol: Protocol, method: str) -> dict:
    """ΔN over the protocol, and the IGF1 and AKT peak times after its first session start (h)."""
    series = signaling.run(signaling.SignalingParams(), protocol, 0.05, 0.5, method)
    day = signaling.first_day(signaling.SignalingParams(), protocol, 0.05, method=method)
    return {
        "dN": float(series["N"][-1] - series["N"][0]),
        "N0": float(series["N"][0]),
        "igf1_peak_h": float(day["t"][np.argmax(day["igf1"])]),
        "akt_peak_h": float(day["t"][np.argmax(day["akt"])]),
    }


def contraction_path(output: Path, name: str) -> Path:
    return output / "runs" / f"contraction_{name}.h5"


def contraction_done(path: Path, ends: str, fibers: str) -> bool:
    import h5py

    if not io.is_complete(path):
        return False
    with h5py.File(path, "r") as f:
        a = f.attrs
        return (str(a["ends"]), str(a["fibers"]), int(a["steps"])) == (ends, fibers, CONTRACTION_STEPS)


def plan(args) -> tuple[list[farm.Job], dict[str, Case]]:
    """The farm's jobs and the coupled runs by key."""
    from hyper.analysis import cohort

    cases: list[Case] = []
    if "idealized" in args.cases:
        cases += idealized_cases(args.quick)
    if "cohort" in args.cases:
        cases += cohort_cases(args.quick)
    if "heterogeneity" in args.cases:
        cases += heterogeneity_cases()
    runs = {c.key: c for c in cases}
    jobs = []
    for c in cases:
        spec = c.run_spec()
        cost = cohort.mesh_cells(c.geometry) * cohort.growth_steps(spec.protocol, spec.settings.growth_dt)
        jobs.append(farm.Job(c.key, cost=float(cost), payload=("grow", c.key)))
    if "contraction" in args.cases:
        jobs += [farm.Job(f"contraction_{n}", cost=2e5, payload=("contraction", n)) for n in CONTRACTIONS]
    if "signaling" in args.cases:
        jobs += [
            farm.Job(f"signaling_{m}_{p}", cost=1e4, payload=("signaling", m, p))
            for m in signaling.METHODS
            for p in protocols.PAPER
        ]
    return jobs, runs


def series_path(output: Path, key: str) -> Path:
    return output / "runs" / f"{key}.h5"


def work_on(output: Path, runs: dict[str, Case], stop, progress_every: float):
    """The farm's ``work``: one case on the group's communicator. Once ``stop()`` turns
    true (SIGTERM) a running growth run stops at its next step with a checkpoint, and no
    case starts: their results are ``{"interrupted": True}``."""

    def work(comm, job):
        interrupted = {"interrupted": True} if comm.rank == 0 else None
        if comm.allreduce(bool(stop()), op=MPI.LOR):
            return interrupted
        kind = job.payload[0]
        if kind == "signaling":
            _, method, name = job.payload
            return signaling_numbers(protocols.named(name), method) if comm.rank == 0 else None
        if kind == "contraction":
            from hyper.model import material
            from hyper.runs import contraction

            ends, fibers = CONTRACTIONS[job.payload[1]]
            args = Namespace(
                geometry="idealized",
                ends=ends,
                fibers=fibers,
                steps=CONTRACTION_STEPS,
                output=contraction_path(output, job.payload[1]),
                material=material.MaterialParams(),
                quadrature_degree=4,
                max_halvings=6,
                petsc=[],
            )
            contraction.contract(comm, args)
            return None
        from hyper.runs import driver as run

        case = runs[job.payload[1]]
        spec = case.run_spec()
        out = runspec.Outputs(series_path(output, case.key))
        try:
            done = run.execute(comm, spec, out, stop=stop, progress_every=progress_every)
        except run.Interrupted:
            return interrupted
        if case.picture:
            picture = done.model.section.box.picture()
            if comm.rank == 0:
                np.savez(out.h5.with_name(f"{case.key}_box.npz"), **{k: v for k, v in picture.items() if v is not None})
        if comm.rank == 0:
            out.store(done.series, {**done.meta, "protocol": spec.protocol.name},
                      runspec.result_groups(spec, done.choice))
        return None

    return work


def is_done_on(output: Path, runs: dict[str, Case]):
    def is_done(job):

        if job.payload[0] == "contraction":
            return contraction_done(contraction_path(output, job.payload[1]), *CONTRACTIONS[job.payload[1]])
        if job.payload[0] == "grow":
            case = runs[job.payload[1]]
            return runspec.Outputs(series_path(output, case.key)).is_current(case.run_spec().digest())
        return False

    return is_done


# ------------------------------------------------------------------------- reading back (rank 0)


def final(output: Path, key: str) -> dict | None:
    """Final CSA (feedback's, cut, box) and volume increases (%), kM (1/h), wall (s) of a stored run."""
    import h5py

    path = series_path(output, key)
    if not io.is_complete(path):
        return None
    with h5py.File(path, "r") as f:
        out = {
            "csa": 100 * (f["csa_ratio"][-1] - 1),
            "volume": 100 * (f["volume_ratio"][-1] - 1),
            "kM": float(f["kM"][-1]),
            "wall_s": float(f.attrs["wall_s"]),
            "steps": int(f.attrs["growth_steps"]),
        }
        for m in ("cut", "box"):
            if f"csa_ratio_{m}" in f:
                out[f"csa_{m}"] = 100 * (f[f"csa_ratio_{m}"][-1] - 1)
        return {k: float(v) if k != "steps" else v for k, v in out.items()}


def contraction_final(output: Path, name: str) -> dict | None:
    path = contraction_path(output, name)
    if not io.is_complete(path):
        return None
    s = io.read_series(path)
    return {k: float(s[k][-1]) for k in ("end_force", "spring_force", "reaction_force_original")}


def collect(output: Path, jobs: list[farm.Job], results: list[farm.JobResult], runs: dict[str, Case]) -> dict:
    """Every number of the report, read from the stored runs and the farm's signaling results."""
    by_key = {r.key: r for r in results}
    data: dict = {
        "signaling": {},
        "runs": {},
        "contraction": {},
        "failed": [r.key for r in results if r.status == "failed"],
    }
    for job in jobs:
        if job.payload[0] == "signaling":
            result = by_key[job.key].result
            if result is not None:
                data["signaling"].setdefault(job.payload[1], {})[job.payload[2]] = result
        elif job.payload[0] == "contraction":
            data["contraction"][job.payload[1]] = contraction_final(output, job.payload[1])
        else:
            data["runs"][job.key] = final(output, job.key)
    return data


# ------------------------------------------------------------------------- the report


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
    dt = QUICK_GROWTH_DT if quick else ORIGINAL_GROWTH_DT
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
        f"`--ends tags --fibers original`) at Δtg = {dt:g} h"
        + (" (--quick; the original: 1 h)" if quick else "")
        + "; default: one growth step per period.",
        "",
    ]
    out += table(["quantity", "paper / original", "hyper, original", "hyper, default"], rows)
    one, coarse = (
        runs.get("idealized_demo15_original_dt1"),
        runs.get(f"idealized_demo15_original_dt{QUICK_GROWTH_DT:g}"),
    )
    if quick and one and coarse:
        out += [
            f"Δtg effect under the original's switches (15-day demo): CSA {pct(one['csa'])} at 1 h against "
            f"{pct(coarse['csa'])} at {QUICK_GROWTH_DT:g} h, volume {pct(one['volume'])} against "
            f"{pct(coarse['volume'])} (the left-point increment f(t0)·Δtg is first order in Δtg).",
            "",
        ]
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
        "the original's switches (`--settings original`, box feedback) at one step "
        "per period (168 h) with the exact increment (--quick: the left-point rule needs short steps)"
        if quick
        else "`--settings original` (box feedback, Δtg = 1 h)"
    )
    out = [
        "## The anatomical cohort under mwf",
        "",
        f"hyper original: {settings}; default: the exact cut feeds back, "
        "one step per period. Both runs record both CSA measures.",
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


# ------------------------------------------------------------------------- figures


def cohort_figure(data: dict, path: Path) -> Path | None:
    """Fig. 6C–D analog: per muscle, CSA by the cut and by the box and volume, default and original side by side."""
    from hyper.runs import plot

    orig, dflt = cohort_rows(data, "original"), cohort_rows(data, "default")
    names = sorted(set(orig) | set(dflt))
    if not names:
        return None
    plt = plot.pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(max(8, 1.1 * len(names) + 4), 4.4), layout="constrained")
    bars = (
        ("default, cut", dflt, "csa_cut", "tab:blue"),
        ("default, box", dflt, "csa_box", "lightsteelblue"),
        ("original, cut", orig, "csa_cut", "tab:red"),
        ("original, box", orig, "csa_box", "salmon"),
    )
    x = np.arange(len(names))
    for j, (label, col, key, colour) in enumerate(bars):
        axes[0].bar(
            x + (j - 1.5) * 0.2, [get(col.get(g), key) or np.nan for g in names], 0.18, label=label, color=colour
        )
    for j, (label, col, colour) in enumerate((("default", dflt, "tab:blue"), ("original", orig, "tab:red"))):
        axes[1].bar(
            x + (j - 0.5) * 0.3, [get(col.get(g), "volume") or np.nan for g in names], 0.28, label=label, color=colour
        )
    for ax, quantity, title in ((axes[0], "csa", "mid-belly CSA, both measures"), (axes[1], "volume", "volume")):
        lo, hi = PAPER_MWF[quantity]
        ax.axhspan(lo, hi, color="0.85", zorder=0, label="paper, mwf")
        ax.set_xticks(x, names, rotation=45, ha="right", fontsize=8)
        ax.set_ylabel(f"{title} change (%)")
        ax.grid(axis="y", alpha=0.3)
        ax.set_ylim(0.0, 1.4 * ax.get_ylim()[1])  # room above the bars for the legend
        ax.legend(fontsize=7, ncol=3, loc="upper center")
    fig.suptitle("cohort under mwf, 9 weeks: hyper's default and the original code's switches")
    plot.save(fig, path, dpi=130)
    plt.close(fig)
    return path


def box_figure(output: Path, path: Path) -> Path | None:
    from hyper.runs import plot

    saved = output / "runs" / f"{BOX_FIGURE_GEOMETRY}_mwf_original_box.npz"
    if not saved.is_file():
        return None
    with np.load(saved) as f:
        picture = {k: f[k] for k in f.files}
    picture.setdefault("outline", np.empty((0, 2, 2)))
    return plot.box_section(
        picture,
        path,
        f"{BOX_FIGURE_GEOMETRY}, mwf, 9 weeks, the original's switches: the box measure's inner and rim facets",
    )


def idealized_figure(output: Path, path: Path, quick: bool) -> Path | None:
    from hyper.runs import measured, plot

    dt = QUICK_GROWTH_DT if quick else ORIGINAL_GROWTH_DT
    files = {
        "default": series_path(output, "idealized_mwf_default"),
        "original": series_path(output, f"idealized_mwf_original_dt{dt:g}"),
    }
    results = {name: io.read_series(p) for name, p in files.items() if io.is_complete(p)}
    data = measured.of_protocol(protocols.named("mwf"))
    return plot.growth_series(results, path, [data] if data else []) if results else None


# ------------------------------------------------------------------------- CLI


def parser() -> cli.Parser:
    p = cli.Parser("reproduce", __doc__)
    p.add_argument("--output", type=cli.output(folder=True), default="results/reproduce", help="output folder")
    p.add_argument(
        "--quick", action="store_true", help="3 muscles, coarser steps, no heterogeneity (about 4 min on 2 ranks)"
    )
    p.add_argument(
        "--cases",
        nargs="+",
        choices=CASES,
        metavar="CASE",
        help=f"families of cases ({', '.join(CASES)}); all of them (--quick: all but heterogeneity) by default",
    )
    p.add_argument(
        "--ranks-per-job", type=cli.integer(1), default=1, help="MPI ranks per run; must divide the number of ranks"
    )
    cli.progress_option(p)
    return p


def reproduce(comm, args) -> int:
    start = time.perf_counter()
    if args.cases is None:
        args.cases = list(QUICK_CASES if args.quick else CASES)
    if comm.size % args.ranks_per_job:
        raise InputError(f"--ranks-per-job must divide the number of MPI ranks ({comm.size}), got {args.ranks_per_job}")
    if "cohort" in args.cases or "heterogeneity" in args.cases:
        from hyper.fem import geometry
        from hyper.runs import driver as run

        for g in QUICK_MUSCLES if args.quick else geometry.ANATOMICAL:
            runspec.check_geometry(comm, g, "--cases cohort")
    jobs, runs = plan(args)
    output = args.output
    with locks.hold(comm, [output]):
        if comm.rank == 0:
            (output / "runs").mkdir(parents=True, exist_ok=True)
        info(
            comm,
            f"reproduce: {len(jobs)} jobs ({', '.join(args.cases)}), {'quick' if args.quick else 'full'} "
            f"mode, on {comm.size} rank(s), output {output}",
        )
        from hyper.runs import driver as run

        with run.StopOnTerm() as stop:
            results = farm.run(
                comm,
                jobs,
                work_on(output, runs, stop, args.progress_every),
                ranks_per_job=args.ranks_per_job,
                is_done=is_done_on(output, runs),
                label="reproduce",
                progress_every=args.progress_every,
            )
        stopped = comm.bcast(
            any(r.status == "done" and isinstance(r.result, dict) and r.result.get("interrupted") for r in results)
            if comm.rank == 0
            else None,
            root=0,
        )
        if stopped:
            info(comm, f"reproduce: stopped by SIGTERM; the finished runs are kept, the running ones have "
                       f"checkpoints: rerun the same command to go on (exit status {cli.EXIT_TERMINATED})")
            return cli.EXIT_TERMINATED
        if comm.rank == 0:
            data = collect(output, jobs, results, runs)
            command = (
                "hyper reproduce"
                + (" --quick" if args.quick else "")
                + (
                    ""
                    if args.cases == list(QUICK_CASES if args.quick else CASES)
                    else " --cases " + " ".join(args.cases)
                )
            )
            data.update(
                mode="quick" if args.quick else "full",
                cases=list(args.cases),
                command=command,
                wall_s=time.perf_counter() - start,
            )
            figures = [
                cohort_figure(data, output / "cohort_ratios.png"),
                box_figure(output, output / "box_section.png"),
                idealized_figure(output, output / "idealized_mwf.png", args.quick),
            ]
            text = report(data, args.quick, time.perf_counter() - start, command)
            shown = [f"![{p.stem}]({p.name})" for p in figures if p is not None]
            text += ("\n## Figures\n\n" + "\n\n".join(shown) + "\n") if shown else ""
            with io.atomic_path(output / "REPORT.md") as tmp:
                tmp.write_text(text)
            with io.atomic_path(output / "report.json") as tmp:
                tmp.write_text(json.dumps(data, indent=1, default=float))
            info(comm, text)
            info(comm, f"{farm.summary_line(results)}; wrote {output / 'REPORT.md'}, {output / 'report.json'}")
        failed = comm.bcast(any(r.status == "failed" for r in results), root=0)
    return cli.EXIT_SOME_FAILED if failed else cli.EXIT_OK


main = cli.entry(parser, reproduce)

if __name__ == "__main__":
    sys.exit(main())
