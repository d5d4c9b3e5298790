"""python -m hyper.grow: the coupled growth model on one geometry for one or more protocols.

    python -m hyper.grow --geometry idealized --protocol mwf --output results/grow/idealized_mwf.h5
    python -m hyper.grow --geometry idealized --protocol all --output results/grow

Writes per run an HDF5 time series (t, csa_ratio, volume_ratio, kM, the signaling
states, Newton iterations) with parameters, protocol, settings and versions as
attributes, and an XDMF file of snapshots (growth displacement, det Ḡ, fibres) for
ParaView; with several protocols, the paper's Fig. 4C–E analog.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import dolfinx_solver  # noqa: F401  (must precede dolfinx and petsc4py)

import numpy as np
from mpi4py import MPI

from hyper import geometry as geo
from hyper import growth, io, protocols, signaling
from hyper.coupled import CoupledModel, GrowthSettings
from hyper.log import Progress, hms, info
from hyper.params import InputError, as_attributes

PAPER_PROTOCOLS = ("mwf", "every3days", "weekly")
SERIES = ("t", "csa_ratio", "volume_ratio", "kM", *signaling.STATES, "newton_iterations", "wall_s")


class Snapshots:
    """Output fields of a run on spaces XDMF can store (P1 and DG0), updated in place."""

    def __init__(self, model: CoupledModel, a0):
        from dolfinx import fem

        mesh = model.geometry.mesh
        self.model = model
        self.u = fem.Function(fem.functionspace(mesh, ("Lagrange", 1, (3,))), name="u")
        self.det = fem.Function(fem.functionspace(mesh, ("DG", 0)), name="detGbar")
        self.a0 = fem.Function(fem.functionspace(mesh, ("Lagrange", 1, (3,))), name="a0")
        self.a0.interpolate(a0)
        self._ncells = len(model.growth.cells)

    def update(self):
        self.u.interpolate(self.model.problem.u)
        self.det.x.array[: self._ncells] = self.model.growth.cell_det()
        self.det.x.scatter_forward()
        return self.u, self.det, self.a0


def run_one(comm, geometry_name: str, protocol, params, settings, *, snapshot_every: int, xdmf_path):
    """Run one coupled simulation; return the series and the model's metadata."""
    geometry = geo.load(geometry_name, comm)
    a0 = geo.fiber_field(geometry)
    model = CoupledModel(geometry, a0, protocol, params=params, settings=settings)
    snaps = Snapshots(model, a0)
    series = {name: [] for name in SERIES}
    progress = Progress(comm, protocol.end, f"{geometry_name}/{protocol.name}")
    start = time.perf_counter()
    with io.atomic_xdmf(comm, xdmf_path) as xdmf:
        xdmf.write_mesh(geometry.mesh)
        for report in model.run():
            wall = time.perf_counter() - start
            for name, value in zip(signaling.STATES, report.states):
                series[name].append(value)
            series["t"].append(report.t)
            series["csa_ratio"].append(report.csa_ratio)
            series["volume_ratio"].append(report.volume_ratio)
            series["kM"].append(report.kM)
            series["newton_iterations"].append(report.newton_iterations)
            series["wall_s"].append(wall)
            last = report.t >= protocol.end
            if report.step % snapshot_every == 0 or last:
                for f in snaps.update():
                    xdmf.write_function(f, report.t)
            progress.update(
                report.t,
                f"day {report.t / 24:5.1f}, CSA/CSA0 {report.csa_ratio:.5f}, V/V0 {report.volume_ratio:.5f}",
                force=last,
            )
    meta = {
        "geometry": geometry_name,
        "csa0_m2": model.csa0,
        "volume0_m3": model.volume0,
        "ranks": comm.size,
        "growth_steps": model.step,
        "wall_s": time.perf_counter() - start,
    }
    return {k: np.asarray(v) for k, v in series.items()}, meta


