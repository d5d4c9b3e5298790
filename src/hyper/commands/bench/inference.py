"""Inference at issue 36's budgets: a Bayesian calibration ≤ 2 min on 2 cores, a protocol
design ≤ 1 min.

Each job runs as a user runs it, in this process, on the data and targets the README shows:

    hyper calibrate --data data/defreitas.csv --protocol mwf --fit kM --method bayes --no-check
    hyper design --target 5 --week 8 --no-check

(the fast model only: the coupled checks are separate runs of `hyper grow`), into a
temporary folder, wall time on rank 0 after a barrier. Writes results/bench/inference.json
and inference.png (wall time against the budget).

    python -m hyper.bench inference
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

from hyper.commands import calibrate as calibrate_job
from hyper.commands import cli
from hyper.commands import design as design_job
from hyper.commands.bench import common
from hyper.core import io, resources
from hyper.core.log import info
from hyper.runs import plot

BUDGETS_S = {"calibrate --method bayes": 120.0, "design": 60.0}  # issue 36


def jobs(data: Path) -> dict:
    return {"calibrate --method bayes": (calibrate_job.main, ["--data", str(data), "--protocol", "mwf", "--fit", "kM",
                                                             "--method", "bayes", "--no-check"]),
            "design": (design_job.main, ["--target", "5", "--week", "8", "--no-check"])}


def parser() -> cli.Parser:
    p = cli.Parser("bench inference", __doc__)
    p.add_argument("--output", type=Path, default=Path("results/bench"), help="output folder")
    return p


def run(comm, args) -> int:
    cases = []
    data = resources.folder("data") / "defreitas.csv"
    with tempfile.TemporaryDirectory() as tmp:
        for name, (main, argv) in jobs(data).items():
            out = Path(comm.bcast(tmp, root=0)) / name.split()[0]
            comm.barrier()
            start = time.perf_counter()
            rc = main([*argv, "--output", str(out)])
            comm.barrier()
            wall = time.perf_counter() - start
            cases.append({"job": name, "argv": argv, "exit": rc, "wall_s": wall, "budget_s": BUDGETS_S[name]})
            info(comm, f"hyper {name}: exit {rc}, {wall:.1f} s on {comm.size} rank(s); budget {BUDGETS_S[name]:g} s: "
                       f"{'within' if wall <= BUDGETS_S[name] else 'OVER'}")
    result = {"benchmark": "inference", "ranks": comm.size, "cases": cases, "machine": common.machine(),
              "versions": io.versions()}
    if comm.rank == 0:
        args.output.mkdir(parents=True, exist_ok=True)
        io.write_json(args.output / "inference.json", result)
        chart(args.output / "inference.png", result)
        info(comm, f"wrote {args.output / 'inference.json'} and {args.output / 'inference.png'}")
    return 0 if all(c["exit"] == 0 for c in cases) else 1


def chart(path: Path, result: dict) -> None:
    plt = plot.pyplot()
    fig, ax = plt.subplots(figsize=(6, 2.6), layout="constrained")
    names = [c["job"] for c in result["cases"]]
    ax.barh(names, [c["wall_s"] for c in result["cases"]], color="C0", label="wall time")
    ax.scatter([c["budget_s"] for c in result["cases"]], names, color="C3", marker="|", s=400, label="budget")
    ax.set_xlabel(f"seconds, {result['ranks']} rank(s)")
    ax.legend(fontsize=8)
    plot.save(fig, path, dpi=110)


main = cli.entry(parser, run)

if __name__ == "__main__":
    sys.exit(main())
