"""Slurm batch scripts from the templates in ``jobs/``: fill the placeholders, check values.

    hyper slurm cohort --ntasks 36 --time 2:00:00 -o cohort.sbatch
    hyper slurm grow-array --protocols mwf weekly -o array.sbatch
    hyper slurm sobol --ntasks 64 --samples 8192 -o sobol.sbatch
    hyper slurm cohort --partition compute --account proj42 --qos normal --mem 4G \
        --prelude site.sh -o cohort.sbatch     # site.sh: module loads, exports
    sbatch cohort.sbatch

A placeholder is ``{name}`` with a lower-case name; shell variables in the templates are
upper case (``${RUNS[...]}``, ``$PID``), so the two never clash. Rendering fails on a
placeholder without a value and on a value without a placeholder, so a script never
leaves here half filled. See jobs/README.md.
"""

from __future__ import annotations

import argparse
import re
import shlex
import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from hyper.analysis import sobol
from hyper.commands import cli
from hyper.core import io, log, resources, term
from hyper.core.params import InputError, read_text
from hyper.fem import geometry as geo
from hyper.model import protocols

# the folder a job runs in by default: the checkout, or (installed) the current folder
ROOT = resources.checkout() or Path.cwd()
# Slurm keeps the warning time of --signal=SIG@TIME in 16 bits
MAX_WARN_S = 65535
TEMPLATES = {
    "cohort": resources.folder("jobs") / "cohort.sbatch.in",
    "grow-array": resources.folder("jobs") / "grow-array.sbatch.in",
    "sobol": resources.folder("jobs") / "sobol.sbatch.in",
}
PLACEHOLDER = re.compile(r"\{([a-z][a-z0-9_]*)\}")
# Slurm's time formats: M, M:S, H:M:S, D-H, D-H:M, D-H:M:S
TIME = re.compile(r"\d+(:\d{1,2}){0,2}|\d+-\d{1,2}(:\d{1,2}){0,2}")
# Slurm's memory per node: a number with an optional unit (K, M, G, T; M by default)
MEMORY = re.compile(r"[1-9]\d*[KMGT]?")
SITE_OPTIONS = ("partition", "account", "qos", "mem")  # the #SBATCH lines a site asks for


def placeholders(text: str) -> set[str]:
    return set(PLACEHOLDER.findall(text))


def render(text: str, values: Mapping[str, Any], source: str = "template") -> str:
    """``text`` with every ``{name}`` replaced by ``str(values[name])``."""
    needed = placeholders(text)
    missing = sorted(needed - set(values))
    unused = sorted(set(values) - needed)
    if missing:
        raise InputError(f"{source}: no value for placeholder(s) {', '.join(missing)}")
    if unused:
        raise InputError(f"{source}: no placeholder for value(s) {', '.join(unused)}")
    return PLACEHOLDER.sub(lambda m: str(values[m.group(1)]), text)


def render_template(path: str | Path, **values) -> str:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such template")
    return render(read_text(path, "template"), values, str(path))


def cohort_runs(geometries: Sequence[str] | None, protocol_names: Sequence[str] | None) -> list[tuple[str, str]]:
    """(geometry, protocol) pairs, geometry-major; by default the paper's cohort."""
    geometries = list(geo.ANATOMICAL) if not geometries else list(geometries)
    protocol_names = list(protocols.PAPER) if not protocol_names else list(protocol_names)
    for g in geometries:
        if g not in geo.GEOMETRIES:
            raise InputError(f"--geometries: unknown geometry {g!r}; known: {', '.join(geo.GEOMETRIES)}")
    for p in protocol_names:
        if p not in protocols.NAMES:
            raise InputError(f"--protocols: unknown protocol {p!r}; known: {', '.join(protocols.NAMES)}")
    return [(g, p) for g in geometries for p in protocol_names]


def runs_block(runs: Sequence[tuple[str, str]]) -> str:
    """The lines of a bash array, one quoted "geometry protocol" pair each."""
    return "\n".join(f'    "{g} {p}"' for g, p in runs)


