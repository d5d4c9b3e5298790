"""hyper study: the study file's sections, its errors, the precedence of options, and
that a study runs what `hyper cohort` and the built-in protocols do."""

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hyper.analysis import cohort, study
from hyper.commands import cli
from hyper.commands import cohort as cohort_job
from hyper.commands import study as study_job
from hyper.core import io
from hyper.core.params import InputError
from hyper.model import protocols
from hyper.model.heterogeneity import Heterogeneity
from hyper.model.protocols import Repeat
from hyper.runs import fidelity

ROOT = Path(__file__).resolve().parents[1]

SHORT = """
[[protocol]]
name = "short"
end = 96.0
[[protocol.session]]
start = 24.0
duration = 1.0
intensity = 0.8

[[protocol]]
name = "twice"
[protocol.repeat]
every_days = 2
duration = 1.0
intensity = 0.5
weeks = 1
"""


def write(folder: Path, text: str, name: str = "s.toml") -> Path:
    path = folder / name
    path.write_text(text)
    return path


# ------------------------------------------------------------------------ repeat rules


def test_repeat_rule_on_weekdays_is_the_built_in_mwf():
    rule = Repeat(duration=1.0, intensity=0.8, weeks=8, weekdays=("mon", "wed", "fri"), lead_in_days=7)
    assert rule.protocol("mwf") == protocols.named("mwf")


def test_repeat_rule_every_n_days_starts_within_the_training_weeks():
    p = Repeat(duration=4.0, intensity=0.2, weeks=1, every_days=3, lead_in_days=2).protocol("e3")
    assert [s.start for s in p.sessions] == [48.0, 120.0, 192.0]  # 48 h + 168 h: the week ends at 216 h
    assert p.end == 216.0


def test_protocol_files_take_repeat_rules(tmp_path):
    path = write(tmp_path, '[repeat]\nweekdays = ["mon", "wed", "fri"]\nduration = 1.0\nintensity = 0.8\n'
                           'weeks = 8\nlead_in_days = 7\n', "mwf.toml")
    assert protocols.load(path) == protocols.named("mwf")


@pytest.mark.parametrize("text, message", [
    ('[repeat]\nduration = 1\nintensity = 0.5\nweeks = 2\n', r"repeat: give exactly one of weekdays"),
    ('[repeat]\nweekdays = ["mon"]\nevery_days = 2\nduration = 1\nintensity = 0.5\nweeks = 2\n',
     r"give exactly one of weekdays"),
    ('[repeat]\nweekdays = ["monday"]\nduration = 1\nintensity = 0.5\nweeks = 2\n',
     r"weekdays: expected days of mon, tue"),
    ('[repeat]\nevery_days = 1\nduration = 1\nintensity = 0.5\nweeks = 1.5\n', r"weeks: expected an integer"),
    ('[repeat]\nevery_days = 0.01\nduration = 1\nintensity = 0.5\nweeks = 1\n', r"session 1: overlaps session 0"),
    ('[repeat]\nevery_days = 1\nduration = 1\nweeks = 1\n', r"repeat: missing intensity"),
    ('[repeat]\nevery_days = 1\nduration = 1\nintensity = 0.5\nweeks = 1\nhour = 6\n',
     r"repeat: unknown key\(s\) hour"),
    ('end = 10\n[repeat]\nevery_days = 1\nduration = 1\nintensity = 0.5\nweeks = 1\n'
     '[[session]]\nstart = 0\nduration = 1\nintensity = 1\n', r"either \[\[session\]\] tables or a \[repeat\] rule"),
])
def test_bad_repeat_rules_are_refused_with_the_key_named(tmp_path, text, message):
    with pytest.raises(InputError, match=message):
        protocols.load(write(tmp_path, text, "p.toml"))


# ------------------------------------------------------------------------ the sections