def figure(results: dict[str, dict], path: Path, data_dir: Path | None = None) -> None:
    """CSA, volume and kM against time for several protocols (the paper's Fig. 4C–E)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8), constrained_layout=True)
    for name, s in results.items():
        weeks = s["t"] / 168.0
        axes[0].plot(weeks, 100 * (s["csa_ratio"] - 1), label=name)
        axes[1].plot(weeks, 100 * (s["volume_ratio"] - 1), label=name)
        axes[2].plot(weeks, s["kM"], label=name)
    if data_dir is not None and (data_dir / "defreitas.csv").is_file():
        data = np.genfromtxt(data_dir / "defreitas.csv", delimiter=",", names=True)
        axes[0].plot(data["week"], 100 * (data["csa"] / data["csa"][0] - 1), "ko", ms=4,
                     label="DeFreitas 2011 (mwf)")
    axes[0].set_ylabel("CSA change (%)")
    axes[1].set_ylabel("volume change (%)")
    axes[2].set_ylabel("kM (1/h)")
    for ax in axes:
        ax.set_xlabel("time (weeks)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=150)
    plt.close(fig)


def parse_args(argv):
    p = argparse.ArgumentParser(prog="python -m hyper.grow", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--geometry", default="idealized", help="geometry id (idealized, cylinder, BFLH_VHF_Left, …)")
    p.add_argument("--protocol", default="mwf",
                   help=f"named protocol ({', '.join(protocols.NAMES)}) or 'all' for {', '.join(PAPER_PROTOCOLS)}")
    p.add_argument("--protocol-file", type=Path, help="TOML protocol file (replaces --protocol)")
    p.add_argument("--params", type=Path, help="TOML file overriding signaling parameters")
    p.add_argument("--output", type=Path, default=Path("results/grow"),
                   help="an .h5 file (one protocol) or a folder (default results/grow)")
    p.add_argument("--growth-dt", type=float, default=GrowthSettings.growth_dt, help="growth step Δtg (h)")
    p.add_argument("--signaling-dt", type=float, default=GrowthSettings.signaling_dt, help="RK4 step (h)")
    p.add_argument("--feedback", choices=growth.FEEDBACK_LAWS, default="hill")
    p.add_argument("--skip-sessions", action="store_true",
                   help="no growth during sessions (the original code's choice)")
    p.add_argument("--fe-stress", action="store_true",
                   help="use P = Fe S (the original code) instead of the consistent det(Fg) Fe S Fg⁻ᵀ")
    p.add_argument("--snapshot-every", type=int, default=10, help="XDMF snapshot every K growth steps")
    p.add_argument("--plot", type=Path, help="figure path (default: next to the output)")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    comm = MPI.COMM_WORLD
    try:
        if args.geometry not in geo.GEOMETRIES:
            raise InputError(f"--geometry: unknown geometry {args.geometry!r}; known: {', '.join(geo.GEOMETRIES)}")
        if args.protocol_file is not None:
            runs = [protocols.load(args.protocol_file)]
        elif args.protocol == "all":
            runs = [protocols.named(n) for n in PAPER_PROTOCOLS]
        else:
            runs = [protocols.named(args.protocol)]
        params = signaling.load_params(args.params) if args.params else signaling.SignalingParams()
        settings = GrowthSettings(
            growth_dt=args.growth_dt,
            signaling_dt=args.signaling_dt,
            feedback=args.feedback,
            grow_during_sessions=not args.skip_sessions,
            consistent_stress=not args.fe_stress,
        )
        if args.snapshot_every < 1:
            raise InputError(f"--snapshot-every must be a positive integer, got {args.snapshot_every}")
        single_file = args.output.suffix == ".h5"
        if single_file and len(runs) > 1:
            raise InputError("--output: several protocols need a folder, not an .h5 file")
    except InputError as err:
        if comm.rank == 0:
            print(f"error: {err}", file=sys.stderr)
        return 2

    results = {}
    for protocol in runs:
        h5 = args.output if single_file else args.output / f"{args.geometry}_{protocol.name}.h5"
        xdmf = h5.with_name(h5.stem + "_fields.xdmf")
        series, meta = run_one(comm, args.geometry, protocol, params, settings,
                               snapshot_every=args.snapshot_every, xdmf_path=xdmf)
        if comm.rank == 0:
            io.write_series(
                h5, series, attrs=meta,
                groups={"signaling": as_attributes(params), "protocol": protocol.to_attributes(),
                        "settings": dataclasses.asdict(settings)},
            )
        info(comm, f"{protocol.name}: CSA/CSA0 {series['csa_ratio'][-1]:.5f}, V/V0 "
                   f"{series['volume_ratio'][-1]:.5f} in {hms(meta['wall_s'])}; wrote {h5} and {xdmf}")
        results[protocol.name] = series
    if comm.rank == 0:
        plot = args.plot or (args.output.with_suffix(".png") if single_file
                             else args.output / f"{args.geometry}_growth.png")
        data_dir = Path(__file__).resolve().parents[2] / "data"
        figure(results, plot, data_dir if data_dir.is_dir() else None)
        print(f"figure: {plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
