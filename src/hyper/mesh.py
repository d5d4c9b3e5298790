"""``python -m hyper.mesh``: the same as ``hyper mesh`` (`hyper.commands.mesh`)."""

import sys

from hyper.commands.mesh import main

if __name__ == "__main__":
    sys.exit(main())
