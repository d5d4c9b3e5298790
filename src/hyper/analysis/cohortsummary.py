"""A cohort's summary, written by rank 0 from the complete .h5 files (so a rerun that had
nothing left to do writes the same summary): summary.csv, failures.txt, the figures of
`hyper.analysis.cohortplot` and table.md, the results against the paper (MODEL.md §8);
where the runs recorded regional sections (--sections), sections.csv, the final CSA change
at each section of each run, and its figure sections.png."""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path

from hyper.analysis.cohort import PAPER_PROTOCOLS, Run, member, series_path
from hyper.analysis.cohortplot import final_fields, ratio_figure, section_figure, shape_figure
from hyper.analysis.cohortstats import PAPER_MWF_INCREASE, increases, mwf_statistics, ordered, ratio_column
from hyper.core import io
from hyper.core.log import hms, info
from hyper.fem.coupled import CSA_METHODS, GrowthSettings
from hyper.runs import farm, runspec

COLUMNS = ("geometry", "muscle", "subject", "side", "protocol", "csa0_cm2", "volume0_cm3",
           "final_csa_ratio", "final_csa_ratio_cut", "final_csa_ratio_box", "final_csa_ratio_solid",
           "final_volume_ratio", "wall_s", "data_rmse_pp", "data_last_difference_pp", "status")
# the summary's numbers: CSA by the feedback's method and by each method, and against
# measured CSA (blank without them)
NUMBERS = ("csa0_cm2", "volume0_cm3", "final_csa_ratio", "final_csa_ratio_cut", "final_csa_ratio_box",
           "final_csa_ratio_solid", "final_volume_ratio", "wall_s", "data_rmse_pp", "data_last_difference_pp")


def summary_row(path: Path) -> dict:
    """The summary row of a complete series file."""
    import h5py

    with h5py.File(path, "r") as f:
        a = f.attrs
        return {
            "geometry": str(a["geometry"]), "muscle": str(a["muscle"]), "subject": str(a["subject"]),
            "side": str(a["side"]), "protocol": str(a["protocol"]),
            "csa0_cm2": float(a["csa0_m2"]) * 1e4, "volume0_cm3": float(a["volume0_m3"]) * 1e6,
            "final_csa_ratio": float(f["csa_ratio"][-1]),
            **{f"final_csa_ratio_{m}": float(f[f"csa_ratio_{m}"][-1]) if f"csa_ratio_{m}" in f else float("nan")
               for m in CSA_METHODS},
            "final_volume_ratio": float(f["volume_ratio"][-1]), "wall_s": float(a["wall_s"]),
            # against measured CSA (hyper.runs.measured), where the run was compared with some
            "data_rmse_pp": float(f["data"].attrs["rmse_pp"]) if "data" in f else float("nan"),
            "data_last_difference_pp": float(f["data"].attrs["last_difference_pp"]) if "data" in f else float("nan"),
            "status": "done",
        }


SECTION_COLUMNS = ("geometry", "protocol", "section", "csa0_cm2", "final_csa_ratio", "csa_change_percent")


def section_rows(path: Path) -> list[dict]:
    """One row per regional section of a complete series file (none where it has none)."""
    import h5py

    with h5py.File(path, "r") as f:
        if "csa_ratio_sections" not in f:
            return []
        a = f.attrs
        final = f["csa_ratio_sections"][-1]
        return [{"geometry": str(a["geometry"]), "protocol": str(a["protocol"]), "section": float(x),
                 "csa0_cm2": float(area) * 1e4, "final_csa_ratio": float(r),
                 "csa_change_percent": 100.0 * (float(r) - 1.0)}
                for x, area, r in zip(a["section_fractions"], a["csa0_sections_m2"], final, strict=True)]


