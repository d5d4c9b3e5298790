"""hyper predict: posterior samples of kM through the coupled model on the farm, against the ODE growth model."""

import json
import re
from pathlib import Path

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from hyper.analysis import predictive
from hyper.commands import cli
from hyper.core import io
from hyper.core.params import InputError
from hyper.runs.checkpoint import file_digest

# two sessions in four days: four growth steps of the cylinder, about a second a run
PROTOCOL = """
name = "short"
end = 96.0
[[session]]
start = 0.0
duration = 1.0
intensity = 0.8
[[session]]
start = 48.0
duration = 1.0
intensity = 0.8
"""
KM = [0.008, 0.01, 0.012, 0.015, 0.02]


@pytest.fixture
def inputs(tmp_path):
    (tmp_path / "short.toml").write_text(PROTOCOL)
    # the fit's geometry is the cylinder, whose section factor is exactly 1 (compatible growth)
    io.write_series(tmp_path / "posterior.h5", {"kM": np.array(KM)},
                    attrs={"method": "bayes", "geometry": "cylinder", "feedback": "hill", "signaling_dt": 0.05})
    return tmp_path


def argv(d, *more):
    return ["predict", "--posterior", str(d / "posterior.h5"), "--geometry", "cylinder", "--protocol",
            str(d / "short.toml"), "--samples", "4", "--output", str(d / "out"), *more]


def test_the_gains_follow_kM_the_interval_holds_the_median_and_a_rerun_skips_the_runs(inputs, capsys):
    assert cli.main(argv(inputs)) == cli.EXIT_OK
    out = inputs / "out"
    summary = json.loads((out / "predictive.json").read_text())
    kM = np.array(summary["kM"])
    assert len(kM) == 4 and set(kM) <= set(KM) and np.all(np.diff(kM) > 0)
    csa = np.array(summary["per_sample"]["csa_gain_pct"])
    volume = np.array(summary["per_sample"]["volume_gain_pct"])
    assert np.all(np.diff(csa) > 0) and np.all(np.diff(volume) > 0) and csa[0] > 0
    for measure in ("csa_gain_pct", "volume_gain_pct"):
        c = summary["coupled"][measure]
        assert c["low"] <= c["median"] <= c["high"] and c["low"] < c["high"]
        values = np.array(summary["per_sample"][measure])
        assert c["median"] == pytest.approx(np.median(values))
        assert values.min() <= c["low"] and c["high"] <= values.max()
    # on the cylinder the ODE growth model is the coupled model's growth exactly, up to the solver
    for measure in ("csa", "volume"):
        error = summary["surrogate_error"][measure]
        assert 0 <= error["mean_abs_pp"] <= error["max_abs_pp"] < 1e-4
    with h5py.File(out / "predictive.h5") as f:
        assert f.attrs["posterior_sha256"] == file_digest(inputs / "posterior.h5")
        assert np.array_equal(f["kM"][()], kM)
        assert np.allclose(f["csa_gain_pct"][()], csa)
        assert f["summary"].attrs["coupled_csa_gain_pct_median"] == pytest.approx(summary["coupled"]["csa_gain_pct"]
                                                                                  ["median"])
    assert (out / "predictive.png").is_file()
    capsys.readouterr()
    first = (out / "runs" / "sample00.h5").stat().st_mtime_ns
    assert cli.main(argv(inputs)) == cli.EXIT_OK
    assert "0 to run, 4 skipped (done before)" in capsys.readouterr().out
    assert (out / "runs" / "sample00.h5").stat().st_mtime_ns == first
    assert json.loads((out / "predictive.json").read_text())["per_sample"] == summary["per_sample"]


def test_the_draw_is_seeded_without_replacement_and_sorted():
    kM = np.arange(1, 101) * 1e-4
    a, b = predictive.draw(kM, 8, 3), predictive.draw(kM, 8, 3)
    assert np.array_equal(a, b) and len(set(a)) == 8 and np.all(np.diff(a) > 0)
    assert not np.array_equal(a, predictive.draw(kM, 8, 4))
    with pytest.raises(InputError, match="holds only 100 samples"):
        predictive.draw(kM, 101, 0)


@pytest.mark.parametrize("change, message", [
    (["--samples", "1"], r"error: argument --samples: expected an integer in \[2, 1000\], got 1"),
    (["--samples", "9"], "error: --samples 9: the posterior holds only 5 samples"),
    (["--geometry", "femur"], "error: --geometry: unknown geometry 'femur'"),
    (["--posterior", "missing.h5"], "error: --posterior missing.h5: no such file"),
])
def test_bad_input_is_one_error_line_and_nothing_is_written(inputs, capsys, change, message, monkeypatch):
    monkeypatch.chdir(inputs)
    words = argv(inputs)
    for option, value in zip(change[::2], change[1::2]):
        words[words.index(option) + 1] = value
    assert cli.main(words) == cli.EXIT_INPUT
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and re.match(message, lines[0]), lines
    assert not (inputs / "out").exists()


def test_a_file_without_kM_samples_is_refused(inputs):
    io.write_series(inputs / "other.h5", {"kF": np.array([0.01, 0.02])})
    with pytest.raises(InputError, match="no kM samples"):
        predictive.read_posterior(inputs / "other.h5")


@pytest.mark.mpi
def test_mpi_two_groups_of_one_and_one_group_of_two_give_the_same_gains(tmp_path):
    comm = MPI.COMM_WORLD
    folder = Path(comm.bcast(str(tmp_path) if comm.rank == 0 else None, root=0))
    if comm.rank == 0:
        (folder / "short.toml").write_text(PROTOCOL)
        io.write_series(folder / "posterior.h5", {"kM": np.array(KM)}, attrs={"geometry": "cylinder"})
    comm.barrier()
    gains = []
    for ranks, name in (("1", "groups"), ("2", "whole")):
        words = argv(folder, "--ranks-per-job", ranks)
        words[words.index("--output") + 1] = str(folder / name)
        assert cli.main(words) == cli.EXIT_OK
        gains.append(json.loads((folder / name / "predictive.json").read_text())["per_sample"]["csa_gain_pct"])
    # the same runs on one rank or split over two: the same growth up to the Newton tolerance
    assert np.allclose(gains[0], gains[1], rtol=0, atol=1e-6)
