import sys

from hyper.signaling.cli import main

sys.exit(main())
