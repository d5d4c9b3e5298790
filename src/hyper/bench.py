"""``python -m hyper.bench``: the same as ``hyper bench`` (`hyper.commands.bench`)."""

import sys

from hyper.commands.bench import main

if __name__ == "__main__":
    sys.exit(main())
