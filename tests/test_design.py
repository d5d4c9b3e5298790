"""hyper design: the least-load protocol reaching a target gain, on the ODE growth model."""

import dataclasses
import json

import h5py
import numpy as np
import pytest

from hyper.analysis import design
from hyper.commands import cli
from hyper.core import io
from hyper.core.params import InputError
from hyper.model import signaling, surrogate
from hyper.model.protocols import WEEK, load

SHORT = ["--target", "3", "--week", "3", "--geometry", "cylinder", "--sessions", "1", "3", "--weekdays", "mon", "wed",
         "fri", "--duration", "0.5", "2"]


def constraints(**kw):
    base = dict(target=0.03, week=3, sessions=(1, 3), weekdays=("mon", "wed", "fri"), intensity=(0.05, 1.0),
                duration=(0.5, 2.0))
    return design.Constraints(**{**base, **kw})


def gain_of(protocol, params=None, factor=1.0):
    params = signaling.SignalingParams() if params is None else params
    return float(surrogate.grow(params, protocol, [protocol.end], factor=factor).csa_ratio[0] - 1.0)


def test_the_design_reaches_the_target_with_the_least_load_of_the_grid():
    c = constraints()
    candidates = design.evaluate(c, signaling.SignalingParams())
    best = design.choose(candidates, c.target, "load")
    assert best.gain >= c.target
    assert all(x.load >= best.load - 1e-12 for x in candidates if x.gain >= c.target)
    # the batch gives each candidate its own run's gain
    assert gain_of(best.rule(3).protocol("d")) == pytest.approx(best.gain, abs=1e-12)
    fewest = design.choose(candidates, c.target, "sessions")
    assert fewest.gain >= c.target and fewest.sessions_per_week == min(x.sessions_per_week for x in candidates
                                                                       if x.gain >= c.target)


def test_the_pareto_front_never_loses_gain_for_more_load():
    candidates = design.evaluate(constraints(), signaling.SignalingParams())
    front = design.front(candidates)
    loads = [c.load for c in front]
    gains = [c.gain for c in front]
    assert len(front) > 3 and np.all(np.diff(loads) > 0) and np.all(np.diff(gains) > 0)
    # nothing off the front does better for its load
    for c in candidates:
        on = [f for f in front if f.load <= c.load + 1e-12]
        assert on and on[-1].gain >= c.gain


def test_sessions_are_spread_over_the_allowed_weekdays():
    assert design.spread(3, design.WEEKDAYS) == ("mon", "wed", "fri")
    assert design.spread(2, ("mon", "tue", "thu")) == ("mon", "thu")


@pytest.mark.parametrize("kw, message", [
    (dict(sessions=(4, 5)), r"at least 4 a week, but only 3 weekday"),
    (dict(sessions=(3, 2)), r"--sessions: the least \(3\) is more than the most \(2\)"),
    (dict(intensity=(0.9, 0.5)), r"--intensity: the least"),
    (dict(intensity=(0.31, 0.34)), r"no intensity of the grid"),
    (dict(duration=(0.1, 0.2)), r"no duration of the grid"),
    (dict(target=0.0), r"--target must be a gain > 0"),
])
def test_contradictory_constraints_are_refused(kw, message):
    with pytest.raises(InputError, match=message):
        constraints(**kw)


def test_the_job_writes_a_design_grow_runs_and_the_coupled_check_agrees(tmp_path, capsys):
    out = tmp_path / "d"
    assert cli.main(["design", *SHORT, "--output", str(out)]) == cli.EXIT_OK
    result = json.loads((out / "design.json").read_text())
    protocol = load(out / "design.toml")
    assert protocol.end == 3 * WEEK
    assert gain_of(protocol) >= 0.03 and result["design"]["gain_pct"] >= 3
    assert abs(result["check"]["difference_pp"]) <= 0.05
    assert (out / "design.png").is_file()
    grown = tmp_path / "g.h5"
    assert cli.main(["grow", "--geometry", "cylinder", "--protocol", str(out / "design.toml"),
                     "--output", str(grown)]) == cli.EXIT_OK
    with h5py.File(grown) as f:
        # grow chooses its own RK4 step (the design's check ran at the design's): within 0.01 pp
        assert f["csa_ratio"][-1] - 1.0 == pytest.approx(result["check"]["coupled_gain_pct"] / 100, abs=1e-4)


def test_a_posterior_design_reaches_the_target_with_the_probability(tmp_path):
    rng = np.random.default_rng(1)
    samples = np.exp(rng.normal(np.log(0.01), 0.3, 400))
    post = tmp_path / "posterior.h5"
    io.write_series(post, {"kM": samples}, attrs={"method": "bayes", "feedback": "hill"})
    out = tmp_path / "d"
    assert cli.main(["design", *SHORT, "--posterior", str(post), "--probability", "0.8", "--draws", "50",
                     "--no-check", "--output", str(out)]) == cli.EXIT_OK
    result = json.loads((out / "design.json").read_text())
    assert result["posterior"]["draws"] == 50 and result["probability"] == 0.8
    protocol = load(out / "design.toml")
    params = signaling.SignalingParams()
    reached = np.array([gain_of(protocol, dataclasses.replace(params, kM=float(k))) >= 0.03 for k in samples])
    assert reached.mean() >= 0.75  # 50 of the 400 drawn: P = 0.8 up to their sampling error
    # a surer design needs at least the load of the point design
    point = tmp_path / "p"
    assert cli.main(["design", *SHORT, "--no-check", "--output", str(point)]) == cli.EXIT_OK
    assert result["design"]["load"] >= json.loads((point / "design.json").read_text())["design"]["load"] - 1e-12


def test_an_unreachable_target_names_the_most_reachable_gain_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "d"
    argv = ["design", "--target", "50", "--week", "3", "--geometry", "cylinder", "--no-check", "--output", str(out)]
    assert cli.main(argv) == cli.EXIT_INPUT
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: --target 50 %: out of reach"), lines
    assert "the most reachable gain is" in lines[0]
    assert not out.exists()
