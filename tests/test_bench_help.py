"""Every benchmark's --help explains every option and shows its default."""

import importlib

import pytest

from hyper.commands import bench

# argparse's own entries, which have no default to show
NO_DEFAULT = ("-h, --help", "--version")


def option_entries(text: str) -> list[str]:
    """The entries of the option sections of a --help text, each joined into one line."""
    entries: list[str] = []
    for line in text.split("\noptions:\n", 1)[1].splitlines():
        if line.startswith("  -"):
            entries.append(line.strip())
        elif line.startswith("   ") and entries:  # the help wrapped onto the next lines
            entries[-1] += " " + line.strip()
    return entries


@pytest.mark.parametrize("name", bench.available())
def test_every_option_has_a_help_string_and_its_default(name):
    text = importlib.import_module(f"hyper.commands.bench.{name}").parser().format_help()
    entries = option_entries(text)
    assert len(entries) > len(NO_DEFAULT)
    bare = [e for e in entries if not e.startswith(NO_DEFAULT) and "(default:" not in e]
    assert bare == []


def test_the_readme_lists_every_benchmark():
    import re
    from pathlib import Path

    from hyper.commands import bench

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    listed = re.search(r"python -m hyper\.bench \{([a-z,]+)\}", readme).group(1).split(",")
    assert listed == bench.available()
