"""``python -m hyper.ensemble``: the same as ``hyper ensemble`` (`hyper.commands.ensemble`)."""

import sys

from hyper.commands.ensemble import main

if __name__ == "__main__":
    sys.exit(main())
