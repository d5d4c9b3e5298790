"""``hyper sobol``: Sobol sensitivity analysis (MODEL.md §7), farmed across MPI ranks.

The analysis is `hyper.analysis.sobol`'s (the design, the indices, the storage), of one of
the functions of `hyper.analysis.sobolmodels`. ``--parameters`` and ``--range LOW HIGH``
(multiples of the baselines), ``--protocol``, ``--at H`` (N, or the CSA gain, at H hours
instead of the protocol's end) or a TOML file (``--problem``, `sobol.read_config`) set
SALib's problem; options win over the file.

The job (``run``) evaluates the rows in chunks (`hyper.analysis.chunks.run_chunks`), each
finished chunk written atomically to ``<output>/chunks/<digest>/``, the digest covering the
sample matrix and every setting, so a rerun skips finished chunks and never reuses chunks
of a different run. A SIGTERM stops it with the finished chunks kept (exit 143).
"""

from __future__ import annotations

import dataclasses
import sys
import time
from importlib.metadata import version
from pathlib import Path

import numpy as np
from mpi4py import MPI

from hyper.analysis import sobolmodels as models
from hyper.analysis.chunks import chunk_jobs, digest, idle_barrier, interrupted, remove_stale, run_chunks
from hyper.analysis.sobol import HIGH, LOW, MAX_SAMPLES, SAMPLES, analyze, design, read_config, sample, store
from hyper.analysis.sobolplot import output_label, save_figures
from hyper.commands import cli
from hyper.core import io, log
from hyper.core.log import info
from hyper.core.params import InputError, positive_hours
from hyper.model import protocols, signaling, surrogate
from hyper.model.protocols import Protocol
from hyper.runs import locks, provenance
from hyper.runs.driver import StopOnTerm
from hyper.runs.farm import summary_line


def parser() -> cli.Parser:
    p = cli.Parser("sobol", description="Sobol sensitivity analysis of N(480 h) under daily15 (MODEL.md §7), or\n"
                   "(--function csa-gain) of the 9-week CSA gain under mwf on the fast growth model,\n"
                   "farmed over MPI ranks (run under mpirun -n K). Writes sobol.h5, indices.csv and two\n"
                   "figures to --output.")
    p.add_argument("--samples", type=cli.integer(2, MAX_SAMPLES),
                   help=f"base samples N (a power of two balances the design); N (2D + 2) evaluations. "
                        f"Default: the --problem file's, else {SAMPLES}")
    p.add_argument("--problem", type=Path, metavar="F.toml",
                   help="the analysis in SALib's problem form (names, bounds) with function, protocol, at, "
                        "samples: a TOML file, or a study file's [sobol] table; options override it")
    p.add_argument("--parameters", nargs="+", metavar="NAME",
                   help="the parameters varied (SignalingParams fields; csa-gain also hill_n); the function's "
                        "own set by default")
    p.add_argument("--range", nargs=2, type=cli.number(), metavar=("LOW", "HIGH"), default=(LOW, HIGH),
                   help="each parameter uniform on [LOW, HIGH] x its baseline (unless the file gives bounds)")
    p.add_argument("--at", type=cli.positive("hours"), metavar="H",
                   help="the output's time (h): N, or the CSA gain, at H hours; the protocol's end by default")
    p.add_argument("--output", type=cli.output(folder=True), default="results/sobol", help="output folder")
    p.add_argument("--signaling-dt", type=cli.positive("hours"), default=0.05, metavar="H", help="largest RK4 step (h)")
    p.add_argument("--chunk", type=cli.integer(1, MAX_SAMPLES), default=10000, help="rows per job and per chunk file")
    p.add_argument("--seed", type=cli.integer(0, 2**32 - 2), default=1,
                   help="seed of the design; the bootstrap uses seed + 1")
    p.add_argument("--resamples", type=cli.integer(2, 10**5), default=100, help="bootstrap resamples")
    p.add_argument("--protocol", default=None, metavar="NAME|FILE",
                   help=f"a named protocol ({', '.join(protocols.NAMES)}) or a TOML protocol file; the output "
                   "is N (signaling; default daily15) or the CSA gain (csa-gain; default "
                   f"{models.GAIN_PROTOCOL}) at its end")
    p.add_argument("--on-failure", choices=("abort", "drop"), default="abort",
                   help="failed members: compute no indices (abort), or drop their base samples")
    p.add_argument("--backend", choices=("c", "numpy"), default="c",
                   help="RK4 backend: compiled (c) or signaling.integrate (numpy); same numbers")
    p.add_argument("--function", choices=models.FUNCTIONS,
                   help="the model: N(end) of the signaling model, CSA/CSA0 - 1 at the end on the fast "
                   "growth model (17 parameters: the rates, kM, kF, thetaM, thetaF, the Hill exponent), "
                   "or the Ishigami test function; signaling unless the --problem file says")
    p.add_argument("--geometry", choices=tuple(models.SECTION_GEOMETRIES), default=models.GAIN_GEOMETRY,
                   help="csa-gain: whose section factor turns N into CSA (surrogate.SECTION_FACTOR)")
    cli.progress_option(p)
    return p


