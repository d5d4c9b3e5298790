"""python -m hyper.bench <name> [options]: run one benchmark (see --help)."""

import argparse
import importlib
import pkgutil
import sys

import hyper.bench


# Modules of the package that are not benchmarks.
SHARED = ("common",)


def available() -> list[str]:
    return sorted(m.name for m in pkgutil.iter_modules(hyper.bench.__path__)
                  if not m.name.startswith("_") and m.name not in SHARED)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] in available():
        # Dispatch before parsing, so that `<name> --help` reaches the benchmark's own parser.
        return importlib.import_module(f"hyper.bench.{argv[0]}").main(argv[1:]) or 0
    parser = argparse.ArgumentParser(prog="python -m hyper.bench", description=__doc__)
    parser.add_argument("name", choices=available(), help="which benchmark")
    parser.parse_args(argv)  # only reached for --help or a bad name
    return 2


if __name__ == "__main__":
    sys.exit(main())