def summarize(output: Path, runs: list[Run], failed: dict[str, str], interrupted=()) -> list[dict]:
    """One row per run, in the order of ``runs``: read back from its complete file, or
    marked failed (``failed``: run key -> error), interrupted or missing, with blank numbers."""
    rows = []
    for entry in runs:
        path = series_path(output, entry)
        if entry.key not in failed and io.is_complete(path):
            rows.append(summary_row(path))
            continue
        row = dict.fromkeys(COLUMNS, float("nan"))
        row.update(geometry=entry.geometry, protocol=entry.protocol.name, **member(entry.geometry),
                   status="failed" if entry.key in failed else "interrupted" if entry.key in interrupted else "missing")
        rows.append(row)
    return rows


def write_csv(rows: list[dict], path: Path, columns=COLUMNS) -> None:
    with io.atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: ("" if isinstance(v, float) and math.isnan(v) else
                                 repr(v) if isinstance(v, float) else v) for k, v in row.items()})


def read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    for row in rows:
        for key in NUMBERS:
            row[key] = float(row[key]) if row.get(key) else float("nan")
    return rows


def _yes(flag: bool | None) -> str:
    return "–" if flag is None else ("yes" if flag else "**no**")


def markdown(rows: list[dict], settings: GrowthSettings) -> str:
    """The cohort's results against the paper (MODEL.md §8), as markdown."""
    geometries = list(dict.fromkeys(r["geometry"] for r in rows))
    names = list(dict.fromkeys(r["protocol"] for r in rows))
    lines = [f"Final increase after {'/'.join(names)} (growth step {settings.growth_dt:g} h), per geometry:", ""]
    head = ["geometry", *(f"CSA {p}" for p in names), *(f"volume {p}" for p in names)]
    if all(p in names for p in PAPER_PROTOCOLS):
        head.append("mwf > every3days > weekly")
    if "mwf" in names:
        head.append("ΔV > ΔCSA (mwf)")
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    order_ok = vol_ok = 0
    for g in geometries:
        csa, vol = increases(rows, g, "csa"), increases(rows, g, "volume")
        cells = [g, *(f"{csa[p]:+.2f} %" if p in csa else "failed" for p in names),
                 *(f"{vol[p]:+.2f} %" if p in vol else "failed" for p in names)]
        if all(p in names for p in PAPER_PROTOCOLS):
            flag = ordered(csa) and ordered(vol) if ordered(csa) is not None and ordered(vol) is not None else None
            order_ok += bool(flag)
            cells.append(_yes(flag))
        if "mwf" in names:
            flag = vol["mwf"] > csa["mwf"] if "mwf" in csa and "mwf" in vol else None
            vol_ok += bool(flag)
            cells.append(_yes(flag))
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    if all(p in names for p in PAPER_PROTOCOLS):
        lines.append(f"- mwf > every3days > weekly in both CSA and volume: {order_ok} of {len(geometries)} geometries.")
    if "mwf" in names:
        lines.append(f"- relative volume increase > relative CSA increase under mwf: {vol_ok} of {len(geometries)}.")
        lines += ["", "mwf across the geometries against the paper:", "",
                  "| quantity | mean | min | max | paper |", "|---|---|---|---|---|"]
        done = [r for r in rows if r["status"] == "done"]
        measured = [(f"csa_{m}", f"mid-belly CSA increase, {m}") for m in CSA_METHODS
                    if done and all(math.isfinite(r.get(ratio_column(f"csa_{m}"), math.nan)) for r in done)]
        for quantity, label in (("volume", "volume increase"), ("csa", "mid-belly CSA increase"), *measured):
            s = mwf_statistics(rows, quantity)
            lo, hi = PAPER_MWF_INCREASE[quantity.split("_")[0]]
            if s is not None:
                lines.append(f"| {label} (n = {s['n']}) | {s['mean']:+.2f} % | {s['min']:+.2f} % | "
                             f"{s['max']:+.2f} % | +{lo:g}–{hi:g} % |")
    failed = [f"{r['geometry']}/{r['protocol']}" for r in rows if r["status"] != "done"]
    if failed:
        lines += ["", f"Not done: {', '.join(failed)}."]
    return "\n".join(lines) + "\n"



