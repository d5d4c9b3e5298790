"""``python -m hyper.box``: the same as ``hyper box`` (`hyper.commands.box`)."""

import sys

from hyper.commands.box import main

if __name__ == "__main__":
    sys.exit(main())
