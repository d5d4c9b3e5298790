"""``python -m hyper.inspect``: the same as ``hyper inspect`` (`hyper.commands.inspect`)."""

import sys

from hyper.commands.inspect import main

if __name__ == "__main__":
    sys.exit(main())
