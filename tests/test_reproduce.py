"""hyper reproduce: the report's columns, and the original code's signaling number."""

import json

from mpi4py import MPI

from hyper.analysis import reproduce, reproducefigures, reproducereport
from hyper.commands.reproduce import main


def test_signaling_report(tmp_path):
    out = tmp_path / "rep"
    assert main(["--cases", "signaling", "--output", str(out), "--quiet"], comm=MPI.COMM_SELF) == 0
    text = (out / "REPORT.md").read_text()
    assert "| quantity | paper / original | hyper, original | hyper, default |" in text
    data = json.loads((out / "report.json").read_text())
    sig = data["signaling"]
    # MODEL.md §9: the original's RK45 gives ΔN = 0.091496 over 9 weeks of mwf, the converged 0.091245
    assert abs(sig["rk45-original"]["mwf"]["dN"] - reproduce.ORIGINAL_DN["mwf"]) < 1e-5
    assert abs(sig["rk4"]["mwf"]["dN"] - 0.091245) < 1e-5
    assert sig["rk45-original"]["mwf"]["N0"] == 1.000768
    row = next(line for line in text.splitlines() if line.startswith("| ΔN at 9 weeks, mwf"))
    assert row.split(" | ")[1:] == ["0.091496 (original)", f"{sig['rk45-original']['mwf']['dN']:.6f}",
                                    f"{sig['rk4']['mwf']['dN']:.6f} |"]
    assert "## Contraction" not in text  # only the cases asked for


def test_switches_make_the_original():
    """The original column sets every switch that applies to its geometry, and the quick
    anatomical one keeps the exact increment at one step per period."""
    settings, spec = (dict(p) for p in reproduce.original_fields("idealized", 1.0))
    assert spec == {"ends": "tags", "fibers": "original"}
    assert settings["growth_increment"] == "left-point" and settings["growth_dt"] == 1.0
    assert "csa_method" not in settings
    settings, spec = (dict(p) for p in reproduce.original_fields("BFLH_VHF_Left", 168.0, exact=True))
    # the paper's fibres of an anatomical mesh: its Stokes fibres (the default runs its Laplace fibres)
    assert spec == {"fibers": "original"}
    assert settings["csa_method"] == "box" and settings["growth_increment"] == "exact"
    built = reproduce.Case("k", "BFLH_VHF_Left", "mwf", tuple(settings.items())).run_spec().settings
    assert (built.signaling_method, built.grow_during_sessions, built.consistent_stress, built.growth_fields) == \
        ("rk45-original", False, False, "dg1")
    demo = reproduce.demo15()
    assert demo.end == 360.0 and [s.start for s in demo.sessions] == [0, 48, 96, 144, 192, 240, 288]


def test_a_sigterm_stops_the_farm_with_exit_143_and_no_report(tmp_path):
    """SIGTERM (Slurm's time limit): the running run stops with a checkpoint, no case
    starts, no report is written, exit 143 (a rerun resumes through run.execute, whose
    resume tests/test_reliability.py checks bit for bit)."""
    import os
    import signal
    import subprocess
    import sys

    out = tmp_path / "rep"
    proc = subprocess.Popen([sys.executable, "-m", "hyper.reproduce", "--cases", "idealized", "--quick",
                             "--output", str(out), "--progress-every", "1"], env={**os.environ, "OMP_NUM_THREADS": "1"},
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines = []
    for line in proc.stdout:  # the first growth run under way
        lines.append(line)
        if "% day" in line and "  0.0% day" not in line:
            break
        assert len(lines) < 200, "".join(lines)
    proc.send_signal(signal.SIGTERM)
    try:
        rest, _ = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 143, "".join(lines) + rest
    assert "stopped by SIGTERM" in rest and not (out / "REPORT.md").exists()
    kept = list((out / "runs").glob("*.ckpt.h5")) + list((out / "runs").glob("*.h5"))
    assert kept, "nothing kept"


def test_the_idealized_figure_shows_both_runs_and_the_mwf_data(tmp_path, monkeypatch):
    """The figure of the full and the quick report (a missing data set crashed the full one)."""
    import numpy as np

    t = np.linspace(0.0, 1512.0, 8)
    series = {"t": t, "csa_ratio": 1 + 0.08 * t / 1512, "volume_ratio": 1 + 0.08 * t / 1512, "kM": 0.01 - 1e-6 * t}
    read = []
    monkeypatch.setattr(reproducefigures.io, "is_complete", lambda p: True)
    monkeypatch.setattr(reproducefigures.io, "read_series", lambda p: read.append(p.name) or series)
    for quick in (True, False):
        path = reproducefigures.idealized_figure(tmp_path, tmp_path / f"fig{quick}.png", quick)
        assert path.stat().st_size > 10_000
    # the original column at its own step, 1 h, in --quick too
    assert read == ["idealized_mwf_default.h5", f"idealized_mwf_original_dt{reproduce.ORIGINAL_GROWTH_DT:g}.h5"] * 2


def test_quick_runs_the_idealized_original_at_its_own_step():
    """--quick runs the idealized original column at the original's Δtg = 1 h, and the
    left-point switch (whose effect is its step's error) against the default at 1 h too:
    no number of the idealized section comes from a 24-h step."""
    cases = {c.key: c for c in reproduce.idealized_cases(quick=True)}
    originals = [c for k, c in cases.items() if "_original" in k]
    assert len(originals) == 2 and all(dict(c.settings)["growth_dt"] == 1.0 for c in originals)
    left_point = [c for k, c in cases.items() if "left-point" in k]
    assert [dict(c.settings)["growth_dt"] for c in left_point] == [1.0]
    assert "idealized_mwf_default_dt1" in cases and not any("dt24" in k for k in cases)
    runs = {k: {"csa": 8.0, "volume": 8.0, "kM": 0.01} for k in cases}
    text = "\n".join(reproducereport.idealized_section({"runs": runs}, quick=True))
    assert "hyper, original (Δtg = 1 h) | hyper, default (Δtg = 168 h)" in text
    assert "`--growth-increment left-point` alone (Δtg = 1 h)" in text
