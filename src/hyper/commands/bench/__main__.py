"""python -m hyper.bench <name> [options]: run one benchmark (see --help)."""

import sys

from hyper.commands.bench import main

if __name__ == "__main__":
    sys.exit(main())
