"""``hyper calibrate`` (interim: the job still lives in `hyper.analysis.calibrate`)."""

from hyper.analysis.calibrate import main  # noqa: F401
