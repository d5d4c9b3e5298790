"""The README and docs/ show commands that work and links that lead somewhere.

Every command shown in README.md and docs/*.md (code blocks and inline code) that starts
with ``hyper JOB``, ``python -m hyper.JOB``, ``mpirun -n N …`` of either, or ``make
TARGET`` must name a real job (``hyper.commands.cli.JOBS``; for ``hyper bench NAME`` a
benchmark of ``hyper.commands.bench.available()``) or a target of the Makefile, and every
``--option`` on it must be one the job's parser accepts. A line without placeholders
(``FILE``, ``<job>``, ``…``, ``[options]``, ``{a,b}``, ``ε``) and without ``--help`` is
parsed whole by the job's parser, as ``hyper JOB`` would, so a wrong value or a missing
argument fails too. Every relative link ``[text](path)`` must point to an existing file.
Parsing needs the job modules only: no MPI job starts, nothing is written.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import re
import shlex
from pathlib import Path

import pytest

from hyper.commands import bench, cli
from hyper.core.params import InputError

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

FENCE = re.compile(r"^\s*(```|~~~)")
INLINE = re.compile(r"(`+)(.+?)\1", re.S)
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
# A placeholder token: an ellipsis, brackets, a choice list, an ALL-CAPS name (FILE,
# RESULT.h5, meshes/NAME/, F.toml) or a non-ASCII letter (ε).
PLACEHOLDER = re.compile(r"…|\.\.\.|[<>\[\]{}|]|(^|[/=])[A-Z][A-Z0-9_]*(\.[A-Za-z0-9]+)*(/|$)|[^\x00-\x7f]")
SHELL = {"&&", "||", ";", "|", ">", ">>", "<", "&"}


# ------------------------------------------------------------------ reading the docs


def candidates(text: str) -> list[str]:
    """Command candidates of a markdown text: the lines of its code blocks (fenced or
    indented, ``\\`` continuations joined, ``#`` comments dropped) and its inline code
    spans (a span may run over a line break)."""
    found, prose, block = [], [], None
    lines = text.split("\n")
    previous_blank = True
    i = 0
    while i < len(lines):
        line = lines[i]
        if block is None and FENCE.match(line):
            block = []
        elif block is not None and FENCE.match(line):
            found += _joined(block)
            block = None
        elif block is not None:
            block.append(line)
        elif line.startswith("    ") and previous_blank and line.strip():
            indented = []
            while i < len(lines) and (lines[i].startswith("    ") or not lines[i].strip()):
                indented.append(lines[i][4:])
                i += 1
            found += _joined(indented)
            previous_blank = True
            continue
        else:
            prose.append(line)
        previous_blank = not line.strip()
        i += 1
    found += [" ".join(m.group(2).split()) for m in INLINE.finditer("\n".join(prose))]
    return found


def _joined(lines: list[str]) -> list[str]:
    out, current = [], ""
    for line in lines:
        current += line
        if current.rstrip().endswith("\\"):
            current = current.rstrip()[:-1] + " "
            continue
        out.append(" ".join(re.sub(r"(^|\s)#.*$", "", current).split()))
        current = ""
    return [line for line in out if line]


def commands(line: str) -> list[list[str]]:
    """The simple commands of a shell line, each a token list (split at ``&&``, ``;``, …)."""
    try:
        tokens = shlex.split(line)
    except ValueError:
        tokens = line.split()
    out, current = [], []
    for token in tokens:
        if token in SHELL:
            out.append(current)
            current = []
        else:
            current.append(token)
    return [c for c in [*out, current] if c]


def invocation(tokens: list[str]) -> tuple[str, str, list[str]] | None:
    """(``"job"``, JOB, its arguments) or (``"make"``, "", targets) for a command of hyper
    or make; None for any other command."""
    tokens = list(tokens)
    while tokens and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*=\S*", tokens[0]):
        tokens.pop(0)  # VAR=value before the command
    if tokens and Path(tokens[0]).name in ("mpirun", "mpiexec"):
        tokens.pop(0)
        if tokens[:1] in (["-n"], ["-np"]) and len(tokens) > 1:
            tokens = tokens[2:]
    if not tokens:
        return None
    head = Path(tokens[0]).name
    if head == "hyper" and len(tokens) > 1:
        return "job", tokens[1], tokens[2:]
    if re.fullmatch(r"python[0-9.]*", head) and tokens[1:2] == ["-m"] and len(tokens) > 2:
        module = tokens[2]
        if module.startswith("hyper.") and module.count(".") == 1:
            return "job", module.split(".", 1)[1], tokens[3:]
    if head == "make":
        return "make", "", [t for t in tokens[1:] if not t.startswith("-") and "=" not in t]
    return None


# ---------------------------------------------------------------------- the checks


@functools.cache
def make_targets() -> frozenset[str]:
    targets = set()
    for line in (ROOT / "Makefile").read_text().splitlines():
        m = re.match(r"^([^\s#:=][^:=]*?)\s*:(?!=)", line)
        if m:
            targets.update(t for t in m.group(1).split() if "$" not in t and "%" not in t)
    return frozenset(targets)


@functools.cache
def job_parser(job: str, name: str | None = None) -> argparse.ArgumentParser:
    """The parser of ``hyper JOB`` (``hyper bench NAME``): every command module has one."""
    module = importlib.import_module(f"hyper.commands.bench.{name}" if job == "bench" else f"hyper.commands.{job}")
    return module.parser()


def option_strings(parser: argparse.ArgumentParser) -> set[str]:
    """The option strings of a parser and of its subcommands' parsers."""
    found = set(parser._option_string_actions)
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                found |= option_strings(sub)
    return found


def subcommands(parser: argparse.ArgumentParser) -> set[str]:
    return {name for action in parser._actions if isinstance(action, argparse._SubParsersAction)
            for name in action.choices}


def choices(token: str) -> list[str] | None:
    """The names of a ``{a,b,c}`` token, None for any other."""
    m = re.fullmatch(r"\{([A-Za-z0-9_,-]+)\}", token)
    return m.group(1).split(",") if m else None


def problems(line: str) -> tuple[int, list[str]]:
    """(how many hyper or make commands ``line`` holds, what is wrong with them)."""
    checked, wrong = 0, []
    for tokens in commands(line):
        found = invocation(tokens)
        if found is None:
            continue
        kind, job, args = found
        if kind == "make":
            checked += 1
            wrong += [f"{line}: make {t}: no such target in the Makefile" for t in args
                      if t not in make_targets()]
            continue
        if PLACEHOLDER.search(job):
            continue  # `hyper <job> …`, `hyper JOB`: the form, not a command
        checked += 1
        if job not in cli.JOBS:
            wrong.append(f"{line}: {job!r} is not a job ({', '.join(cli.JOBS)})")
            continue
        if job == "bench":
            if not args:
                continue
            names = choices(args[0]) or [args[0]]
            missing = [n for n in names if n not in bench.available()]
            if missing:
                wrong.append(f"{line}: no benchmark {', '.join(missing)} ({', '.join(bench.available())})")
                continue
            if len(names) > 1:
                continue  # {a,b,...}: the names only
            parser, args = job_parser("bench", names[0]), args[1:]
        else:
            parser = job_parser(job)
        known = option_strings(parser)
        for token in args:
            option = token.lstrip("[(").split("=", 1)[0].rstrip("])")  # [--unit mm|m] too
            if option.startswith("--") and len(option) > 2 and option not in known:
                wrong.append(f"{line}: {parser.prog} has no option {option}")
        for token in args:
            names = choices(token)
            if names and subcommands(parser):
                wrong += [f"{line}: {parser.prog} has no subcommand {n}" for n in names
                          if n not in subcommands(parser)]
        concrete = not any(PLACEHOLDER.search(t) for t in args)
        if concrete and args and not {"--help", "-h", "--version"} & set(args) and not wrong:
            try:
                parser.parse_args(args)
            except InputError as err:
                wrong.append(f"{line}: {parser.prog}: {err}")
    return checked, wrong


def broken_links(path: Path, text: str | None = None) -> tuple[int, list[str]]:
    """(how many relative links ``path`` holds, those whose file does not exist)."""
    text = path.read_text() if text is None else text
    checked, wrong = 0, []
    for target in LINK.findall(text):
        if re.match(r"[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # http(s), mailto, an anchor in the same page
        checked += 1
        if not (path.parent / target.split("#", 1)[0]).exists():
            wrong.append(f"{path.name}: [{target}] points to no file")
    return checked, wrong


# ------------------------------------------------------------------------ the tests


@pytest.fixture(autouse=True)
def _in_the_checkout(monkeypatch):
    monkeypatch.chdir(ROOT)  # relative paths in the docs are the checkout's


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_the_docs_commands_are_valid(doc):
    wrong = []
    for line in candidates(doc.read_text()):
        wrong += problems(line)[1]
    assert wrong == [], "\n".join(wrong)


def test_the_docs_show_commands():
    counted = sum(problems(line)[0] for doc in DOCS for line in candidates(doc.read_text()))
    assert counted >= 50, counted  # the extractor still finds the README's commands


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_the_docs_links_point_to_files(doc):
    checked, wrong = broken_links(doc)
    assert wrong == [], "\n".join(wrong)


def test_the_checker_finds_a_wrong_option():
    assert problems("hyper grow --geometry idealized --protocol mwf") == (1, [])
    assert problems("mpirun -n 2 python -m hyper.grow --geometry idealized --protocol mwf") == (1, [])
    assert "no option --no-such-option" in problems("hyper grow --geometry idealized --no-such-option")[1][0]
    # a placeholder line: option names only
    assert problems("hyper box RESULT.h5 --output F.h5") == (1, [])
    assert "no option --outptu" in problems("hyper box RESULT.h5 --outptu F.h5")[1][0]
    assert "no option --cels" in problems("hyper mesh SURFACE.stl [--cels 8000]")[1][0]
    # parsed whole: a bad value too
    assert problems("hyper grow --geometry idealized --progress-every soon")[1]


def test_the_checker_finds_a_wrong_job_benchmark_or_target():
    assert "not a job" in problems("hyper nosuchjob --help")[1][0]
    assert "no benchmark nosuch" in problems("python -m hyper.bench nosuch")[1][0]
    assert "no benchmark nosuch" in problems("python -m hyper.bench {speed,nosuch}")[1][0]
    assert problems("make demo") == (1, [])
    assert "no such target" in problems("make no-such-target")[1][0]
    assert problems("xvfb-run -a pvbatch jobs/paraview_render.py A B") == (0, [])
    assert problems("hyper <job> …") == (0, [])


def test_the_extractor_reads_blocks_spans_and_continuations():
    text = ("Run `hyper grow\n--geometry idealized` now.\n\n"
            "    hyper cohort --geometries a \\\n        --output b   # a comment\n\n"
            "```sh\nmake test\n```\n")
    assert candidates(text) == ["hyper cohort --geometries a --output b", "make test",
                                "hyper grow --geometry idealized"]


def test_the_link_check_finds_a_broken_link():
    text = "[ok](README.md) [gone](docs/nothing.md) [web](https://example.org) [here](#jobs)"
    assert broken_links(ROOT / "README.md", text) == (2, ["README.md: [docs/nothing.md] points to no file"])


MODULE_PATH = re.compile(r"`(hyper\.(?:core|model|fem|runs|analysis|commands)(?:\.[A-Za-z_][A-Za-z0-9_]*)+)")


def unresolved(text: str) -> list[str]:
    """The `hyper.LAYER.module[.name]` references of ``text`` that name no module or attribute."""
    bad = []
    for ref in sorted(set(MODULE_PATH.findall(text))):
        parts = ref.split(".")
        for i in range(len(parts), 1, -1):
            try:
                obj = importlib.import_module(".".join(parts[:i]))
            except ImportError:
                continue
            try:
                for name in parts[i:]:
                    obj = getattr(obj, name)
            except AttributeError:
                bad.append(ref)
            break
        else:
            bad.append(ref)
    return bad


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_the_docs_module_paths_resolve(doc):
    assert unresolved(doc.read_text()) == []


def test_the_module_path_check_finds_a_moved_name():
    assert unresolved("`hyper.fem.coupled.CoupledModel` and `hyper.runs.driver.execute`") == []
    assert unresolved("`hyper.runs.driver.Specification` and `hyper.fem.nowhere`") == [
        "hyper.fem.nowhere", "hyper.runs.driver.Specification"]
