"""``python -m hyper.calibrate``: the same as ``hyper calibrate`` (`hyper.commands.calibrate`)."""

import sys

from hyper.commands.calibrate import main

if __name__ == "__main__":
    sys.exit(main())