def _settings(args, protocol: Protocol | None, prob: dict) -> dict:
    """Everything a chunk's outputs depend on besides the sample matrix."""
    own = models.settings(args.function, protocol, dt=args.signaling_dt, geometry=args.geometry)
    return own if args.function == "ishigami" else {**own, "problem": prob, "at": args.at}


def _check(args) -> tuple[Protocol | None, dict]:
    """The protocol and SALib's problem of the options and the --problem file (options win);
    completes ``args`` with the file's function, samples and time."""
    positive_hours(args.signaling_dt, "--signaling-dt", signaling.SMALLEST_DT)
    config = read_config(args.problem) if args.problem is not None else {}
    source = f"--problem {args.problem}: " if args.problem is not None else ""
    args.function = args.function or config.get("function", "signaling")
    args.samples = args.samples or config.get("samples", SAMPLES)
    names = args.parameters or config.get("names")
    bounds = config.get("bounds") if args.parameters is None else None
    try:
        prob = design(args.function, names, bounds, *args.range)
    except InputError as err:
        from_file = err.field == "bounds" or (err.field == "names" and not args.parameters)
        where = f"{source}{err.field}" if from_file else {"names": "--parameters", "range": "--range"}[err.field]
        raise InputError(f"{where}: {err.reason}") from None
    if args.function == "ishigami":
        if args.at is not None or args.protocol is not None:
            raise InputError("--at and --protocol: the Ishigami function has no time and no protocol")
        return None, prob
    default = models.GAIN_PROTOCOL if args.function == "csa-gain" else "daily15"
    text = args.protocol or config.get("protocol", default)
    found = protocols.from_option(text)
    args.protocol_text = str(Path(text).resolve()) if text not in protocols.NAMES else text
    if len(found) > 1:
        raise InputError(f"--protocol {text}: the analysis takes one protocol")
    args.at = args.at if args.at is not None else config.get("at")
    if args.at is not None:
        positive_hours(args.at, "--at")
        if args.at > found[0].end:
            raise InputError(f"--at: {args.at:g} h is after the end of {found[0].name} ({found[0].end:g} h)")
    return found[0], prob


def run(comm, args) -> int:
    protocol, prob = _check(args)
    # a second analysis writing the same folder would take the first one's chunks for stale
    with locks.hold(comm, [args.output]):
        return analyse(comm, args, protocol, prob)


def analyse(comm, args, protocol, prob) -> int:
    start = time.perf_counter()
    # io.versions() imports dolfinx, whose PETSc initialization is collective over COMM_WORLD:
    # done by rank 0 alone (when it writes the results) it would meet the other ranks' next
    # collective call and hang. All ranks import it here, together.
    io.versions()
    D = prob["num_vars"]
    # before sampling: SALib's sampler marks the problem dict it is given (rank 0's only)
    settings = _settings(args, protocol, prob)
    X = sample(dict(prob), args.samples, args.seed) if comm.rank == 0 else np.empty((args.samples * (2 * D + 2), D))
    idle_barrier(comm)
    comm.Bcast(X, root=0)
    key = digest(X, settings)
    if args.function != "ishigami" and args.backend == "c":
        # rank 0 builds the kernel; the other ranks then load it from the cache
        error = comm.bcast(signaling.c_backend_error() if comm.rank == 0 else None, root=0)
        if error is not None:
            log.error(comm, f"{error}; use --backend numpy")
            return cli.EXIT_SOME_FAILED
        signaling.c_backend_error()
    evaluate = models.evaluator(args.function, names=prob["names"], protocol=protocol, dt=args.signaling_dt,
                                geometry=args.geometry, backend=args.backend, at=args.at)
    chunks = args.output / "chunks"
    if comm.rank == 0:
        stale = remove_stale(chunks, key)
        if stale:
            info(comm, f"removed chunks of other settings: {', '.join(stale)}")
        if args.samples & (args.samples - 1):
            info(comm, f"note: {args.samples} base samples is not a power of 2; "
                       "the Sobol sequence is balanced only then")
    comm.barrier()
    info(comm, f"sobol: {args.function}, {D} parameters, N = {args.samples}, {X.shape[0]} evaluations in chunks of "
               f"{args.chunk} on {comm.size} rank(s), dt = {args.signaling_dt} h, backend {args.backend}, "
               f"digest {key}")
    t_eval, c_eval = time.perf_counter(), time.process_time()
    with StopOnTerm(comm) as stop:
        Y, results = run_chunks(comm, X, evaluate, chunks, key, args.chunk, label="sobol", stop=stop,
                                progress_every=args.progress_every)
    if comm.allreduce(stop(), op=MPI.LOR):
        left = sum(interrupted(r) for r in results)
        info(comm, f"stopped by SIGTERM: {left} chunk(s) not computed, the others saved in {chunks}; "
                   f"run the same command again to continue; exit status {cli.EXIT_TERMINATED}")
        idle_barrier(comm)
        return cli.EXIT_TERMINATED
    eval_wall = time.perf_counter() - t_eval
    # CPU time of all ranks: on a shared machine, cpu / (wall x ranks) is the share of their
    # cores the ranks actually got
    eval_cpu = comm.reduce(time.process_time() - c_eval, root=0)
    info(comm, summary_line(results))
    code = (_finish(args, prob, X, Y, results, protocol, key, (eval_wall, eval_cpu), start, comm.size)
            if comm.rank == 0 else 0)
    idle_barrier(comm)
    return int(comm.bcast(code, root=0))


