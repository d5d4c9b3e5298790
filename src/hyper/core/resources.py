"""Where the inputs shipped with hyper live: meshes (with their fibre fields), data,
studies and the Slurm templates in jobs/.

In a checkout they are the folders beside src/; `pip install .` copies the same folders
into the installed package (pyproject.toml maps them to hyper/meshes, hyper/data,
hyper/studies, hyper/jobs), so an installed hyper runs from any folder.
"""

from __future__ import annotations

from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1]  # hyper/, this module being hyper/core/resources.py
FOLDERS = ("meshes", "data", "studies", "jobs")


def checkout() -> Path | None:
    """The project folder when hyper runs from a checkout (src/hyper); None when installed."""
    root = PACKAGE.parents[1]
    return root if PACKAGE.parent.name == "src" and (root / "pyproject.toml").is_file() else None


def folder(name: str) -> Path:
    """One of `FOLDERS`: the installed copy where there is one, else the checkout's."""
    if name not in FOLDERS:
        raise ValueError(f"no shipped folder {name!r}; known: {', '.join(FOLDERS)}")
    installed = PACKAGE / name
    return installed if installed.is_dir() or checkout() is None else checkout() / name
