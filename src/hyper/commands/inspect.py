"""hyper inspect: what a result file is, where it came from, and what it says.

    hyper inspect results/grow/idealized_mwf.h5

Prints the fibres a run used (their kind, how they were made and their file's SHA-256),
the provenance (command, versions, git commit, run digest, mesh hash, ranks,
quadrature degree, refinements, linear solver), the attribute groups (signaling, material, protocol,
settings, heterogeneity, fidelity, spatial: the names every job uses), the study file that reruns
a growth result, and each series with its unit, length and first and last values.
Works on every HDF5 result the jobs write.

    hyper inspect results/a/idealized_mwf.h5 --against results/b/idealized_mwf.h5

compares every series of the two results instead (but wall_s, a run's own timing): bit for
bit, or by its largest difference; exit status 1 where any differs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hyper.commands import cli
from hyper.core import io
from hyper.core.params import InputError

# the groups every job names alike, shown first
GROUPS = ("signaling", "material", "protocol", "settings", "heterogeneity", "fidelity", "spatial")


def parser() -> cli.Parser:
    p = cli.Parser("inspect", __doc__)
    p.add_argument("result", type=Path, help="an HDF5 result file")
    p.add_argument("--against", type=Path, metavar="OTHER.h5", help="another result: compare their series")
    return p


def shown(value) -> str:
    if isinstance(value, bytes):
        value = value.decode(errors="replace")
    if isinstance(value, np.ndarray) and value.size > 6:
        return f"[{', '.join(f'{v:g}' for v in value[:3])}, …, {value[-1]:g}] ({value.size} values)"
    return str(value)


def describe(path: Path) -> list[str]:
    import h5py

    # the whole reading in `reading_h5`: a file damaged inside (its header whole) fails at
    # the first group or dataset that lies in the damage, and that is bad input too
    with io.reading_h5(path) as f:
        lines = [f"{path}: {'complete' if f.attrs.get('complete') else 'INCOMPLETE (its writer did not finish)'}"]
        provenance = {k: v for k, v in f.attrs.items() if k not in ("complete", "study")}
        if "fibers" in f.attrs:  # the fibres a run used: kind, how they were made, their file
            sha = shown(f.attrs.get("fibers_sha256", "")) or "none (from a formula)"
            lines.append(f"fibres: {shown(f.attrs['fibers'])}, {shown(f.attrs.get('fibers_method', '?'))}; "
                         f"file SHA-256 {sha}")
        lines.append("provenance:")
        lines += [f"  {k} = {shown(v)}" for k, v in sorted(provenance.items())]
        groups = sorted((name for name, item in f.items() if isinstance(item, h5py.Group)),
                        key=lambda name: (GROUPS.index(name) if name in GROUPS else len(GROUPS), name))
        for name in groups:
            lines.append(f"[{name}]")
            lines += [f"  {k} = {shown(v)}" for k, v in sorted(f[name].attrs.items())]
        if "study" in f.attrs:
            lines.append("study (the study file that reruns this result):")
            lines += [f"  {line}" for line in shown(f.attrs["study"]).splitlines()]
        lines.append("series:")
        for name, item in sorted(f.items()):
            if isinstance(item, h5py.Dataset):
                data = item[()]
                ends = (f", first {data.flat[0]:.6g}, last {data.flat[-1]:.6g}"
                        if data.size and data.dtype.kind in "iuf" else "")
                lines.append(f"  {name} [{shown(item.attrs.get('units', '?'))}]: shape {data.shape}{ends}")
    return lines


def compare(path: Path, other: Path) -> tuple[list[str], bool]:
    """(a line per series of either result, whether every one is the same bits)."""
    for result in (path, other):
        if not io.is_complete(result):
            raise InputError(f"{result}: missing or incomplete (no 'complete' mark): not a result to compare")
    series, others = io.read_series(path), io.read_series(other)
    lines, same = [], True
    for name in sorted(set(series) | set(others)):
        if name == "wall_s":
            continue
        a, b = series.get(name), others.get(name)
        if a is None or b is None:
            lines.append(f"  {name}: only in {path if b is None else other}")
            same = False
        elif a.shape != b.shape:
            lines.append(f"  {name}: shapes {a.shape} and {b.shape}")
            same = False
        elif np.array_equal(a, b, equal_nan=a.dtype.kind == "f"):
            lines.append(f"  {name}: identical ({a.size} values)")
        else:
            difference = np.max(np.abs(a.astype(float) - b.astype(float)))
            lines.append(f"  {name}: differs, largest |difference| {difference:.3g}")
            same = False
    return [f"{path} against {other}:", *lines], same


def run(comm, args) -> int:
    if args.against is None:
        print("\n".join(describe(args.result)))
        return cli.EXIT_OK
    lines, same = compare(args.result, args.against)
    print("\n".join(lines))
    return cli.EXIT_OK if same else cli.EXIT_SOME_FAILED


main = cli.entry(parser, run, world=False)