def test_geometries_and_named_protocols(tmp_path):
    s = study.load(write(tmp_path, 'geometries = ["cylinder", "idealized"]\nprotocols = ["mwf", "weekly"]\n'))
    assert s.names == ["cylinder", "idealized"]
    assert [p.name for p in s.protocols] == ["mwf", "weekly"]
    assert s.meshes == () and s.heterogeneity is None
    assert study.load(write(tmp_path, 'geometries = ["cylinder"]\nprotocols = ["all"]\n')).protocols == tuple(
        protocols.named(n) for n in protocols.PAPER)


def test_protocol_files_are_relative_to_the_study_file(tmp_path):
    (tmp_path / "sub").mkdir()
    write(tmp_path / "sub", "end = 10.0\n", "quiet.toml")
    s = study.load(write(tmp_path / "sub", 'geometries = ["cylinder"]\nprotocols = ["quiet.toml"]\n'))
    assert s.protocols == (protocols.Protocol((), 10.0, "quiet"),)


def test_protocols_written_in_the_study_with_sessions_or_a_repeat_rule(tmp_path):
    s = study.load(write(tmp_path, 'geometries = ["cylinder"]\n' + SHORT))
    short, twice = s.protocols
    assert short == protocols.Protocol((protocols.Session(24.0, 1.0, 0.8),), 96.0, "short")
    assert [x.start for x in twice.sessions] == [0.0, 48.0, 96.0, 144.0] and twice.end == 168.0


def test_a_mesh_file_with_its_unit(tmp_path):
    mesh = ROOT / "meshes/VHF_Left_Muscle_TibialisAnterior_smooth/VHF_Left_Muscle_TibialisAnterior_smooth.xdmf"
    s = study.load(write(tmp_path, f'protocols = ["weekly"]\n[[mesh]]\nfile = "{mesh}"\nunit = "mm"\n'))
    assert s.names == [mesh.stem]
    assert s.meshes[0].path == mesh and s.meshes[0].unit == "mm"


def test_signaling_parameters_and_heterogeneity(tmp_path):
    s = study.load(write(tmp_path, 'geometries = ["cylinder"]\nprotocols = ["weekly"]\n[signaling]\na10 = 0.1\n'
                                   '[heterogeneity]\nmodel = "matern"\nepsilon = 0.05\nlength = 0.03\nseed = 7\n'))
    assert s.signaling.a10 == 0.1
    assert s.heterogeneity == Heterogeneity("matern", 0.05, 0.03) and s.seed == 7
    assert study.spec_options(s, None)["seed"] == 7


def test_numerics_growth_step_and_accuracy(tmp_path):
    s = study.load(write(tmp_path, 'geometries = ["cylinder"]\nprotocols = ["weekly"]\n[numerics]\ngrowth_dt = 24\n'
                                   'signaling_dt = 0.1\nquadrature_degree = 2\nlinear_solver = "iterative"\n'
                                   'max_halvings = 2\n'))
    settings, choice = study.steps(s)
    assert (settings.growth_dt, settings.signaling_dt, settings.max_halvings, choice) == (24.0, 0.1, 2, None)
    assert study.spec_options(s, choice)["linear_solver"] == "iterative"
    assert study.spec_options(s, choice)["quadrature_degree"] == 2
    s = study.load(write(tmp_path, 'geometries = ["cylinder"]\nprotocols = ["weekly"]\n[numerics]\naccuracy = 1e-3\n'))
    settings, choice = study.steps(s)
    assert choice is not None and settings.growth_dt == choice.growth_dt
    assert study.spec_options(s, choice)["linear_solver"] == "auto"
    assert choice.spatial_error == fidelity.spatial("cylinder").error and choice.refine == 0
    assert choice.predicted_error > choice.spatial_error


