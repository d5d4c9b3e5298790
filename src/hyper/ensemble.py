"""``python -m hyper.ensemble``: the same as ``hyper ensemble`` (`hyper.commands.ensemble`)."""

import sys

from hyper.core import term

term.install()  # first, before the job's imports: from here on a TERM ends in exit status 143
from hyper.commands.ensemble import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
