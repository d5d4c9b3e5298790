"""hyper bench growthlaws: its parts are the switches they say, on the scene they say (no runs)."""

import argparse

from hyper.commands.bench import growthlaws
from hyper.fem.coupled import GrowthSettings
from hyper.model import protocols


def args(**kw):
    base = dict(geometry="BFLH_VHF_Left", tau=growthlaws.TAU, stretch=1.1, quick=False, quick_end=336.0)
    return argparse.Namespace(**{**base, **kw})


def test_the_parts_are_named_once_the_default_first_and_each_a_valid_setting():
    assert growthlaws.PARTS[0].name == "default" and growthlaws.PARTS[0].settings == {}
    assert len(set(growthlaws.NAMES)) == len(growthlaws.NAMES)
    for part in growthlaws.PARTS:
        case = growthlaws.case_of(part, args())
        GrowthSettings(**case["settings"])  # refuses a field or value that is not one
        assert (case["stretch"] is not None) == part.stretched
    detraining = growthlaws.case_of(next(p for p in growthlaws.PARTS if p.name == "detraining"), args(tau=500.0))
    assert detraining["settings"] == {"detraining": 500.0}


def test_the_scene_is_mwf_its_sessions_stretched_or_cut():
    mwf = protocols.named("mwf")
    whole = growthlaws.scene({"stretch": None, "end": None})
    assert whole.sessions == mwf.sessions and whole.end == mwf.end and not whole.stretched
    stretched = growthlaws.scene({"stretch": 1.1, "end": None})
    assert [s.stretch for s in stretched.sessions] == [1.1] * len(mwf.sessions)
    assert [(s.start, s.duration, s.intensity) for s in stretched.sessions] == [
        (s.start, s.duration, s.intensity) for s in mwf.sessions]
    cut = growthlaws.scene({"stretch": None, "end": 336.0})
    assert cut.end == 336.0 and all(s.start < 336.0 for s in cut.sessions) and len(cut.sessions) == 3