def _word(value, option: str) -> str:
    """A value that goes into the script unquoted: it must need no shell quoting."""
    text = str(value)
    if not text or shlex.quote(text) != text:
        raise InputError(f"{option}: {text!r} must be non-empty, without spaces or shell characters")
    return text


def _folder(path: Path, option: str) -> str:
    """An existing folder, as an absolute path that needs no shell quoting."""
    if not path.is_dir():
        raise InputError(f"{option} {path}: no such folder")
    return _word(path.resolve(), option)


def check_syntax(script: str, source: str) -> None:
    """``bash -n`` on a rendered script: what an --args value or a --prelude can still break."""
    with term.spawning():
        done = subprocess.run(["bash", "-n"], input=script, capture_output=True, text=True, timeout=30)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["no message"])[-1]
        raise InputError(f"{source}: the rendered script is not valid bash ({last}); check --args and --prelude")


def site_lines(args: argparse.Namespace) -> str:
    """The #SBATCH lines of --partition, --account, --qos and --mem (a comment without any)."""
    if args.mem is not None and not MEMORY.fullmatch(args.mem):
        raise InputError(f"--mem: {args.mem!r} is not a Slurm memory size (a number with K, M, G or T, e.g. 4G)")
    lines = [f"#SBATCH --{name}={_word(getattr(args, name), '--' + name)}" for name in SITE_OPTIONS
             if getattr(args, name) is not None]
    return "\n".join(lines) if lines else "# (no --partition, --account, --qos or --mem: the site's defaults)"


def prelude_lines(path: Path | None) -> str:
    """The lines of --prelude (module loads, exports), put after the venv's activation."""
    if path is None:
        return "# (no --prelude)"
    if not path.is_file():
        raise InputError(f"--prelude {path}: no such file")
    try:
        text = read_text(path, "shell file")
    except InputError as err:
        raise InputError(f"--prelude {err}") from None
    return f"# from --prelude {path}:\n{text.rstrip()}"


def values_for(kind: str, args: argparse.Namespace) -> dict[str, Any]:
    """The placeholder values of template ``kind`` from the parsed options, checked."""
    if not TIME.fullmatch(args.time):
        raise InputError(f"--time: {args.time!r} is not a Slurm time (M, H:M:S, D-H:M:S, ...)")
    if "\n" in args.args:
        raise InputError("--args must be one line")
    try:
        shlex.split(args.args)
    except ValueError as err:  # an unbalanced quote would swallow the rest of the script
        raise InputError(f"--args {args.args!r}: {err}") from None
    venv = args.venv.resolve()
    if not (venv / "bin" / "activate").is_file():
        raise InputError(f"--venv {args.venv}: no bin/activate, not a virtual environment")
    values = {
        "job_name": _word(args.job_name, "--job-name"),
        "ntasks": args.ntasks,
        "time": args.time,
        "workdir": _folder(args.workdir, "--workdir"),
        "venv": _word(venv, "--venv"),
        "output": _word(args.output, "--output"),
        "log_dir": _word(args.log_dir, "--log-dir"),
        "warn_s": args.warn_s,
        "max_requeue": args.max_requeue,
        "srun_mpi": _word(args.srun_mpi, "--srun-mpi"),
        "args": args.args,
        "site": site_lines(args),
        "prelude": prelude_lines(args.prelude),
    }
    if kind == "cohort":
        values["ranks_per_job"] = args.ranks_per_job
        if args.ntasks % args.ranks_per_job:
            raise InputError(f"--ranks-per-job {args.ranks_per_job} must divide --ntasks {args.ntasks}")
    elif kind == "grow-array":
        runs = cohort_runs(args.geometries, args.protocols)
        throttle = f"%{args.max_parallel}" if args.max_parallel is not None else ""
        values["runs"] = runs_block(runs)
        values["array"] = f"0-{len(runs) - 1}{throttle}"
    elif kind == "sobol":
        values["samples"] = args.samples
    return values


DEFAULTS = {  # first guesses per template: ntasks, time, output
    "cohort": (36, "2:00:00", "results/cohort"),
    "grow-array": (1, "1:00:00", "results/grow"),
    "sobol": (32, "24:00:00", "results/sobol"),
}


