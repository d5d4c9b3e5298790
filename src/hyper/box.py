"""``python -m hyper.box``: the same as ``hyper box`` (`hyper.commands.box`)."""

import sys

from hyper.core import term

term.install()  # first, before the job's imports: from here on a TERM ends in exit status 143
from hyper.commands.box import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
