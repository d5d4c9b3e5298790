"""``hyper ensemble`` (interim: the job still lives in `hyper.analysis.ensemble`)."""

from hyper.analysis.ensemble import main  # noqa: F401
