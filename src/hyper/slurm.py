"""``python -m hyper.slurm``: the same as ``hyper slurm`` (`hyper.commands.slurm`)."""

import sys

from hyper.commands.slurm import main

if __name__ == "__main__":
    sys.exit(main())
