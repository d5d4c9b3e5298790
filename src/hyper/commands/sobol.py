"""``hyper sobol`` (interim: the job still lives in `hyper.analysis.sobol`)."""

from hyper.analysis.sobol import main  # noqa: F401