class _KindParser(cli.Parser):
    """The parser of one template: a `cli.Parser` named ``hyper slurm KIND`` by argparse."""

    def __init__(self, prog: str, **kwargs):
        super().__init__(prog.removeprefix("hyper "), **kwargs)


def parser() -> cli.Parser:
    p = cli.Parser("slurm", description=__doc__)
    kinds = p.add_subparsers(dest="kind", required=True, metavar="{cohort,grow-array,sobol}",
                             parser_class=_KindParser, help="the template to render")
    for kind, (ntasks, time, output) in DEFAULTS.items():
        k = kinds.add_parser(kind, help=f"render jobs/{TEMPLATES[kind].name}")
        k.add_argument("-o", "--script", type=cli.output(folder=False),
                       help="where to write the script (stdout if not given)")
        k.add_argument("--ntasks", type=cli.integer(1), default=ntasks, help="MPI ranks")
        k.add_argument("--time", default=time, help="time limit")
        k.add_argument("--job-name", default=f"hyper-{kind}", help="the Slurm job name")
        k.add_argument("--output", default=output, help="results folder")
        k.add_argument("--workdir", type=Path, default=ROOT, help="the project folder the job runs in (must exist)")
        k.add_argument("--venv", type=Path, default=Path(sys.prefix), help="virtual environment to activate")
        k.add_argument("--log-dir", default="results/slurm", help="Slurm logs, relative to --workdir")
        k.add_argument("--warn-s", type=cli.integer(1, MAX_WARN_S), default=300,
                       help="stop the run (TERM to its ranks) this many s before the time limit")
        k.add_argument("--max-requeue", type=cli.integer(0), default=3, help="requeue at most this many times")
        k.add_argument("--srun-mpi", default="pmi2", help="srun --mpi plugin")
        k.add_argument("--args", default="", help="extra options for the python command, as one string")
        k.add_argument("--prelude", type=Path, metavar="FILE", reads=True,
                       help="shell lines put into the script after the venv's activation (module loads, exports)")
        k.add_argument("--partition", help="#SBATCH --partition (the site's default if not given)")
        k.add_argument("--account", help="#SBATCH --account, the allocation charged")
        k.add_argument("--qos", help="#SBATCH --qos")
        k.add_argument("--mem", help="#SBATCH --mem, memory per node (e.g. 4G)")
        if kind == "cohort":
            k.add_argument("--ranks-per-job", type=cli.integer(1), default=1, help="ranks per run")
        elif kind == "grow-array":
            k.add_argument("--geometries", nargs="+", metavar="ID",
                           help="geometries; the 12 anatomical meshes if not given")
            k.add_argument("--protocols", nargs="+", metavar="NAME", default=list(protocols.PAPER), help="protocols")
            k.add_argument("--max-parallel", type=cli.integer(1), help="at most this many array tasks at once")
        else:
            k.add_argument("--samples", type=cli.integer(2, sobol.MAX_SAMPLES), default=sobol.SAMPLES,
                           help="Sobol base samples (hyper.sobol's bounds)")
    return p


def run(comm, args) -> int:
    script = render_template(TEMPLATES[args.kind], **values_for(args.kind, args))
    check_syntax(script, f"hyper slurm {args.kind}")
    logs = args.workdir / args.log_dir
    if logs.exists() and not logs.is_dir():
        raise InputError(f"--log-dir {args.log_dir}: {logs} is not a folder")
    if args.script is not None and args.script.is_dir():
        raise InputError(f"--script {args.script}: is a folder; name the script file")
    # Slurm does not create the folder of --output: a missing one fails the job silently.
    logs.mkdir(parents=True, exist_ok=True)
    if args.script is None:
        sys.stdout.write(script)
    else:
        # atomic: a full disk leaves no truncated script that looks whole
        with io.atomic_path(args.script) as tmp:
            tmp.write_text(script)
        log.info(comm, f"wrote {args.script}; submit with: sbatch {args.script}")
    return cli.EXIT_OK


# Scripts are rendered on a login node, where MPI need not start.
main = cli.entry(parser, run, world=False)

if __name__ == "__main__":
    sys.exit(main())
