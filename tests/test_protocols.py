"""Protocols as data: the named protocols of MODEL.md §2, periods, TOML files, and every rejection."""

import math

import numpy as np
import pytest

from hyper.core import io
from hyper.core.params import InputError
from hyper.model.protocols import NAMES, Protocol, Session, load, named, resolve


@pytest.mark.parametrize(
    "name, count, first, duration, intensity, end",
    [
        ("mwf", 24, 168.0, 1.0, 0.8, 1512.0),
        ("weekly", 8, 168.0, 1.0, 0.8, 1512.0),
        ("every3days", 18, 168.0, 4.0, 0.2, 1512.0),
        ("daily15", 15, 0.0, 1.0, 0.8, 480.0),
        ("rest", 0, None, None, None, 1512.0),
    ],
)
def test_named_protocols_match_the_model(name, count, first, duration, intensity, end):
    p = named(name)
    assert p.name == name and p.end == end and len(p.sessions) == count
    if count:
        assert p.sessions[0].start == first
        assert {s.duration for s in p.sessions} == {duration}
        assert {s.intensity for s in p.sessions} == {intensity}
        # sessions start on whole hours
        assert all(s.start == math.floor(s.start) for s in p.sessions)


def test_session_times_of_the_paper_protocols():
    week = 168.0
    assert named("mwf").starts.tolist() == [week + week * w + d for w in range(8) for d in (0, 48, 96)]
    assert named("weekly").starts.tolist() == [week * (k + 1) for k in range(8)]
    assert named("every3days").starts.tolist() == [week + 72 * k for k in range(18)]
    assert named("daily15").starts.tolist() == [24.0 * k for k in range(15)]
    assert named("mwf").sessions[-1].end == 1441.0


def test_names_are_exactly_the_named_protocols():
    assert NAMES == ("mwf", "weekly", "every3days", "daily15", "rest")
    for name in NAMES:
        assert named(name).name == name


@pytest.mark.parametrize("name", NAMES)
def test_periods_cover_the_span_without_gaps(name):
    p = named(name)
    periods = p.periods()
    assert periods[0][0] == 0.0 and periods[-1][1] == p.end
    for (a0, a1, _), (b0, _, _) in zip(periods[:-1], periods[1:]):
        assert a1 == b0 and a0 < a1
    sessions = [(a, b) for a, b, on in periods if on]
    assert sessions == [(s.start, s.end) for s in p.sessions]
    # rest periods never follow each other
    flags = [on for _, _, on in periods]
    assert not any(not x and not y for x, y in zip(flags[:-1], flags[1:]))


def test_periods_leave_out_empty_gaps():
    p = Protocol((Session(0.0, 1.0, 0.5), Session(1.0, 2.0, 0.7)), 3.0)
    assert p.periods() == [(0.0, 1.0, True), (1.0, 3.0, True)]
    assert Protocol((), 5.0).periods() == [(0.0, 5.0, False)]


def test_attributes_round_trip_through_hdf5(tmp_path):
    import h5py

    for name in ("mwf", "rest"):
        attrs = named(name).to_attributes()
        path = io.write_series(tmp_path / f"{name}.h5", {"t": [0.0]}, groups={"protocol": attrs})
        with h5py.File(path) as f:
            stored = dict(f["protocol"].attrs)
        assert stored["name"] == name and stored["end"] == 1512.0
        np.testing.assert_array_equal(stored["starts"], named(name).starts)
        np.testing.assert_array_equal(stored["durations"], [s.duration for s in named(name).sessions])


def _protocol(*sessions, end=100.0):
    return Protocol(tuple(Session(*s) for s in sessions), end)


