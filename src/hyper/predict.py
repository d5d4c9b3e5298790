"""``python -m hyper.predict``: the same as ``hyper predict`` (`hyper.commands.predict`)."""

import sys

from hyper.core import term

term.install()  # first, before the job's imports: from here on a TERM ends in exit status 143
from hyper.commands.predict import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
