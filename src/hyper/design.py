"""``python -m hyper.design``: the same as ``hyper design`` (`hyper.commands.design`)."""

import sys

from hyper.core import term

term.install()  # first, before the job's imports: from here on a TERM ends in exit status 143
from hyper.commands.design import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
