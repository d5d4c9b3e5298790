"""``hyper study`` (interim: the job still lives in `hyper.analysis.study`)."""

from hyper.analysis.study import main  # noqa: F401
