"""``hyper mesh`` (interim: the job still lives in `hyper.fem.meshing`)."""

from hyper.fem.meshing import main  # noqa: F401