def _finish(args, prob, X, Y, results, protocol, key, timing, start, ranks) -> int:
    """Rank 0: analysis, HDF5, CSV, figures, summary. Returns the exit code."""
    if Y is None:
        log.error(None, "some chunks failed (see above); rerun the same command to compute only those")
        return cli.EXIT_SOME_FAILED
    jobs = chunk_jobs(X.shape[0], args.chunk)
    computed = sum(r.status == "done" for r in results)
    evaluated_rows = sum(j.payload[1] - j.payload[0] for j, r in zip(jobs, results) if r.status == "done")
    failed = np.flatnonzero(~np.isfinite(Y))
    eval_wall, eval_cpu = timing
    rate = evaluated_rows / eval_wall if evaluated_rows else float("nan")
    share = eval_cpu / (eval_wall * ranks) if eval_wall > 0 else float("nan")
    info(None, f"evaluations: {X.shape[0]} ({evaluated_rows} computed now in {computed} chunks, "
               f"{eval_wall:.1f} s, {rate:.0f} evaluations/s, the ranks got {100 * share:.0f} % of "
               f"{ranks} core(s)), failed members: {failed.size}")
    if failed.size:
        for row in failed[:5]:
            info(None, "  failed: row " + str(row) + ", "
                       + ", ".join(f"{n}={v:.4g}" for n, v in zip(prob["names"], X[row])))
    try:
        ind = analyze(prob, Y, seed=args.seed, resamples=args.resamples, on_failure=args.on_failure)
    except ValueError as err:
        log.error(None, str(err))
        return cli.EXIT_SOME_FAILED
    if ind.dropped:
        info(None, f"dropped {ind.dropped} base samples with a failed member; indices from {ind.base_samples}")
    wall = time.perf_counter() - start
    attrs = {
        "model": f"Sobol indices of {models.OUTPUT[args.function]} (MODEL.md §7)",
        "function": args.function, "N": args.samples, "D": prob["num_vars"], "evaluations": X.shape[0],
        "seed": args.seed, "bootstrap_seed": args.seed + 1, "resamples": args.resamples, "conf_level": 0.95,
        "dt": args.signaling_dt, "backend": args.backend, "ranks": ranks, "chunk": args.chunk, "digest": key,
        "failures": int(failed.size), "on_failure": args.on_failure, "dropped_base_samples": ind.dropped,
        "base_samples_used": ind.base_samples, "wall_s": wall, "evaluation_wall_s": eval_wall,
        "evaluation_cpu_s": eval_cpu, "cpu_share": share,
        "evaluations_computed": evaluated_rows, "evaluations_per_s": rate, "version_SALib": version("SALib"),
        "protocol": protocol.name if protocol else "", "start_state": "baseline rest state (MODEL.md §1)",
        "at_h": (protocol.end if args.at is None else args.at) if protocol else float("nan"),
    }
    if args.function == "csa-gain":
        attrs.update(output="CSA/CSA0 - 1 at the protocol's end (surrogate.grow, Hill feedback, K = 1)",
                     geometry=args.geometry, section_factor=surrogate.section_factor(args.geometry),
                     hill_n_baseline=models.HILL_N)
    groups = {"bounds": {n: np.asarray(b, dtype=float) for n, b in zip(prob["names"], prob["bounds"])}}
    groups["settings"] = {"function": args.function, "signaling_dt": args.signaling_dt, "backend": args.backend,
                          "samples": args.samples, "seed": args.seed, "chunk": args.chunk,
                          "at_h": attrs["at_h"], "problem": args.problem.name if args.problem else ""}
    if protocol is not None:
        groups["protocol"] = protocol.to_attributes()
        groups["signaling"] = dataclasses.asdict(signaling.SignalingParams())
    # the [sobol] table of a study file that reruns this analysis (hyper sobol --problem FILE)
    config = {"function": args.function, "names": list(prob["names"]),
              "bounds": [[float(lo), float(hi)] for lo, hi in prob["bounds"]], "samples": args.samples}
    if protocol is not None:
        config["protocol"] = args.protocol_text
        if args.at is not None:  # else the protocol's end, which the digest records as "not given"
            config["at"] = args.at
    attrs["study"] = "\n".join(provenance.table("sobol", config))
    out = args.output
    store(out, prob, X, Y, failed, ind, attrs=attrs, groups=groups)
    save_figures(ind, output_label(args.function, protocol, args.at), out)
    info(None, ind.table())
    info(None, f"wall {wall:.1f} s; results: {out / 'sobol.h5'}, {out / 'indices.csv'}, {out / 'spread.png'}, "
               f"{out / 'indices.png'}")
    return 0


main = cli.entry(parser, run)

if __name__ == "__main__":
    sys.exit(main())
