"""``python -m hyper.fibers``: the same as ``hyper fibers`` (`hyper.commands.fibers`)."""

import sys

from hyper.commands.fibers import main

if __name__ == "__main__":
    sys.exit(main())
