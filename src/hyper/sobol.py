"""``python -m hyper.sobol``: the same as ``hyper sobol`` (`hyper.commands.sobol`)."""

import sys

from hyper.commands.sobol import main

if __name__ == "__main__":
    sys.exit(main())
