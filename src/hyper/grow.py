"""``python -m hyper.grow``: the same as ``hyper grow`` (`hyper.commands.grow`)."""

import sys

from hyper.commands.grow import main

if __name__ == "__main__":
    sys.exit(main())