@pytest.mark.parametrize(
    "sessions, end, message",
    [
        (((0, 2, 0.5), (1, 1, 0.5)), 10,
         r"session 1: overlaps session 0: it starts at 1 h, before session 0 ends \(2 h\)"),
        (((5, 1, 0.5), (0, 1, 0.5)), 10, r"session 1: sessions must be sorted by start"),
        (((0, 1, 0.5), (2, 0, 0.5)), 10, r"session 1: duration must be > 0 h, got 0"),
        (((0, -1, 0.5),), 10, r"session 0: duration must be > 0 h, got -1"),
        (((0, 1, 1.5),), 10, r"session 0: intensity must lie in \[0, 1\], got 1.5"),
        (((0, 1, -0.1),), 10, r"session 0: intensity must lie in \[0, 1\], got -0.1"),
        (((0, 1, float("nan")),), 10, r"session 0: intensity must be a finite number"),
        (((float("inf"), 1, 0.5),), 10, r"session 0: start must be a finite number"),
        (((-1, 1, 0.5),), 10, r"session 0: start must be >= 0 h"),
        (((0, 1, 0.5), (5, 3, 0.5)), 7, r"end \(7 h\) lies before the end of the last session 1 \(8 h\)"),
        ((), 0, r"end must be a finite number > 0 h"),
        ((), float("nan"), r"end must be a finite number > 0 h"),
    ],
)
def test_invalid_protocols_are_rejected_with_the_session_named(sessions, end, message):
    with pytest.raises(InputError, match=message):
        _protocol(*sessions, end=end)


def test_unknown_name_lists_the_known_ones():
    with pytest.raises(InputError, match=r"unknown protocol 'monday'; known: mwf, weekly, every3days, daily15, rest"):
        named("monday")
    with pytest.raises(InputError, match=r"unknown protocol 'monday'.*mwf, weekly"):
        resolve("monday")


TOML = """
name = "two"
end = 360.0
[[session]]
start = 0.0
duration = 1.0
intensity = 0.8
[[session]]
start = 48
duration = 2.5
intensity = 0.4
"""


def test_load_from_toml(tmp_path):
    path = tmp_path / "two.toml"
    path.write_text(TOML)
    p = load(path)
    assert p == Protocol((Session(0.0, 1.0, 0.8), Session(48.0, 2.5, 0.4)), 360.0, "two")
    assert resolve(str(path)) == p
    # the name defaults to the file's stem
    (tmp_path / "mine.toml").write_text("end = 10.0\n")
    assert load(tmp_path / "mine.toml") == Protocol((), 10.0, "mine")


@pytest.mark.parametrize(
    "text, message",
    [
        ("end = 10\n[[session]]\nstart = 0\nduration = 1\n", r"session 0: missing intensity"),
        ("end = 10\nspeed = 3\n", r"unknown key\(s\) speed; known: end, name, repeat, session"),
        ("end = 10\n[[session]]\nstart = 0\nduration = 1\nintensity = 0.5\nrpm = 2\n",
         r"session 0: unknown key\(s\) rpm"),
        ("end = 10\n[[session]]\nstart = 0\nduration = 1\nintensity = 'high'\n",
         r"session 0: intensity: expected a number"),
        ("end = 10\n[[session]]\nstart = 0\nduration = 1\nintensity = 2\n",
         r"session 0: intensity must lie in \[0, 1\]"),
        ("end = 0.5\n[[session]]\nstart = 0\nduration = 1\nintensity = 0.5\n",
         r"end \(0.5 h\) lies before the end of the last session 0"),
        ("[[session]]\nstart = 0\nduration = 1\nintensity = 0.5\n", r"missing 'end'"),
        ("end = 10\nsession = 3\n", r"'session' must be an array of tables"),
        ("end = = 10\n", r"malformed TOML"),
    ],
)
def test_bad_toml_names_the_file_and_the_field(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(InputError, match=message) as err:
        load(path)
    assert str(path) in str(err.value)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        load(tmp_path / "none.toml")


def test_from_option_names_a_protocol_all_or_a_file(tmp_path):
    from hyper.model.protocols import PAPER, from_option

    assert from_option("weekly") == [named("weekly")]
    assert [p.name for p in from_option("all")] == list(PAPER) == ["mwf", "every3days", "weekly"]
    path = tmp_path / "two.toml"
    path.write_text(TOML)
    assert from_option(str(path)) == [load(path)]
    with pytest.raises(InputError, match=r"--plan: unknown protocol 'monday'; known: mwf, .*'all'"):
        from_option("monday", "--plan")
    with pytest.raises(InputError, match=r"absent.toml: no such file"):
        from_option(str(tmp_path / "absent.toml"))
