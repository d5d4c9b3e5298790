"""``hyper cohort`` (interim: the job still lives in `hyper.analysis.cohort`)."""

from hyper.analysis.cohort import main  # noqa: F401
