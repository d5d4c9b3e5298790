"""``python -m hyper.contraction``: the same as ``hyper contraction`` (`hyper.commands.contraction`)."""

import sys

from hyper.commands.contraction import main

if __name__ == "__main__":
    sys.exit(main())
