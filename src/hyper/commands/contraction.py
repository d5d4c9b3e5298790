"""``hyper contraction`` (interim: the job still lives in `hyper.runs.contraction`)."""

from hyper.runs.contraction import main  # noqa: F401
