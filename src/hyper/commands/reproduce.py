"""``hyper reproduce`` (interim: the job still lives in `hyper.analysis.reproduce`)."""

from hyper.analysis.reproduce import main  # noqa: F401
