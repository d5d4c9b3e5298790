"""``python -m hyper.reproduce``: the same as ``hyper reproduce`` (`hyper.commands.reproduce`)."""

import sys

from hyper.commands.reproduce import main

if __name__ == "__main__":
    sys.exit(main())
