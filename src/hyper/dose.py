"""``python -m hyper.dose``: the same as ``hyper dose`` (`hyper.commands.dose`)."""

import sys

from hyper.commands.dose import main

if __name__ == "__main__":
    sys.exit(main())
