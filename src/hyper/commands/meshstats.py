"""``hyper meshstats`` (interim: the job still lives in `hyper.fem.meshstats`)."""

from hyper.fem.meshstats import main  # noqa: F401