@dataclasses.dataclass(frozen=True)
class Outcome:
    """How a cohort ended, for its exit status: the runs that failed, and those SIGTERM stopped."""

    failed: tuple[str, ...] = ()
    interrupted: tuple[str, ...] = ()


def finish(output: Path, runs: list[Run], results, settings: GrowthSettings, elapsed: float, *,
           plot_geometry: str, figures: bool = True) -> Outcome:
    """Rank 0: summary, failures, figures (unless ``figures`` is false), table. Returns
    the runs that failed and those interrupted (the command's exit status)."""
    failed = {r.key: r.error for r in results if r.status == "failed"}
    interrupted = {r.key for r in results if r.status == "done" and r.result and r.result.get("interrupted")}
    rows = summarize(output, runs, failed, interrupted)
    write_csv(rows, output / "summary.csv")
    failures = output / "failures.txt"
    if failed:
        with io.atomic_path(failures) as tmp:
            tmp.write_text("".join(f"== {key} ==\n{error.rstrip()}\n\n" for key, error in failed.items()))
    else:
        failures.unlink(missing_ok=True)
    done = [r for r in rows if r["status"] == "done"]
    written = [output / "summary.csv"]
    if done and figures:
        ratio_figure(done, output / "ratios.png")
        written.append(output / "ratios.png")
    # the regional CSA of the runs that recorded it (read back, as the summary is)
    sections = [s for r in runs if r.key not in failed and io.is_complete(series_path(output, r))
                for s in section_rows(series_path(output, r))]
    if sections:
        write_csv(sections, output / "sections.csv", SECTION_COLUMNS)
        written.append(output / "sections.csv")
        if figures:
            section_figure(sections, output / "sections.png")
            written.append(output / "sections.png")
    pictured = {r.protocol.name: runspec.Outputs(series_path(output, r)).fields for r in runs
                if r.geometry == plot_geometry}
    pictured = {name: p for name, p in pictured.items() if p.is_file()}
    if pictured and figures:
        shape_figure({name: final_fields(p) for name, p in pictured.items()}, output / "shape.png", plot_geometry)
        written.append(output / "shape.png")
    elif figures:
        info(None, f"shape.png not written: {plot_geometry}, its geometry, has no finished run")
    table = markdown(rows, settings)
    with io.atomic_path(output / "table.md") as tmp:
        tmp.write_text(table)
    written.append(output / "table.md")

    info(None, f"\n{'geometry':<16} {'protocol':<11} {'CSA0 cm²':>8} {'V0 cm³':>8} {'CSA/CSA0':>9} "
               f"{'V/V0':>8} {'wall':>8} status")
    for r in rows:
        info(None, f"{r['geometry']:<16} {r['protocol']:<11} {r['csa0_cm2']:>8.3f} {r['volume0_cm3']:>8.2f} "
                   f"{r['final_csa_ratio']:>9.5f} {r['final_volume_ratio']:>8.5f} "
                   f"{hms(r['wall_s']) if r['status'] == 'done' else '-':>8} {r['status']}")
    for r in rows:
        if r["status"] == "done" and not math.isnan(r["data_rmse_pp"]):
            info(None, f"{r['geometry']}/{r['protocol']} against measured CSA: RMSE {r['data_rmse_pp']:.2f} "
                       f"percentage points, model − data at the last measured time "
                       f"{r['data_last_difference_pp']:+.2f} points")
    info(None, "\n" + table)
    info(None, farm.summary_line(results) + f"; cohort wall time {hms(elapsed)} ({elapsed:.0f} s)")
    if failed:
        written.append(failures)
        info(None, f"errors in {failures}; rerun the same command to retry only the failed runs")
    if interrupted:
        info(None, f"stopped by SIGTERM: {len(interrupted)} run(s) not finished ({', '.join(sorted(interrupted))}); "
                   "rerun the same command to continue them from their checkpoints")
    info(None, "wrote " + ", ".join(str(p) for p in written))
    return Outcome(tuple(failed), tuple(sorted(interrupted)))