def test_accuracy_counts_the_worst_mesh_and_refines_every_mesh_alike(tmp_path, monkeypatch):
    # a table for TA_VHF_Left's mesh and fibres: 4.6e-3 of the growth, 2.0e-3 of it kept, order 1,
    # so 3.3e-3 refined once; half of 0.008 (the mesh's share) needs one refinement
    ta = fidelity.MeshError(4.6e-3, 2.0e-3, 1.0, "a test")
    monkeypatch.setitem(fidelity.SHIPPED_ERROR["laplace"], "TA_VHF_Left", ta)
    once = ta.kept + (ta.error - ta.kept) / 2
    assert 2 * once < 0.008 < 2 * ta.error
    s = study.load(write(tmp_path, 'geometries = ["cylinder", "TA_VHF_Left"]\nprotocols = ["weekly"]\n'
                                   '[numerics]\naccuracy = 0.008\n'))
    settings, choice = study.steps(s)
    assert choice.refine == 1 and study.spec_options(s, choice)["refine"] == 1
    assert choice.spatial_error == pytest.approx(once, rel=1e-12)
    assert choice.predicted_error <= 0.008
    # a looser accuracy leaves the meshes as they are; the worst one still counts
    s = study.load(write(tmp_path, 'geometries = ["cylinder", "TA_VHF_Left"]\nprotocols = ["weekly"]\n'
                                   '[numerics]\naccuracy = 0.02\n'))
    _, choice = study.steps(s)
    assert (choice.refine, choice.spatial_error) == (0, ta.error)


def test_an_accuracy_no_mesh_of_the_study_can_give_is_refused(tmp_path):
    s = study.load(write(tmp_path, 'geometries = ["cylinder", "TA_VHF_Left"]\nprotocols = ["weekly"]\n'
                                   '[numerics]\naccuracy = 1e-3\n'))
    with pytest.raises(InputError, match=r"numerics.accuracy 0.001: accuracy 0.001 is tighter than the mesh of "
                                         r"TA_VHF_Left can give: .* the smallest supported accuracy is"):
        study.steps(s)


def test_material_and_model_switches(tmp_path):
    s = study.load(write(tmp_path, GOOD + "[material]\nsigma_act = 2.5e5\nk_tendon = 2e5\n[numerics]\n"
                                   'feedback = "linear"\ngrow_during_sessions = false\nconsistent_stress = false\n'))
    assert (s.material.sigma_act, s.material.k_tendon, s.material.c1) == (2.5e5, 2e5, 1e4)
    settings, _ = study.steps(s)
    assert (settings.feedback, settings.grow_during_sessions, settings.consistent_stress) == ("linear", False, False)
    spec = study.first_spec(s, settings, None)
    assert spec.material == s.material and spec.describe()["material"]["sigma_act"] == 2.5e5


def test_output_section(tmp_path):
    s = study.load(write(tmp_path, f'geometries = ["cylinder"]\nprotocols = ["weekly"]\n[output]\n'
                                   f'folder = "{tmp_path}/out"\nfigures = false\n'))
    assert s.output == study.Output(tmp_path / "out", False)
    assert study.load(write(tmp_path, 'geometries = ["cylinder"]\nprotocols = ["weekly"]\n')).output.folder == \
        study.DEFAULT_FOLDER


def test_command_line_options_override_the_file(tmp_path):
    path = write(tmp_path, 'geometries = ["cylinder"]\nprotocols = ["weekly"]\n[numerics]\ngrowth_dt = 24\n'
                           'linear_solver = "iterative"\n[output]\nfolder = "a"\nfigures = true\n')
    args = study_job.parser().parse_args([str(path), "--growth-dt", "12", "--output", str(tmp_path / "b"),
                                              "--no-figures", "--linear-solver", "lu"])
    s = study_job.from_args(args)
    assert (s.numerics.growth_dt, s.numerics.linear_solver) == (12.0, "lu")
    assert s.output == study.Output(tmp_path / "b", False)
    # what the command line leaves out stays the file's
    assert study_job.from_args(study_job.parser().parse_args([str(path)])).numerics.growth_dt == 24.0
    # a bad overriding value is named by its option: where the option reads it (a number of hours > 0) …
    with pytest.raises(InputError, match=r"^argument --growth-dt: expected a finite number of hours > 0"):
        study_job.parser().parse_args([str(path), "--growth-dt", "-1"])
    # … or where the study checks it against the rest
    with pytest.raises(InputError, match=r"^--signaling-dt: 0.5 h must not exceed the growth step \(0.1 h\)"):
        study_job.from_args(study_job.parser().parse_args([str(path), "--growth-dt", "0.1", "--signaling-dt", "0.5"]))


