"""``python -m hyper.study``: the same as ``hyper study`` (`hyper.commands.study`)."""

import sys

from hyper.commands.study import main

if __name__ == "__main__":
    sys.exit(main())
