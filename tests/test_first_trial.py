"""What a first trial tripped over (issue 18, item 9), each fixed and kept fixed."""

import os
import subprocess
import sys

import h5py
import numpy as np
import pytest

from hyper.analysis import cohortplot
from hyper.commands import cli
from hyper.commands import cohort as cohort_job
from hyper.model import protocols, signaling
from hyper.runs import plot


def test_an_h5_job_refuses_a_png_output_and_writes_nothing(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert cli.main(["signaling", "--output", "a.png"]) == cli.EXIT_INPUT
    assert "--output a.png: expected an .h5 file or a folder, got a .png file" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_contraction_names_its_default_output_after_the_geometry(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli.main(["contraction", "--geometry", "cylinder", "--steps", "1", "--quiet"]) == 0
    out = tmp_path / "results" / "contraction"
    assert sorted(p.name for p in out.iterdir()) == ["cylinder.h5", "cylinder.png", "cylinder_fields.h5",
                                                    "cylinder_fields.xdmf"]
    with h5py.File(out / "cylinder.h5") as f:
        assert f["end_force"].attrs["units"] == "N" and f["settings"].attrs["steps"] == 1
        assert f["material"].attrs["sigma_act"] == 3.0e5 and len(f.attrs["mesh_sha256"]) == 64


def test_one_colour_per_protocol_name_in_every_figure():
    assert plot.protocol_colour("mwf") == "#c0392b" and plot.protocol_colour("weekly") == "#229954"
    # another name has one colour whatever its place, none of the built-in ones, and the same
    # in every process (a colour from Python's salted hash() would differ between the ranks'
    # and the runs' figures)
    assert plot.protocol_colour("tue-fri") not in plot.PROTOCOL_COLOURS.values()
    code = "from hyper.runs import plot; print(plot.protocol_colour('tue-fri'))"
    elsewhere = {subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                                env={**os.environ, "PYTHONHASHSEED": seed}).stdout.strip() for seed in ("1", "2")}
    assert elsewhere == {plot.protocol_colour("tue-fri")}
    from hyper.model.signaling.integrators import run
    from hyper.runs.signalingplot import figure_protocols

    runs = {"weekly": protocols.named("weekly"), "mwf": protocols.named("mwf")}
    results = {n: run(signaling.SignalingParams(), p, 0.1, 6.0) for n, p in runs.items()}
    fig = figure_protocols(results, runs, signaling.SignalingParams())
    first = fig.axes[0]
    assert [line.get_color() for line in first.lines] == ["#229954", "#c0392b"]
    plot.pyplot().close(fig)


def test_the_growth_figure_has_one_time_range(tmp_path):
    t = np.array([0.0, 168.0, 336.0])
    results = {"short": {"t": t, "csa_ratio": 1 + t / 1e4, "volume_ratio": 1 + t / 1e4, "kM": 0.01 + 0 * t}}
    plt = plot.pyplot()
    saved = []
    original = plot.save
    try:
        plot.save = lambda fig, path, **kw: saved.append([ax.get_xlim() for ax in fig.axes]) or original(fig, path)
        plot.growth_series(results, tmp_path / "g.png")
    finally:
        plot.save = original
    assert saved[0] == [(-0.04, 2.04)] * 3
    plt.close("all")


def test_the_ratio_figure_says_dots_only_with_several_members(tmp_path, monkeypatch):
    titles = []
    monkeypatch.setattr(plot, "save", lambda fig, path, **kw: titles.extend(ax.get_title() for ax in fig.axes))
    row = {"geometry": "cylinder", "muscle": "", "subject": "", "side": "", "protocol": "weekly", "status": "done",
           "final_csa_ratio": 1.03, "final_volume_ratio": 1.031}
    cohortplot.ratio_figure([row], tmp_path / "r.png")
    assert titles and not any("dots" in t for t in titles)


def test_a_shape_geometry_outside_the_cohort_is_refused(tmp_path, capsys):
    code = cli.main(["cohort", "--geometries", "cylinder", "--plot-geometry", "idealized", "--output",
                     str(tmp_path / "c")])
    assert code == cli.EXIT_INPUT
    assert "--plot-geometry idealized: not one of --geometries (cylinder)" in capsys.readouterr().err
    args = cohort_job.parser().parse_args(["--geometries", "cylinder", "idealized"])
    from mpi4py import MPI

    cohort_job.check(args, MPI.COMM_SELF)
    assert args.plot_geometry == "cylinder"


@pytest.mark.parametrize("name", ["mwf", "tue-fri"])
def test_protocol_colour_is_a_colour(name):
    from matplotlib.colors import is_color_like

    assert is_color_like(plot.protocol_colour(name))