def test_shipped_studies_load():
    paper = study.load(ROOT / "studies/paper-cohort.toml")
    assert paper.names == list(cohort.geo.ANATOMICAL)
    assert [p.name for p in paper.protocols] == list(cohort.PAPER_PROTOCOLS)
    custom = study.load(ROOT / "studies/custom.toml")
    assert custom.meshes[0].unit == "mm" and custom.protocols[0].name == "tue-fri"
    assert [s.start for s in custom.protocols[0].sessions[:2]] == [168.0 + 24.0, 168.0 + 96.0]
    for path in sorted((ROOT / "studies").glob("*.toml")):
        study.steps(study.load(path))  # its accuracy, if any, is one its meshes can give


def test_study_is_a_job():
    assert "study" in cli.JOBS


# ------------------------------------------------------------------------ malformed files

GOOD = 'geometries = ["cylinder"]\nprotocols = ["weekly"]\n'
MALFORMED = {
    "toml": ("geometries = [\n", r"malformed TOML"),
    "unknown_top_key": (GOOD + "colour = 3\n", r"unknown key\(s\) colour; known: geometries, protocols"),
    "geometries_not_array": ('geometries = "cylinder"\nprotocols = ["weekly"]\n', r"geometries: expected an array"),
    "unknown_geometry": ('geometries = ["sphere"]\nprotocols = ["weekly"]\n', r"geometries: unknown 'sphere'"),
    "no_geometry": ('protocols = ["weekly"]\n', r"geometries: no geometry"),
    "no_protocol": ('geometries = ["cylinder"]\n', r"protocols: no protocol"),
    "unknown_protocol": ('geometries = ["cylinder"]\nprotocols = ["sometimes"]\n',
                         r"protocols: 'sometimes' is neither a built-in protocol"),
    "repeated_geometry": ('geometries = ["cylinder", "cylinder"]\nprotocols = ["weekly"]\n',
                          r"geometries: names must be unique.*cylinder"),
    "repeated_protocol": ('geometries = ["cylinder"]\nprotocols = ["weekly", "weekly"]\n',
                          r"protocols: names must be unique.*weekly"),
    "protocol_table_key": (GOOD + '[[protocol]]\nname = "x"\nlength = 3\n', r"protocol 0: unknown key\(s\) length"),
    "protocol_without_end": (GOOD + '[[protocol]]\nname = "x"\n', r"protocol 0: missing 'end'"),
    "repeat_weekday": (GOOD + '[[protocol]]\nname = "x"\n[protocol.repeat]\nweekdays = ["funday"]\nduration = 1\n'
                       'intensity = 0.5\nweeks = 1\n', r"protocol 0: repeat: weekdays: expected days of mon"),
    "repeat_intensity": (GOOD + '[[protocol]]\nname = "x"\n[protocol.repeat]\nevery_days = 2\nduration = 1\n'
                         'intensity = 1.5\nweeks = 1\n', r"protocol 0: session 0: intensity must lie in \[0, 1\]"),
    "mesh_missing": (GOOD + '[[mesh]]\nfile = "none.xdmf"\n', r"mesh 0: file: .*none.xdmf: no such file"),
    "mesh_unit": (GOOD + '[[mesh]]\nfile = "s.toml"\nunit = "cm"\n', r"mesh 0: unit: expected one of m, mm"),
    "mesh_key": (GOOD + '[[mesh]]\nfile = "s.toml"\nscale = 2\n', r"mesh 0: unknown key\(s\) scale; known: file, unit"),
    "mesh_not_xdmf": (GOOD + '[[mesh]]\nfile = "s.toml"\n', r"mesh 0: .*expected an XDMF mesh file"),
    "signaling_unknown": (GOOD + "[signaling]\nk = 1\n", r"signaling: unknown key\(s\) k; known: a10"),
    "signaling_value": (GOOD + "[signaling]\na10 = -1\n", r"signaling: a10"),
    "signaling_not_table": (GOOD + "signaling = 3\n", r"signaling: expected a table"),
    "material_unknown": (GOOD + "[material]\nc3 = 1\n", r"material: unknown key\(s\) c3; known: c1"),
    "material_value": (GOOD + "[material]\nlambda0 = 0\n", r"material: lambda0: expected a number > 0"),
    "material_not_number": (GOOD + "[material]\nc1 = 'soft'\n", r"material: c1: expected a number"),
    "sobol_key": (GOOD + "[sobol]\nnames = ['kM']\nspread = 2\n", r"sobol: unknown key\(s\) spread; known: function"),
    "feedback": (GOOD + '[numerics]\nfeedback = "cubic"\n', r"numerics.feedback: expected one of hill"),
    "consistent_stress": (GOOD + "[numerics]\nconsistent_stress = 1\n",
                          r"numerics.consistent_stress: expected true or false"),
    "heterogeneity_seed": (GOOD + "[heterogeneity]\nepsilon = 0.1\n", r"heterogeneity: seed: expected an integer"),
    "heterogeneity_model": (GOOD + '[heterogeneity]\nmodel = "spots"\nseed = 1\n',
                            r"heterogeneity: heterogeneity model must be one of uniform-noise, matern"),
    "heterogeneity_key": (GOOD + "[heterogeneity]\nseed = 1\nspread = 2\n", r"heterogeneity: unknown key\(s\) spread"),
    "numerics_key": (GOOD + "[numerics]\ndt = 1\n", r"numerics: unknown key\(s\) dt; known: growth_dt, accuracy"),
    "growth_dt": (GOOD + "[numerics]\ngrowth_dt = 0\n", r"numerics.growth_dt: expected a finite number of hours > 0"),
    "accuracy": (GOOD + "[numerics]\naccuracy = 2\n", r"numerics.accuracy: expected a number in \(0, 0.5\)"),
    "quadrature": (GOOD + "[numerics]\nquadrature_degree = 20\n", r"numerics.quadrature_degree: expected an integer "
                   r"in \[1, 12\]"),
    "solver": (GOOD + '[numerics]\nlinear_solver = "cg"\n', r"numerics.linear_solver: expected one of lu, iterative"),
    "max_halvings": (GOOD + "[numerics]\nmax_halvings = -1\n", r"numerics.max_halvings: expected an integer in"),
    "rk4_above_growth": (GOOD + "[numerics]\ngrowth_dt = 1\nsignaling_dt = 2\n",
                         r"numerics.signaling_dt: 2 h must not exceed the growth step"),
    "output_key": (GOOD + "[output]\nplace = 'x'\n", r"output: unknown key\(s\) place; known: folder, figures"),
    "output_figures": (GOOD + "[output]\nfigures = 'yes'\n", r"output.figures: expected true or false"),
    "output_folder_is_file": (GOOD + "[output]\nfolder = '{d}/s.toml'\n", r"output.folder: .*exists and is not a "
                              r"folder"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_study_files_are_refused_and_write_nothing(tmp_path, capsys, monkeypatch, case):
    text, message = MALFORMED[case]
    path = write(tmp_path, text.replace("{d}", str(tmp_path)))
    monkeypatch.chdir(tmp_path)  # the default output folder would be results/study here
    before = sorted(tmp_path.rglob("*"))
    assert study_job.main([str(path), "--output", str(tmp_path / "out")] if "output" not in case
                              else [str(path)]) == cli.EXIT_INPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    assert str(path) in err[0]
    assert re.search(message, err[0]), err[0]
    assert sorted(tmp_path.rglob("*")) == before


def test_malformed_study_file_under_mpirun(tmp_path):
    path = write(tmp_path, GOOD + "[numerics]\ngrowth_dt = 0\n")
    mpirun = Path(sys.executable).with_name("mpirun")
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "OMP_NUM_THREADS": "1"}
    done = subprocess.run([str(mpirun), "-n", "2", "env", f"PYTHONPATH={ROOT / 'src'}", sys.executable, "-m",
                           "hyper.study", str(path), "--output", str(tmp_path / "out")],
                          capture_output=True, text=True, timeout=240, env=env, cwd=tmp_path)
    assert done.returncode == cli.EXIT_INPUT, done.stderr
    errors = [line for line in done.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "numerics.growth_dt: expected a finite number of hours > 0" in errors[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.toml"]


# ------------------------------------------------------------------------ runs


def test_a_two_protocol_study_is_the_cohort_with_the_same_settings(tmp_path):
    """1 geometry × 2 protocols: the farm of hyper cohort, the same runs and ratios."""
    path = write(tmp_path, 'geometries = ["cylinder"]\n[numerics]\ngrowth_dt = 24\n'
                           f'[output]\nfolder = "{tmp_path}/study"\nfigures = false\n' + SHORT)
    assert study_job.main([str(path)]) == 0
    made = study.load(path)
    for p in made.protocols:
        protocols_file = tmp_path / f"{p.name}.toml"
        protocols_file.write_text(f'name = "{p.name}"\nend = {p.end!r}\n' + "".join(
            f"[[session]]\nstart = {s.start!r}\nduration = {s.duration!r}\nintensity = {s.intensity!r}\n"
            for s in p.sessions))
    assert cohort_job.main(["--geometries", "cylinder", "--protocols", str(tmp_path / "short.toml"),
                                str(tmp_path / "twice.toml"), "--growth-dt", "24", "--output", str(tmp_path / "cohort"),
                                "--plot-geometry", "cylinder"]) == 0
    for name in ("short", "twice"):
        a = io.read_series(tmp_path / "study" / "runs" / f"cylinder_{name}.h5")
        b = io.read_series(tmp_path / "cohort" / "runs" / f"cylinder_{name}.h5")
        assert np.array_equal(a["t"], b["t"])
        for key in ("csa_ratio", "volume_ratio"):
            np.testing.assert_allclose(a[key][-1], b[key][-1], rtol=1e-12, atol=0)
    assert (tmp_path / "study" / "summary.csv").is_file() and not (tmp_path / "study" / "ratios.png").exists()


def test_one_run_study_writes_what_grow_writes(tmp_path):
    path = write(tmp_path, 'geometries = ["cylinder"]\n[numerics]\ngrowth_dt = 24\n'
                           f'[output]\nfolder = "{tmp_path}/one"\n' + SHORT.split("[[protocol]]\nname = \"twice\"")[0])
    assert study_job.main([str(path)]) == 0
    assert io.is_complete(tmp_path / "one" / "cylinder_short.h5")
    assert (tmp_path / "one" / "cylinder_short_fields.xdmf").is_file()
    assert (tmp_path / "one" / "cylinder_growth.png").is_file()


def test_a_study_carries_the_sobol_problem(tmp_path):
    from hyper.commands import sobol as sobol_job

    path = write(tmp_path, GOOD + '[sobol]\nnames = ["kM"]\nbounds = [[0.005, 0.02]]\nprotocol = "weekly"\n')
    assert study.load(path).names == ["cylinder"]
    protocol, prob = sobol_job._check(sobol_job.parser().parse_args(["--problem", str(path)]))
    assert protocol.name == "weekly" and prob == {"num_vars": 1, "names": ["kM"], "bounds": [[0.005, 0.02]]}
