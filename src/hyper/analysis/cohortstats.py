"""Statistics of a cohort's summary rows (`hyper.analysis.cohortsummary`): the final
increases in percent per (group, protocol), their mean and standard error, the order of
the protocols and the mwf range against the paper (MODEL.md §8). Plain numbers."""

from __future__ import annotations

import numpy as np

from hyper.analysis.cohort import PAPER_PROTOCOLS

# MODEL.md §8, anatomical cohort under mwf: increases in percent (low, high)
PAPER_MWF_INCREASE = {"volume": (8.0, 9.0), "csa": (3.0, 6.0)}


def standard_error(values) -> float:
    """Standard error of the mean, s/√n with the sample standard deviation; NaN for n < 2."""
    values = np.asarray(values, dtype=float)
    if values.size < 2:
        return float("nan")
    return float(values.std(ddof=1) / np.sqrt(values.size))


def group(row: dict) -> str:
    """The group a run belongs to in the statistics: its muscle, or its geometry if it has none."""
    return row["muscle"] or row["geometry"]


def ratio_column(quantity: str) -> str:
    """The summary column of ``quantity``: 'csa', 'volume', or 'csa_cut', 'csa_box' (one CSA measure)."""
    name, _, method = quantity.partition("_")
    return f"final_{name}_ratio" + (f"_{method}" if method else "")


def percent(row: dict, quantity: str) -> float:
    """The final relative increase of ``quantity`` (`ratio_column`) in percent."""
    return 100.0 * (row[ratio_column(quantity)] - 1.0)


def group_statistics(rows: list[dict], quantity: str) -> dict[tuple[str, str], dict]:
    """(group, protocol) -> n, mean and standard error of the increase (%) over the done runs."""
    out: dict[tuple[str, str], list[float]] = {}
    for row in rows:
        if row["status"] == "done":
            out.setdefault((group(row), row["protocol"]), []).append(percent(row, quantity))
    return {key: {"n": len(v), "mean": float(np.mean(v)), "se": standard_error(v)} for key, v in out.items()}


def increases(rows: list[dict], geometry: str, quantity: str) -> dict[str, float]:
    """protocol -> increase (%) of one geometry's done runs."""
    return {r["protocol"]: percent(r, quantity) for r in rows if r["geometry"] == geometry and r["status"] == "done"}


def ordered(values: dict[str, float], order=PAPER_PROTOCOLS) -> bool | None:
    """Whether the values strictly decrease along ``order``; None if one is missing."""
    if not all(p in values for p in order):
        return None
    return all(values[a] > values[b] for a, b in zip(order, order[1:]))


def mwf_statistics(rows: list[dict], quantity: str) -> dict | None:
    """Mean, min and max over the geometries of the mwf increase (%), or None without mwf runs."""
    values = [percent(r, quantity) for r in rows if r["protocol"] == "mwf" and r["status"] == "done"]
    if not values:
        return None
    return {"n": len(values), "mean": float(np.mean(values)), "min": float(np.min(values)),
            "max": float(np.max(values))}

