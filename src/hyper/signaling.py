"""``python -m hyper.signaling``: the same as ``hyper signaling`` (`hyper.commands.signaling`)."""

import sys

from hyper.commands.signaling import main

if __name__ == "__main__":
    sys.exit(main())
