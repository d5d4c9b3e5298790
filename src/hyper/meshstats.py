"""``python -m hyper.meshstats``: the same as ``hyper meshstats`` (`hyper.commands.meshstats`)."""

import sys

from hyper.commands.meshstats import main

if __name__ == "__main__":
    sys.exit(main())
