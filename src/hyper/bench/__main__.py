"""python -m hyper.bench <name> [options]: run one benchmark (see --help)."""

import argparse
import importlib
import pkgutil
import sys

import hyper.bench


def available() -> list[str]:
    return sorted(m.name for m in pkgutil.iter_modules(hyper.bench.__path__) if not m.name.startswith("_"))


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(prog="python -m hyper.bench", description=__doc__)
    parser.add_argument("name", choices=available(), help="which benchmark")
    args, rest = parser.parse_known_args(argv)
    module = importlib.import_module(f"hyper.bench.{args.name}")
    return module.main(rest) or 0


if __name__ == "__main__":
    sys.exit(main())
