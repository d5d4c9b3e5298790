"""``python -m hyper.cohort``: the same as ``hyper cohort`` (`hyper.commands.cohort`)."""

import sys

from hyper.commands.cohort import main

if __name__ == "__main__":
    sys.exit(main())
