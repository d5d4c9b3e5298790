"""Benchmarks: ``hyper bench <name>`` or ``python -m hyper.bench <name>``; each writes
results/bench/<name>.json and charts (``--output``: another folder).

Speeds are reported as ratios of methods timed side by side in one run, so a loaded
or slower machine changes the absolute numbers but not the conclusions.
"""

import argparse
import importlib
import pkgutil
import sys

# Modules of the package that are not benchmarks.
SHARED = ("common",)


def available() -> list[str]:
    return sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_") and m.name not in SHARED)


def main(argv=None) -> int:
    """Run the benchmark named first in ``argv`` with the rest of it."""
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in available():
        # Dispatch before parsing, so that `<name> --help` reaches the benchmark's own parser.
        return importlib.import_module(f"hyper.commands.bench.{argv[0]}").main(argv[1:]) or 0
    parser = argparse.ArgumentParser(prog="hyper bench", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("name", choices=available(), help="which benchmark")
    parser.parse_args(argv)  # only reached for --help or a bad name
    return 2
