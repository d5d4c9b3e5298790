"""``hyper fibers`` (interim: the job still lives in `hyper.fem.fibers`)."""

from hyper.fem.fibers import main  # noqa: F401
