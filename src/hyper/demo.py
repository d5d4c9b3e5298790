"""``python -m hyper.demo``: the same as ``hyper demo`` (`hyper.commands.demo`)."""

import sys

from hyper.commands.demo import main

if __name__ == "__main__":
    sys.exit(main())
