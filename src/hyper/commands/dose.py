"""``hyper dose`` (interim: the job still lives in `hyper.analysis.dose`)."""

from hyper.analysis.dose import main  # noqa: F401
