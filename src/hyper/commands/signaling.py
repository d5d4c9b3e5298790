"""hyper signaling: the signaling ODEs alone (no mesh) for exercise protocols.

Writes one HDF5 series per protocol (t and the five states, with the parameters, the
protocol and the settings as attributes) and, with --plot, the Fig. 3A–E analog.

    hyper signaling --protocol all --output results/signaling --plot results/signaling/protocols.png
    hyper signaling --protocol my_protocol.toml --params my_params.toml --output mine.h5
"""

from __future__ import annotations

import sys
from pathlib import Path

from hyper.commands import cli
from hyper.core import io, log
from hyper.core.collective import on_rank0
from hyper.core.params import as_attributes, positive_hours
from hyper.model import protocols
from hyper.model.signaling.integrators import SMALLEST_DT, SMALLEST_SAMPLE, SignalingError, first_day
from hyper.model.signaling.integrators import run as series
from hyper.model.signaling.params import load_params
from hyper.runs import locks, plot
from hyper.runs.presets import method_option
from hyper.runs.signalingplot import figure_protocols


def parser() -> cli.Parser:
    p = cli.Parser("signaling", description=__doc__)
    p.add_argument("--protocol", default="mwf", metavar="NAME|FILE", reads=True,
                   help=f"a named protocol ({', '.join(protocols.NAMES)}), 'all' for {' '.join(protocols.PAPER)}, "
                   "or a TOML protocol file")
    p.add_argument("--params", type=Path, metavar="F.toml", reads=True,
                   help="parameter overrides, keys as in MODEL.md's table")
    p.add_argument("--signaling-dt", type=cli.positive("hours"), default=0.05, metavar="H",
                   help="largest step (h), of either method")
    method_option(p)
    p.add_argument("--sample-every", type=cli.positive("hours"), default=0.5, metavar="H", help="output sampling (h)")
    p.add_argument("--output", type=cli.output(), default="results/signaling",
                   help="an .h5 file (one protocol) or a folder that gets <protocol>.h5 per protocol")
    p.add_argument("--plot", type=cli.output(folder=False, suffixes=(".png",)), metavar="F.png",
                   help="write the figure here")
    return p


def write(path: Path, series: dict, params, protocol, dt: float, sample_every: float, groups=None,
          method: str = "rk4") -> None:
    """A signaling result: the series, the integrator's settings, parameters and protocol
    (and any other attribute ``groups``, e.g. a fidelity choice)."""

    io.write_series(
        path, series,
        attrs={"model": "signaling (MODEL.md §1)", "integrator": "RK4" if method == "rk4" else "RK45",
               "signaling_method": method, "dt": dt, "sample_every": sample_every,
               "N_final": float(series["N"][-1])},
        groups={"signaling": as_attributes(params), "protocol": protocol.to_attributes(),
                "settings": {"integrator": "RK4", "signaling_dt": dt, "sample_every": sample_every}, **(groups or {})},
    )


def answer(comm, runs: list, paths: list[Path], params, dt: float, sample_every: float, groups=None,
           method: str = "rk4") -> dict:
    """Integrate each protocol of ``runs`` with ``method`` and write its result to the path
    beside it; the series by name. All are integrated before any is written: a failure
    writes nothing."""
    results = {protocol.name: series(params, protocol, dt, sample_every, method) for protocol in runs}
    for protocol, path in zip(runs, paths):
        write(path, results[protocol.name], params, protocol, dt, sample_every, groups, method)
        log.info(comm, f"{protocol.name}: N({protocol.end:g} h) = {results[protocol.name]['N'][-1]:.6f}; "
                       f"no mesh built -> {path}")
    return results


def run(comm, args) -> int:
    dt = positive_hours(args.signaling_dt, "--signaling-dt", SMALLEST_DT)
    sample_every = positive_hours(args.sample_every, "--sample-every", SMALLEST_SAMPLE)
    params = load_params(args.params)
    runs = protocols.from_option(args.protocol)
    paths = io.result_paths(args.output, [p.name for p in runs])

    def work():
        method = args.signaling_method
        insets = {p.name: first_day(params, p, dt, method=method) for p in runs}
        results = answer(comm, runs, paths, params, dt, sample_every, method=method)
        if args.plot is not None:
            fig = figure_protocols(results, {p.name: p for p in runs}, params, insets)
            log.info(comm, f"wrote {plot.save(fig, args.plot, dpi=130)}")

    # The ODEs of a few protocols take seconds: rank 0 alone integrates and writes them.
    try:
        with locks.hold(comm, paths):
            on_rank0(comm, work)
    except SignalingError as err:
        log.error(comm, str(err))
        return cli.EXIT_FAILED
    return cli.EXIT_OK


main = cli.entry(parser, run)

if __name__ == "__main__":
    sys.exit(main())
