"""Every job refuses bad input alike: exit status 2, one `error:` line on stderr, nothing
on stdout, and nothing written (the output folder absent, the input folder unchanged).

The table runs each job in-process through `hyper.commands.cli.main`, as `hyper JOB …` does; the
MPI cases run `mpirun -n 2 python -m hyper.JOB …` with a time limit, so that a job that
leaves a rank waiting fails the test instead of hanging it.
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from hyper.commands import cli
from hyper.runs import locks

ROOT = Path(__file__).resolve().parents[1]

PROTOCOL_FILES = {
    "climbs_out.toml": 'name = "../../escaped"\nend = 48.0\n',
    "hidden.toml": 'name = ".hidden"\nend = 48.0\n',
    "slashed.toml": 'name = "a/b"\nend = 48.0\n',
    "empty_name.toml": 'name = ""\nend = 48.0\n',
    "nul.toml": 'name = "a\\u0000b"\nend = 48.0\n',
    "huge_end.toml": "end = " + "9" * 401 + "\n",
    "long_end.toml": "end = 1e15\n",
    "huge_duration.toml": "end = 48.0\n[[session]]\nstart = 0.0\nduration = " + "9" * 401 + "\nintensity = 0.5\n",
    # issue 35: a session's passive stretch (along-fibre growth), a finite number >= 1
    **{f"stretch_{k}.toml": f"end = 48.0\n[[session]]\nstart = 0.0\nduration = 1.0\nintensity = 0.5\nstretch = {v}\n"
       for k, v in (("short", "0.9"), ("nan", "nan"), ("text", '"long"'))},
}
HUGE = "1" + "0" * 400  # a TOML integer too large for a float
STUDY = 'geometries = ["cylinder"]\nprotocols = ["mwf"]\n'
REPEAT = STUDY.replace('protocols = ["mwf"]\n', "") + '[[protocol]]\nname = "r"\n[protocol.repeat]\n'
STUDY_FILES = {  # name -> (text, the message); the study job's rows below
    "growth_dt": (STUDY + f"[numerics]\ngrowth_dt = {HUGE}\n", r"numerics.growth_dt: expected a finite number of "
                  r"hours > 0, got an integer of 401 digits"),
    "signaling_dt": (STUDY + "[numerics]\nsignaling_dt = nan\n", r"numerics.signaling_dt: expected a finite number"),
    "accuracy": (STUDY + f"[numerics]\naccuracy = {HUGE}\n", r"numerics.accuracy: .* got an integer of 401 digits"),
    "max_halvings": (STUDY + f"[numerics]\nmax_halvings = {HUGE}\n", r"numerics.max_halvings: .*401 digits"),
    "quadrature_degree": (STUDY + f"[numerics]\nquadrature_degree = -{HUGE}\n", r"quadrature_degree: .*401 digits"),
    "refine": (STUDY + "[numerics]\nrefine = 7\n", r"numerics.refine: expected an integer in \[0, 3\], got 7"),
    "refine_fraction": (STUDY + "[numerics]\nrefine = 1.5\n", r"numerics.refine: expected an integer in \[0, 3\]"),
    "snapshot_every": (STUDY + f"[output]\nsnapshot_every = {HUGE}\n", r"output.snapshot_every: .*401 digits"),
    "signaling": (STUDY + f"[signaling]\nkM = {HUGE}\n", r"signaling: kM: expected a finite number, got an integer"),
    "material": (STUDY + f"[material]\nsigma_act = -{HUGE}\n", r"material: sigma_act: expected a finite number"),
    "epsilon": (STUDY + f"[heterogeneity]\nepsilon = {HUGE}\nseed = 1\n", r"epsilon must be a number in .*401 digits"),
    "length": (STUDY + '[heterogeneity]\nmodel = "matern"\nlength = inf\nseed = 1\n', r"length must be a number"),
    "seed_huge": (STUDY + f"[heterogeneity]\nseed = {HUGE}\n",
                  r"heterogeneity: seed: expected an integer in \[0, 4294967295\], got an integer of 401 digits"),
    "seed_past_32_bits": (STUDY + f"[heterogeneity]\nseed = {2**32}\n",
                          r"seed: expected an integer in \[0, 4294967295\]"),
    "seed_negative": (STUDY + "[heterogeneity]\nseed = -1\n",
                      r"seed: expected an integer in \[0, 4294967295\], got -1"),
    "seed_float": (STUDY + "[heterogeneity]\nseed = 1.5\n", r"seed: expected an integer, got 1.5"),
    "too_long": (STUDY + "[numerics]\ngrowth_dt = " + "1" * 5000 + "\n", r"a number too long to read"),
    "repeat_tiny_period": (REPEAT + "every_days = 1e-9\nduration = 1e-12\nintensity = 0.5\nweeks = 1\n",
                           r"every_days: 7e\+09 sessions, more than 100000"),
    "repeat_denormal_period": (REPEAT + "every_days = 5e-324\nduration = 1\nintensity = 0.5\nweeks = 1\n",
                               r"every_days: inf sessions, more than 100000"),
    "repeat_weeks": (REPEAT + f"every_days = 2\nduration = 1\nintensity = 0.5\nweeks = {HUGE}\n",
                     r"weeks: expected an integer in \[1, 520\], got an integer of 401 digits"),
    "repeat_lead_in": (REPEAT + 'weekdays = ["mon"]\nduration = 1\nintensity = 0.5\nweeks = 1\nlead_in_days = 1e308\n',
                       r"lead_in_days: expected a number of days in \[0, 3633\]"),
    "repeat_duration": (REPEAT + f"every_days = 2\nduration = {HUGE}\nintensity = 0.5\nweeks = 1\n",
                        r"duration: expected a finite number, got an integer of 401 digits"),
    "sections": (STUDY + "[numerics]\nsections = -1\n", r"numerics.sections: expected an integer in \[0, 99\], got -1"),
    "detraining": (STUDY + "[numerics]\ndetraining = 0\n",
                   r"numerics.detraining: expected a finite number of hours > 0, got 0"),
    "detraining_nan": (STUDY + "[numerics]\ndetraining = nan\n", r"numerics.detraining: expected a finite number"),
    "fiber_growth": (STUDY + '[numerics]\nfiber_growth = "along"\n',
                     r"numerics.fiber_growth: must be one of none, stretch, got 'along'"),
    "fiber_tau": (STUDY + "[numerics]\nfiber_tau = 0\n", r"numerics.fiber_tau: expected a finite number of hours > 0"),
    "fiber_crit": (STUDY + "[numerics]\nfiber_crit = 0.5\n", r"numerics.fiber_crit: expected a number >= 1"),
    "stimulus": (STUDY + '[numerics]\nstimulus = "regional"\n',
                 r"numerics.stimulus: must be one of global, local, got 'regional'"),
    "sobol_names": (STUDY + '[sobol]\nnames = ["bogus"]\n',
                    r"sobol: names: expected distinct parameters of .* got bogus"),
    "sobol_names_of_ishigami": (STUDY + '[sobol]\nfunction = "ishigami"\nnames = ["kM"]\n',
                                r"sobol: names: the Ishigami function has its own three parameters"),
    "sobol_bounds": (STUDY + f'[sobol]\nnames = ["kM"]\nbounds = [[0, {HUGE}]]\n', r"sobol: bounds: expected a finite"),
    "sobol_at": (STUDY + f"[sobol]\nat = {HUGE}\n", r"sobol: at: expected a finite number of hours > 0"),
    "sobol_num_vars": (STUDY + f'[sobol]\nnames = ["kM"]\nnum_vars = {HUGE}\n',
                       r"sobol: num_vars: expected an integer"),
}
PRIOR_FILES = {  # name -> (a --priors file, the message); the calibrate job's rows below
    "unknown": ("[kX]\nlow = 0.001\nhigh = 0.1\n", r"priors_unknown.toml: unknown parameter 'kX'"),
    "reversed": ("[kM]\nlow = 0.1\nhigh = 0.01\n", r"prior kM: need low < high, got \[0.1, 0.01\]"),
    "nan": ("[kM]\nlow = nan\n", r"\[kM\] low: expected a finite number, got nan"),
    "inf": ("[noise]\nhigh = inf\n", r"\[noise\] high: expected a finite number, got inf"),
    "huge": (f"[kM]\nhigh = {HUGE}\n", r"\[kM\] high: expected a finite number, got an integer of 401 digits"),
}
PROTOCOL_CASES = {
    "unknown": (["{p}", "daily"], r"unknown protocol 'daily'"),
    "absent_file": (["{p}", "{d}/absent.toml"], r"absent.toml: no such file"),
    "folder": (["{p}", "{d}/a_folder.toml"], r"a_folder.toml: is a folder, not a TOML file"),
    "climbs_out": (["{p}", "{d}/climbs_out.toml"], r"name must be 1-64 letters, .* got '../../escaped'"),
    "hidden": (["{p}", "{d}/hidden.toml"], r"name must be .* got '.hidden'"),
    "slashed": (["{p}", "{d}/slashed.toml"], r"name must be .* got 'a/b'"),
    "empty_name": (["{p}", "{d}/empty_name.toml"], r"name must be .* got ''"),
    "nul": (["{p}", "{d}/nul.toml"], r"name must be .* got 'a\\x00b'"),
    "huge_end": (["{p}", "{d}/huge_end.toml"], r"end: expected a finite number, got an integer of 401 digits"),
    "long_end": (["{p}", "{d}/long_end.toml"], r"end must be at most 87360 h \(ten years\), got 1e\+15"),
    "huge_duration": (["{p}", "{d}/huge_duration.toml"], r"duration: expected a finite number, got an integer"),
    "stretch_short": (["{p}", "{d}/stretch_short.toml"], r"session 0: stretch: expected a number >= 1, got 0.9"),
    "stretch_nan": (["{p}", "{d}/stretch_nan.toml"], r"session 0: stretch: expected a finite number, got nan"),
    "stretch_text": (["{p}", "{d}/stretch_text.toml"], r"session 0: stretch: expected a number, got 'long'"),
}
OUTPUT_CASES = {
    "under_a_file": (["--output", "{d}/a_file/{o}"], r"a_file is a file, not a folder"),
    "under_proc": (["--output", "/proc/hyper/{o}"], r"under /proc, not a place for results"),
    "under_sys": (["--output", "/sys/hyper/{o}"], r"under /sys, not a place for results"),
    "empty": (["--output", ""], r"--output: expected a path, got ''"),
}
FOLDER_OUTPUT = {"a_file_as_folder": (["--output", "{d}/a_file"], r"a_file: exists and is not a folder")}
STEP_CASES = {
    "zero": (["--signaling-dt", "0"], r"--signaling-dt: expected a finite number of hours > 0, got 0"),
    "nan": (["--signaling-dt", "nan"], r"--signaling-dt: expected a finite number of hours > 0, got nan"),
    "tiny": (["--signaling-dt", "1e-300"], r"--signaling-dt: expected at least 0.0001 h, got 1e-300"),
    "text": (["--signaling-dt", "fast"], r"argument --signaling-dt: expected a number of hours, got 'fast'"),
}


# issue 35: --detraining TAU, hours > 0 (0, nan, -1 and inf refused)
DETRAINING_CASES = {f"detraining_{name}": (["--detraining", text], rf"argument --detraining: expected a finite "
                                           rf"number of hours > 0{tail}")
                    for name, text, tail in (("zero", "0", ", got 0"), ("nan", "nan", ""),
                                             ("negative", "-1", ", got -1"), ("inf", "inf", ""))}


def integer_cases(option, least, most=None):
    bounds = rf">= {least}" if most is None else rf"in \[{least}, {most}\]"
    out = {
        f"{option}_below": ([option, str(least - 1)],
                            rf"argument {option}: expected an integer {bounds}, got {least - 1}"),
        f"{option}_fraction": ([option, "2.5"], rf"argument {option}: expected an integer, got '2.5'"),
    }
    if most is not None:
        out[f"{option}_huge"] = ([option, "1" + "0" * 30], rf"argument {option}: expected an integer {bounds}, got 1")
    return out


# job -> (the base command, with {out} its output; the output's name for OUTPUT_CASES;
#         the job's cases besides the shared ones)
JOBS = {
    "signaling": (["--protocol", "mwf", "--output", "{out}"], "x.h5", {
        **{f"protocol_{k}": (v[0], v[1]) for k, v in PROTOCOL_CASES.items()},
        **{f"step_{k}": v for k, v in STEP_CASES.items()},
        "sample_every_zero": (["--sample-every", "0"], r"--sample-every: expected a finite number of hours > 0"),
        "sample_every_tiny": (["--sample-every", "1e-9"], r"--sample-every: expected at least 0.001 h, got 1e-09"),
        "plot_not_png": (["--plot", "{out}/figure.pdf"], r"figure.pdf: expected a .png file"),
        "plot_under_proc": (["--plot", "/proc/figure.png"], r"under /proc"),
        "params_absent": (["--params", "{d}/absent_params.toml"], r"absent_params.toml: no such file"),
        "params_folder": (["--params", "{d}/a_folder.toml"], r"is a folder, not a TOML file"),
        "params_huge": (["--params", "{d}/huge_params.toml"], r"kM: expected a finite number, got an integer"),
        "unknown_option": (["--bogus"], r"unrecognized arguments: --bogus"),
    }),
    "sobol": (["--samples", "4", "--output", "{out}"], "sobol", {
        **{f"protocol_{k}": v for k, v in PROTOCOL_CASES.items() if k != "unknown"},
        **{f"step_{k}": v for k, v in STEP_CASES.items()},
        **FOLDER_OUTPUT,
        **integer_cases("--samples", 2, 10**7),
        **integer_cases("--chunk", 1, 10**7),
        **integer_cases("--seed", 0, 2**32 - 2),
        **integer_cases("--resamples", 2, 10**5),
        "backend": (["--backend", "fortran"], r"argument --backend: invalid choice: 'fortran'"),
        "unknown_option": (["--bogus"], r"unrecognized arguments: --bogus"),
    }),
    "cohort": (["--geometries", "cylinder", "--protocols", "mwf", "--output", "{out}"], "cohort", {
        **{f"protocol_{k}": (["--protocols", v[0][1]], v[1]) for k, v in PROTOCOL_CASES.items()},
        **FOLDER_OUTPUT,
        **integer_cases("--ranks-per-job", 1),
        **integer_cases("--refine", 0, 3),
        "snapshot_every": (["--snapshot-every", "-3"],
                           r"--snapshot-every: expected a finite number of hours > 0, got -3"),
        "snapshot_every_inf": (["--snapshot-every", "inf"], r"--snapshot-every: expected a finite number of hours > 0"),
        "growth_dt": (["--growth-dt", "-1"], r"--growth-dt: expected a finite number of hours > 0, got -1"),
        "max_halvings": (["--max-halvings", "40"], r"--max-halvings: expected an integer in \[0, 12\], got 40"),
        "geometry": (["--geometries", "biceps"], r"--geometries: unknown biceps"),
        "geometry_empty": (["--geometries", ""], r"--geometries: unknown"),
        "plot_geometry": (["--plot-geometry", "nowhere"], r"--plot-geometry nowhere: not one of --geometries"),
        "unknown_option": (["--bogus"], r"unrecognized arguments: --bogus"),
        **integer_cases("--sections", 0, 99),
        **DETRAINING_CASES,
        "fiber_growth": (["--fiber-growth", "along"], r"argument --fiber-growth: invalid choice: 'along'"),
    }),
    "ensemble": (["--geometry", "cylinder", "--protocol", "mwf", "--output", "{out}"], "ensemble", {
        **{f"protocol_{k}": v for k, v in PROTOCOL_CASES.items()},
        **FOLDER_OUTPUT,
        **integer_cases("--samples", 1, 100_000),
        **integer_cases("--first-seed", 0, 2**32 - 1),
        **integer_cases("--ranks-per-job", 1),
        "epsilon": (["--epsilon", "1.5"], r"epsilon"),
        "growth_dt": (["--growth-dt", "0"], r"--growth-dt: expected a finite number of hours > 0, got 0"),
        "signaling_dt": (["--signaling-dt", "1e-300"], r"--signaling-dt: expected at least 0.0001 h"),
        "geometry": (["--geometry", "nowhere"], r"--geometry: unknown geometry 'nowhere'"),
        "geometry_empty": (["--geometry", ""], r"--geometry: unknown geometry ''"),
        "protocol_all": (["--protocol", "all"], r"an ensemble runs one protocol"),
        "model": (["--model", "brownian"], r"argument --model: invalid choice: 'brownian'"),
        "unknown_option": (["--bogus"], r"unrecognized arguments: --bogus"),
    }),
    "contraction": (["--geometry", "cylinder", "--output", "{out}/c.h5"], "c.h5", {
        **integer_cases("--steps", 1, 10**4),
        **integer_cases("--quadrature-degree", 1, 12),
        **integer_cases("--max-halvings", 0, 12),
        **integer_cases("--refine", 0, 3),
        "output_suffix": (["--output", "{out}/c.txt"], r"c.txt: expected a .h5 file"),
        "geometry": (["--geometry", "nowhere"], r"unknown geometry 'nowhere'"),
        "fibers": (["--fibers", "helical"], r"--fibers helical: expected one of auto, idealized"),
    }),
    "meshstats": (["--geometries", "TA_VHF_Left", "--output", "{out}/s.csv"], "s.csv", {
        "output_suffix": (["--output", "{out}/s.txt"], r"s.txt: expected a .csv file"),
        "geometry": (["--geometries", "nowhere"], r"nowhere"),
        "unknown_option": (["--bogus"], r"unrecognized arguments: --bogus"),
    }),
    "fibers": (["--geometries", "TA_VHF_Left", "--output", "{out}"], "fibers", {
        **FOLDER_OUTPUT,
        **integer_cases("--ranks-per-job", 1),
        "geometry": (["--geometries", "nowhere"], r"nowhere"),
        "unknown_option": (["--bogus"], r"unrecognized arguments: --bogus"),
    }),
    "demo": (["--output", "{out}"], "demo", {**FOLDER_OUTPUT, "unknown_option": (["--bogus"], r"--bogus")}),
    # the study file is a row's first option, so the shared --output rows run without one
    "study": (["--output", "{out}"], "study", {
        **{f"file_{k}": ([f"{{d}}/study_{k}.toml"], message) for k, (_, message) in STUDY_FILES.items()},
        **FOLDER_OUTPUT,
        "growth_dt_overflow": (["{d}/study_good.toml", "--growth-dt", "1e400"],
                               r"argument --growth-dt: expected a finite number of hours > 0, got inf"),
        "accuracy_nan": (["{d}/study_good.toml", "--accuracy", "nan"], r"argument --accuracy: expected a finite"),
        **{k: (["{d}/study_good.toml", *v[0]], v[1]) for k, v in integer_cases("--max-halvings", 0, 12).items()},
        **{k: (["{d}/study_good.toml", *v[0]], v[1]) for k, v in integer_cases("--quadrature-degree", 1, 12).items()},
        **{k: (["{d}/study_good.toml", *v[0]], v[1]) for k, v in integer_cases("--sections", 0, 99).items()},
        **{k: (["{d}/study_good.toml", *v[0]], v[1]) for k, v in DETRAINING_CASES.items()},
        **{k: (["{d}/study_good.toml", *v[0]], v[1]) for k, v in integer_cases("--refine", 0, 3).items()},
    }),
    "calibrate": (["--data", str(ROOT / "data" / "defreitas.csv"), "--protocol", "mwf", "--fit", "kM", "--no-check",
                   "--output", "{out}"], "calibration", {
        **FOLDER_OUTPUT,
        "bounds_negative": (["--fit", "kF=-1:-0.5"], r"--fit kF=-1:-0.5: kF must be >= 0, got -1"),
        "too_few_points": (["--exclude-until", "8"], r"1 data point\(s\) for 1 parameter\(s\)"),
        # issue 35: the detraining τ as a fitted parameter: hours > 0, finite bounds
        "detraining_zero": (["--fit", "detraining=0:100"],
                            r"--fit detraining=0:100: detraining: expected a finite number of hours > 0, got 0"),
        "detraining_inf": (["--fit", "detraining=5:inf"], r"--fit detraining=5:inf: expected finite bounds .* "
                           r"detraining=24:100000"),
        "detraining_one_point": (["--fit", "detraining", "--exclude-until", "8"],
                                 r"1 data point\(s\) for 2 parameter\(s\)"),
        **{f"priors_{k}": (["--method", "bayes", "--priors", f"{{d}}/priors_{k}.toml"], message)
           for k, (_, message) in PRIOR_FILES.items()},
        "priors_without_bayes": (["--priors", "{d}/priors_reversed.toml"], r"--priors: only with --method bayes"),
        "noise_without_bayes": (["--noise", "0.01"], r"--noise: only with --method bayes"),
        "noise_zero": (["--method", "bayes", "--noise", "0"], r"argument --noise: expected a number > 0, got 0"),
        "noise_count": (["--method", "bayes", "--noise", "0.01", "--noise", "0.02"], r"2 --noise for 1 --data"),
        "grid_of_two": (["--method", "bayes", "--sampler", "grid", "--fit", "kF"],
                        r"--sampler grid: the grid posterior is for one parameter, got 2"),
        "walkers_too_few": (["--method", "bayes", "--sampler", "emcee", "--walkers", "3", "--fit", "kF"],
                            r"--walkers 3: emcee needs at least 2 per sampled quantity \(6\)"),
        "bayes_on_the_coupled_model": (["--method", "bayes", "--geometry", "TA_VHF_Left"],
                                       r"--method bayes samples the ODE growth model only"),
    }),
    "dose": (["--output", "{out}"], "dose", {
        **FOLDER_OUTPUT,
        **integer_cases("--seed", 0, 2**32 - 1),
        **integer_cases("--checks", 0, 1000),
        "seed_past_32_bits": (["--seed", str(2**32)], r"argument --seed: expected an integer in \[0, 4294967295\]"),
        "budget_zero": (["--budgets", "1", "0"], r"argument --budgets: expected a finite number of hours > 0, got 0"),
        "budget_inf": (["--budgets", "inf"], r"argument --budgets: expected a finite number of hours > 0"),
        "accuracy_text": (["--accuracy", "tight"], r"argument --accuracy: expected a number, got 'tight'"),
    }),
    "predict": (["--posterior", "{d}/posterior.h5", "--geometry", "cylinder", "--output", "{out}"], "predict", {
        **FOLDER_OUTPUT,
        **{f"protocol_{k}": v for k, v in PROTOCOL_CASES.items()},
        "samples_one": (["--samples", "1"], r"argument --samples: expected an integer in \[2, 1000\], got 1"),
        "samples_past_the_posterior": (["--samples", "9"], r"--samples 9: the posterior holds only 3 samples"),
        "geometry_unknown": (["--geometry", "femur"], r"--geometry: unknown geometry 'femur'"),
        "posterior_missing": (["--posterior", "{d}/absent.h5"], r"--posterior .*absent.h5: no such file"),
        "posterior_not_hdf5": (["--posterior", "{d}/a_file"], r"posterior file"),
        "posterior_without_kM": (["--posterior", "{d}/kF.h5"], r"kF.h5: no kM samples \(datasets: kF\)"),
        "ranks_per_job_zero": (["--ranks-per-job", "0"], r"argument --ranks-per-job: expected an integer"),
    }),
    "design": (["--target", "5", "--week", "8", "--no-check", "--output", "{out}"], "design", {
        **FOLDER_OUTPUT,
        **integer_cases("--week", 1, 104),
        "target_zero": (["--target", "0"], r"argument --target: expected a number in \(0, 1000\], got 0"),
        "target_text": (["--target", "lots"], r"argument --target: expected a number, got 'lots'"),
        "target_out_of_reach": (["--target", "90"], r"--target 90 %: out of reach under the constraints; the most "
                                                   r"reachable gain is"),
        "sessions_above_weekdays": (["--sessions", "3", "4", "--weekdays", "mon", "thu"],
                                    r"--sessions: at least 3 a week, but only 2 weekday"),
        "sessions_reversed": (["--sessions", "5", "2"], r"--sessions: the least \(5\) is more than the most \(2\)"),
        "sessions_eight": (["--sessions", "1", "8"], r"argument --sessions: expected an integer in \[1, 7\]"),
        "intensity_reversed": (["--intensity", "0.8", "0.2"], r"--intensity: the least \(0.8\) is more than"),
        "intensity_above_one": (["--intensity", "0.5", "1.5"], r"argument --intensity: expected a number"),
        "intensity_off_grid": (["--intensity", "0.31", "0.34"], r"--intensity: no intensity of the grid"),
        "duration_zero": (["--duration", "0", "1"], r"argument --duration: expected a finite number of hours > 0"),
        "duration_off_grid": (["--duration", "5", "6"], r"--duration: no duration of the grid"),
        "weekday_twice": (["--weekdays", "mon", "mon"], r"--weekdays: each of .* at most once"),
        "weekday_unknown": (["--weekdays", "moon"], r"argument --weekdays: invalid choice: 'moon'"),
        "probability_without_posterior": (["--probability", "0.9"], r"--probability: only with --posterior"),
        "probability_one": (["--posterior", "{d}/R.h5", "--probability", "1"], r"argument --probability: expected"),
        "posterior_missing": (["--posterior", "{d}/absent.h5"], r"absent.h5"),
        "posterior_not_hdf5": (["--posterior", "{d}/R.h5"], r"R.h5: not a readable posterior file"),
        "draws_zero": (["--draws", "0"], r"argument --draws: expected an integer in \[1, 2000\]"),
    }),
    "box": (["{d}/R.h5", "--output", "{out}/box.h5"], "box.h5", {
        "output_is_the_result": (["--output", "{d}/R.h5"], r"R.h5: is an input of this job \(.*R.h5\)"),
        "output_is_the_snapshots": (["--output", "{d}/R_fields.h5"], r"R_fields.h5: is an input of this job"),
    }),
    "mesh": (["{d}/surface/s.stl", "--output", "{out}"], "mesh", {
        **FOLDER_OUTPUT,
        "force_over_its_surface": (["--output", "{d}/surface", "--force"],
                                   r"surface: holds an input of this job .*replacing the folder would delete it"),
        "force_over_a_file": (["--output", "{d}/a_file", "--force"], r"a_file: exists and is not a folder"),
        "output_is_the_surface": (["--output", "{d}/surface/s.stl", "--force"], r"s.stl: exists and is not a folder"),
        "origin_toward_zero": (["--origin-toward", "0", "0", "0"],
                               r"argument --origin-toward: expected a nonzero direction, got 0 0 0"),
        "origin_toward_nan": (["--origin-toward", "nan", "nan", "nan"],
                              r"argument --origin-toward: expected a finite number, got 'nan'"),
        "axis_inf": (["--axis", "inf", "0", "0"], r"argument --axis: expected a finite number, got 'inf'"),
        "axis_overflow": (["--axis", "1e400", "0", "0"], r"argument --axis: expected a finite number, got '1e400'"),
        "axis_text": (["--axis", "x", "0", "0"], r"argument --axis: expected a number, got 'x'"),
        "axis_two": (["--axis", "1", "0"], r"argument --axis: expected 3 arguments"),
        "end_band_half": (["--end-band", "0.5"], r"argument --end-band: expected a number in \(0, 0.5\), got 0.5"),
        "end_band_nan": (["--end-band", "nan"], r"argument --end-band: expected a finite number, got 'nan'"),
        "end_rule": (["--end-rule", "centroid"], r"argument --end-rule: invalid choice: 'centroid'"),
        "fibers_smoothing_negative": (["--fibers-smoothing", "-1"],
                                      r"argument --fibers-smoothing: expected a number in"),
        "fibers_smoothing_nan": (["--fibers-smoothing", "nan"],
                                r"argument --fibers-smoothing: expected a finite number, got 'nan'"),
        **integer_cases("--cells", 200, 2_000_000),
    }),
}


def cases():
    for job, (_, _, own) in JOBS.items():
        for key, (options, message) in {**OUTPUT_CASES, **own}.items():
            yield pytest.param(job, options, message, id=f"{job}-{key}")


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("inputs")
    for name, text in PROTOCOL_FILES.items():
        (d / name).write_text(text)
    (d / "huge_params.toml").write_text("kM = " + "1" * 401 + "\n")
    for name, (text, _) in STUDY_FILES.items():
        (d / f"study_{name}.toml").write_text(text)
    (d / "study_good.toml").write_text(STUDY)
    for name, (text, _) in PRIOR_FILES.items():
        (d / f"priors_{name}.toml").write_text(text)
    (d / "a_file").write_text("not a folder\n")
    (d / "a_folder.toml").mkdir()
    (d / "surface").mkdir()
    (d / "surface" / "s.stl").write_text("solid s\nendsolid s\n")
    (d / "R.h5").write_text("a result\n")
    from hyper.core import io

    io.write_series(d / "posterior.h5", {"kM": [0.01, 0.012, 0.014]}, attrs={"geometry": "cylinder"})
    io.write_series(d / "kF.h5", {"kF": [0.01, 0.012]})
    (d / "R_fields.h5").write_text("its snapshots\n")
    return d


def command(job, options, inputs, out):
    base, name, _ = JOBS[job]
    fill = {"d": inputs, "out": out, "o": name, "p": "--protocol"}
    return [job, *(o.format(**fill) for o in base), *(o.format(**fill) for o in options)]


def listing(folder: Path):
    return sorted((p.name, p.stat().st_size) for p in folder.rglob("*"))


@pytest.mark.parametrize("job, options, message", list(cases()))
def test_every_job_refuses_bad_input_in_one_line_and_writes_nothing(inputs, tmp_path, capsys, job, options,
                                                                     message):
    out = tmp_path / "out"
    before = listing(inputs)
    assert cli.main(command(job, options, inputs, out)) == cli.EXIT_INPUT
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), captured.err
    assert re.search(message, lines[0]), lines[0]
    assert captured.out == ""
    assert not out.exists() and listing(inputs) == before
    assert not (ROOT / "escaped").exists()


def test_the_table_is_long_enough():
    assert len(list(cases())) >= 150


def mount_read_only(folder: Path) -> bool:
    """A read-only tmpfs on ``folder`` (root ignores a folder's mode bits, not a read-only mount)."""
    if os.geteuid() != 0:
        folder.chmod(0o555)
        return True
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m,ro", "tmpfs", str(folder)], capture_output=True)
    return done.returncode == 0


# job -> its command with {out} an existing output folder it may not write into
READ_ONLY = {
    "cohort": ["cohort", "--geometries", "cylinder", "--protocols", "mwf", "--output", "{out}"],
    "study": ["study", str(ROOT / "studies" / "paper-cohort.toml"), "--output", "{out}"],
    "calibrate": ["calibrate", "--data", str(ROOT / "data" / "defreitas.csv"), "--protocol", "mwf", "--fit", "kM",
                  "--output", "{out}"],
    "dose": ["dose", "--output", "{out}"],
    "slurm": ["slurm", "cohort", "-o", "{out}/cohort.sbatch"],
}


@pytest.mark.parametrize("job", sorted(READ_ONLY))
def test_an_output_folder_that_is_itself_read_only_is_refused_before_any_work(tmp_path, capsys, job):
    out = tmp_path / "ro"
    out.mkdir()
    if not mount_read_only(out):
        pytest.skip("cannot mount a read-only tmpfs (root ignores mode bits)")
    try:
        assert cli.main([a.format(out=out) for a in READ_ONLY[job]]) == cli.EXIT_INPUT
    finally:
        if os.geteuid() == 0:
            subprocess.run(["umount", str(out)], check=True)
        else:
            out.chmod(0o755)
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert captured.out == "" and len(lines) == 1 and "not writable" in lines[0], captured.err
    assert list(out.iterdir()) == []


def test_slurm_refuses_a_script_under_a_file_and_a_prelude_with_nul_bytes(tmp_path, capsys):
    (tmp_path / "a_file").write_text("x\n")
    (tmp_path / "nul.sh").write_bytes(b"module load a\0b\n")
    for argv, message in ((["-o", str(tmp_path / "a_file" / "x.sbatch")], "a_file is a file, not a folder"),
                          (["--prelude", str(tmp_path / "nul.sh"), "-o", str(tmp_path / "x.sbatch")], "a NUL byte"),
                          (["--prelude", str(tmp_path / "a_file"), "-o", str(tmp_path / "a_file")], "is an input")):
        assert cli.main(["slurm", "cohort", *argv]) == cli.EXIT_INPUT
        captured = capsys.readouterr()
        lines = captured.err.strip().splitlines()
        assert captured.out == "" and len(lines) == 1 and message in lines[0], captured.err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "nul.sh"]


# ------------------------------------------------------- files that are not what they say

# Text inputs that are not UTF-8 (`hyper.core.params.read_text`) and result or field files
# that HDF5 or XML cannot read (`hyper.core.io.reading_h5`, `read_xml`), for every job that
# reads them: the same one line and nothing written. {d}: the folder of `damaged_inputs`.
CALIBRATE = ["calibrate", "--protocol", "mwf", "--fit", "kM", "--output", "{out}", "--data"]
GROW = ["grow", "--geometry", "cylinder", "--protocol", "mwf", "--output", "{out}/run.h5", "--data"]
BINARY = r"binary.csv: not text: a NUL byte at byte offset 8"
UTF16 = r"utf16.csv: UTF-16 text \(a byte order mark at byte 0\); save it as UTF-8"
LATIN1 = r"latin1.csv: not UTF-8 text: byte 0xe9 at byte offset 13"
FILE_CASES = {
    "calibrate-data_binary": ([*CALIBRATE, "{d}/binary.csv"], BINARY),
    "calibrate-data_utf16": ([*CALIBRATE, "{d}/utf16.csv"], UTF16),
    "calibrate-data_latin1": ([*CALIBRATE, "{d}/latin1.csv"], LATIN1),
    "grow-data_binary": ([*GROW, "{d}/binary.csv"], BINARY),
    "grow-data_utf16": ([*GROW, "{d}/utf16.csv"], UTF16),
    "study-data_binary": (["study", "{d}/data_binary.toml", "--output", "{out}"], r"data.file: .*" + BINARY),
    "study-data_utf16": (["study", "{d}/data_utf16.toml", "--output", "{out}"], r"data.file: .*" + UTF16),
    "study-data_option_latin1": (["study", "{d}/study.toml", "--data", "{d}/latin1.csv", "--output", "{out}"],
                                 LATIN1),
    "study-file_utf16": (["study", "{d}/utf16.toml", "--output", "{out}"], r"utf16.toml: UTF-16 text"),
    "signaling-protocol_utf16": (["signaling", "--protocol", "{d}/utf16.toml", "--output", "{out}"],
                                 r"utf16.toml: UTF-16 text"),
    "signaling-params_binary": (["signaling", "--params", "{d}/binary.toml", "--output", "{out}"],
                                r"binary.toml: not text: a NUL byte"),
    "slurm-prelude_binary": (["slurm", "cohort", "--prelude", "{d}/binary.csv", "-o", "{out}/s.sbatch",
                              "--workdir", "{d}"], r"--prelude .*" + BINARY),
    "inspect-damaged": (["inspect", "{d}/damaged.h5"], r"damaged.h5: not a readable HDF5 result file \("),
    "inspect-truncated": (["inspect", "{d}/truncated.h5"], r"truncated.h5: not a readable HDF5 result file"),
    "inspect-text": (["inspect", "{d}/binary.csv"], r"binary.csv: not a readable HDF5 result file"),
    "inspect-folder": (["inspect", "{d}"], r"is a folder, not an HDF5 result file"),
    "box-damaged": (["box", "{d}/damaged.h5"], r"damaged.h5: not a readable HDF5 result file \("),
    "box-fields_binary": (["box", "{d}/binary_fields/run.h5"], r"run_fields.xdmf: not text: a NUL byte"),
    "box-fields_utf16": (["box", "{d}/utf16_fields/run.h5"], r"run_fields.xdmf: UTF-16 text"),
    "box-fields_without_time": (["box", "{d}/timeless_fields/run.h5"], r"run_fields.xdmf: a <Grid> without <Time>"),
    "box-fields_not_xml": (["box", "{d}/garbled_fields/run.h5"], r"run_fields.xdmf: not a well-formed XDMF file"),
    "contraction-petsc_refused": (["contraction", "--geometry", "cylinder", "--output", "{out}/c.h5",
                                   "-mechanics_snes_type", "bogus"],
                                  r"^error: PETSc refused -mechanics_snes_type bogus: Unable to find requested SNES"),
}
STUDY = 'geometries = ["cylinder"]\nprotocols = ["mwf"]\n'
FIELDS = """<?xml version="1.0"?>
<Xdmf Version="3.0"><Domain><Grid Name="fields" GridType="Collection" CollectionType="Temporal">
<Grid Name="fields" GridType="Uniform">
  <Geometry GeometryType="XYZ"><DataItem Dimensions="2 3" Format="HDF">run_fields.h5:/x</DataItem></Geometry>
  {time}<Attribute Name="u" AttributeType="Vector" Center="Node">
    <DataItem Dimensions="2 3" Format="HDF">run_fields.h5:/u</DataItem></Attribute>
</Grid></Grid></Domain></Xdmf>
"""


@pytest.fixture(scope="module")
def damaged_inputs(tmp_path_factory):
    import h5py
    import numpy as np

    from hyper.core import io

    d = tmp_path_factory.mktemp("damaged")
    csv = "week,csa\n0,10.0\n3,10.5\n"
    (d / "binary.csv").write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR")
    (d / "utf16.csv").write_bytes(csv.encode("utf-16"))
    (d / "latin1.csv").write_bytes("week,csa\n0,10\u00e9\n".encode("latin-1"))
    (d / "binary.toml").write_bytes(b"kM = 0.01\n\x00\x01")
    (d / "utf16.toml").write_bytes(STUDY.encode("utf-16"))
    (d / "study.toml").write_text(STUDY)
    (d / "data_binary.toml").write_text(STUDY + '[data]\nfile = "binary.csv"\n')
    (d / "data_utf16.toml").write_text(STUDY + '[data]\nfile = "utf16.csv"\n')
    good = io.write_series(d / "good.h5", {"t": np.arange(2000.0), "csa_ratio": np.ones(2000)},
                           attrs={"geometry": "cylinder"})
    data = bytearray(good.read_bytes())
    data[800:len(data) - 100] = bytes(len(data) - 900)  # the middle zeroed, the size kept
    (d / "damaged.h5").write_bytes(bytes(data))
    (d / "truncated.h5").write_bytes(good.read_bytes()[: len(data) // 2])
    for name, xdmf in {"binary": b"\x89HDF\r\n\x1a\n\x00\x00", "utf16": FIELDS.format(time="").encode("utf-16"),
                       "timeless": FIELDS.format(time="").encode(),
                       "garbled": FIELDS.format(time='<Time Value="0"/>').encode()[:-30]}.items():
        folder = d / f"{name}_fields"
        folder.mkdir()
        io.write_series(folder / "run.h5", {"t": np.array([0.0]), "csa_ratio_box": np.ones(1)},
                        attrs={"geometry": "cylinder"})
        with h5py.File(folder / "run_fields.h5", "w") as f:
            f["x"], f["u"] = np.eye(2, 3), np.zeros((2, 3))
        (folder / "run_fields.xdmf").write_bytes(xdmf)
    return d


@pytest.mark.parametrize("argv, message", list(FILE_CASES.values()), ids=list(FILE_CASES))
def test_every_job_refuses_a_file_that_is_not_what_it_says_in_one_line(damaged_inputs, tmp_path, capsys, argv,
                                                                         message):
    import re

    out = tmp_path / "out"
    before = listing(damaged_inputs)
    assert cli.main([a.format(d=damaged_inputs, out=out) for a in argv]) == cli.EXIT_INPUT
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), captured.err
    assert re.search(message, lines[0]), lines[0]
    assert "--petsc-option" not in lines[0] and captured.out == ""
    assert not out.exists() and listing(damaged_inputs) == before


# ------------------------------------------------------------------------- 2 ranks

MPI_CASES = [
    ("grow", ["--geometry", "cylinder", "--protocol", "mwf", "--output", "{d}/a_file/run.h5"], "a_file is a file"),
    ("grow", ["--geometry", "cylinder", "--protocol", "mwf", "--output", "{out}/run.h5", "--petsc-option",
              "snes_maxit=3"], "PETSc does not read snes_maxit"),
    ("cohort", ["--geometries", "cylinder", "--output", "{d}/a_file"], "exists and is not a folder"),
    ("ensemble", ["--geometry", "cylinder", "--output", "/proc/ensemble"], "under /proc"),
    ("sobol", ["--samples", "4", "--output", "{d}/a_file/sobol"], "a_file is a file"),
    ("signaling", ["--protocol", "{d}/climbs_out.toml", "--output", "{out}"], "name must be"),
    ("fibers", ["--geometries", "TA_VHF_Left", "--output", "{d}/a_file"], "exists and is not a folder"),
]


@pytest.mark.parametrize("job, options, message", MPI_CASES, ids=[f"{c[0]}-{i}" for i, c in enumerate(MPI_CASES)])
def test_no_job_leaves_a_rank_waiting_on_bad_input(inputs, tmp_path, job, options, message):
    """Under mpirun -n 2 every rank stops at once: exit 2, one error line (rank 0's)."""
    out = tmp_path / "out"
    argv = [o.format(d=inputs, out=out) for o in options]
    mpirun = str(Path(sys.executable).parent / "mpirun")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run([mpirun, "-n", "2", sys.executable, "-m", f"hyper.{job}", *argv], cwd=ROOT, env=env,
                            capture_output=True, text=True, timeout=120)
    lines = [line for line in result.stderr.splitlines() if line.startswith("error: ")]
    assert result.returncode == cli.EXIT_INPUT, result.stderr
    assert len(lines) == 1 and message in lines[0], result.stderr
    assert not out.exists()


# job -> its command, {out} the output whose lock another run holds
LOCKED = {
    "signaling": ["--protocol", "mwf", "--output", "{out}"],
    "sobol": ["--samples", "4", "--output", "{out}"],
    "cohort": ["--geometries", "cylinder", "--protocols", "mwf", "--output", "{out}"],
    "ensemble": ["--geometry", "cylinder", "--samples", "1", "--output", "{out}"],
    "contraction": ["--geometry", "cylinder", "--output", "{out}.h5"],
    "meshstats": ["--geometries", "TA_VHF_Left", "--output", "{out}.csv"],
    "fibers": ["--geometries", "TA_VHF_Left", "--output", "{out}"],
    "dose": ["--output", "{out}"],
    "design": ["--target", "5", "--week", "8", "--no-check", "--output", "{out}"],
    "calibrate": ["--data", str(ROOT / "data" / "defreitas.csv"), "--protocol", "mwf", "--fit", "kM",
                  "--output", "{out}"],
}


@pytest.mark.parametrize("job", sorted(LOCKED))
def test_every_job_that_writes_stops_at_once_on_an_output_another_run_holds(tmp_path, capsys, job):

    out = tmp_path / "out"
    argv = [a.format(out=out) for a in LOCKED[job]]
    held = argv[argv.index("--output") + 1]
    if job == "ensemble":  # an ensemble writes, and locks, its label's folder
        held = str(out / "cylinder_mwf" / "uniform-noise_eps0.01")
    if job == "signaling":  # signaling locks each result file
        held = str(out / "mwf.h5")
    lock = locks.OutputLock(Path(held))
    assert lock.acquire()
    try:
        assert cli.main([job, *argv]) == cli.EXIT_BUSY
    finally:
        lock.release()
    assert "another run is writing this output" in capsys.readouterr().err
    assert not out.exists() or not any(p.suffix in (".h5", ".csv", ".png", ".json") for p in out.rglob("*"))


def test_a_term_reaches_the_run_when_petsc_starts_after_the_handler():
    """PETSc's own SIGTERM handler aborts the process; a job that starts PETSc after it
    installed run.StopOnTerm (the farm imports DOLFINx late) must still get a stop flag.
    A fresh process, as PETSc in this one started long ago."""
    code = ("import os, signal\nfrom hyper.runs.driver import StopOnTerm\n"
            "with StopOnTerm() as stop:\n"
            "    import dolfinx_solver\n    from petsc4py import PETSc\n"
            "    os.kill(os.getpid(), signal.SIGTERM)\n"
            "    assert stop(), 'the TERM did not reach StopOnTerm'\n"
            "print('stopped')\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout == "stopped\n", done.stderr


def test_a_term_stops_a_sobol_job_with_its_chunks_kept(tmp_path):
    """What Slurm's warning does to `hyper sobol` on two ranks (two farm groups, whose
    first DOLFINx import starts PETSc late): exit 143 with the finished chunks on disk,
    not PETSc's abort, which test_slurm_real.py caught once. mpirun passes the TERM on."""
    import signal
    import time

    chunks = tmp_path / "sobol" / "chunks"
    mpirun = str(Path(sys.executable).parent / "mpirun")
    command = [mpirun, "-n", "2", sys.executable, "-m", "hyper.sobol", "--samples", "32", "--chunk", "16",
               "--output", str(tmp_path / "sobol"), "--quiet"]
    job = subprocess.Popen(command, cwd=ROOT, stderr=subprocess.PIPE, text=True,
                           env={**os.environ, "OMP_NUM_THREADS": "1"})
    try:
        end = time.monotonic() + 60
        while not list(chunks.glob("*/*.npz")):  # 60 chunks, about 0.15 s each
            assert job.poll() is None and time.monotonic() < end, "no chunk written"
            time.sleep(0.05)
        job.send_signal(signal.SIGTERM)
        rc, stderr = job.wait(timeout=60), job.stderr.read()
    finally:
        job.kill()
    assert rc == cli.EXIT_TERMINATED, stderr
    assert 1 <= len(list(chunks.glob("*/*.npz"))) < 60


# ------------------------------------------------------------------ the mechanisms
# One reader per class of input (hyper.core.params), tested as such; the table above shows
# that the jobs use them, the properties below that they hold for any malformed value.

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from hyper.core.params import InputError, as_float, as_int, as_seed, as_vector, float_text, int_text  # noqa: E402


def test_the_numeric_reader_refuses_what_a_float64_or_int64_cannot_hold_and_names_the_key():
    assert as_float(3, "k") == 3.0 and type(as_float(3, "k")) is float
    assert as_float(0.5, "k", least=0, most=1) == 0.5
    for value, message in [(10**400, "k: expected a finite number, got an integer of 401 digits"),
                           (math.nan, "k: expected a finite number, got nan"), (-math.inf, "got -inf"),
                           ("1", "k: expected a number, got '1'"), (True, "k: expected a number, got True"),
                           (None, "expected a number, got None")]:
        with pytest.raises(InputError, match=re.escape(message)):
            as_float(value, "k")
    for kw, message in [({"least": 0}, ">= 0"), ({"above": 0}, "> 0"), ({"least": 0, "below": 1}, "in [0, 1)"),
                        ({"most": -2}, "<= -2")]:
        with pytest.raises(InputError, match=re.escape(f"k: expected a number {message}, got -1")):
            as_float(-1, "k", **kw)
    assert as_int(2**63 - 1, "n") == 2**63 - 1
    for value, message in [(2**63, "fits in 64 bits"), (-(2**63) - 1, "fits in 64 bits"), (2.0, "integer, got 2.0"),
                           (False, "integer, got False"), ("3", "integer, got '3'")]:
        with pytest.raises(InputError, match=re.escape(message)):
            as_int(value, "n")
    with pytest.raises(InputError, match=re.escape("n: expected an integer in [1, 12], got 13")):
        as_int(13, "n", 1, 12)
    # the field a message names is where the number was given, so build() can name the option
    with pytest.raises(InputError) as err:
        as_float(math.inf, "growth_dt")
    assert err.value.field == "growth_dt"


def test_a_seed_is_an_integer_that_numpy_salib_and_hdf5_all_take():
    assert as_seed(0, "seed") == 0 and as_seed(2**32 - 1, "seed") == 2**32 - 1
    for bad in (-1, 2**32, 10**400, 1.0, "1"):
        with pytest.raises(InputError, match="seed: expected an integer"):
            as_seed(bad, "seed")


def test_option_text_is_read_by_the_same_reader():
    assert float_text("1e-3", "--x") == 1e-3 and int_text("-7", "--n") == -7
    for text, message in [("1e400", "expected a finite number, got '1e400'"), ("nan", "finite"),
                          ("fast", "expected a number, got 'fast'"), ("9" * 5000, "(5002 characters)")]:
        with pytest.raises(InputError, match=re.escape(message)):
            float_text(text, "--x")
    for text in ("2.5", "1e3", "1" * 5000, "", "0x10"):
        with pytest.raises(InputError, match="expected an integer"):
            int_text(text, "--n")
    with pytest.raises(InputError, match="expected an integer that fits in 64 bits"):
        int_text(str(2**64), "--n")


def test_the_vector_reader_gives_a_unit_direction_or_refuses():
    assert as_vector([0, 0, 2], "--axis") == (0.0, 0.0, 1.0)
    assert as_vector([3, 4, 0], "--axis") == pytest.approx((0.6, 0.8, 0.0), abs=1e-16)
    assert as_vector([1e300, 1e300, 0], "--axis") == pytest.approx((2**-0.5, 2**-0.5, 0.0))  # no overflow
    assert as_vector([5e-324, 0, 0], "--axis") == (1.0, 0.0, 0.0)  # no underflow
    for bad, message in [([0, 0, 0], "nonzero direction"), ([math.nan, 0, 0], "finite"), ([math.inf, 0, 0], "finite"),
                         ([1, 0], "3 components"), ([1, 0, 0, 0], "3 components"), (["x", 0, 0], "a number")]:
        with pytest.raises(InputError, match=message):
            as_vector(bad, "--axis")


def test_a_repeat_rule_counts_its_sessions_before_it_builds_them(monkeypatch):
    from hyper.model import protocols

    for rule in (protocols.Repeat(1.0, 0.5, 3, every_days=2.5, lead_in_days=1.5),
                 protocols.Repeat(1.0, 0.5, 2, weekdays=("mon", "thu")), protocols.Repeat(1.0, 0.5, 1, every_days=7)):
        assert rule.count() == len(rule.protocol("r").sessions)
    built = []
    monkeypatch.setattr(protocols, "Session", lambda *a: built.append(a))  # nothing may be built
    with pytest.raises(InputError, match="sessions, more than 100000"):
        protocols.Repeat(1e-12, 0.5, 520, every_days=1e-9)
    assert built == []


def test_a_sobol_file_s_names_are_checked_where_it_is_read(tmp_path):
    from hyper.analysis import sobol

    path = tmp_path / "p.toml"
    for text, message in [('names = ["bogus"]\n', "names: expected distinct parameters"),
                          ('function = "signaling"\nnames = ["hill_n"]\n', "got hill_n"),
                          ('names = ["kM", "kM"]\n', "expected distinct"),
                          ('names = ["kM"]\nbounds = [[2, 1]]\n', "bounds: kM: expected 0 < lower < upper")]:
        path.write_text(text)
        with pytest.raises(InputError, match=message):
            sobol.read_config(path)
    path.write_text('names = ["kM", "hill_n"]\n')  # no function: --function csa-gain may still choose it
    assert sobol.read_config(path)["names"] == ["kM", "hill_n"]


# Property-based: any malformed value of any numeric key or option is refused as bad input.
# Parse-level only (no job gets as far as its work); derandomized, so every run draws alike.
PROPERTY = settings(max_examples=30, derandomize=True, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture])
HUGE_INTS = st.one_of(st.integers(min_value=2**1100, max_value=2**1300), st.integers(max_value=-(2**1100)))
NOT_NUMBERS = st.one_of(st.text(max_size=8).filter(lambda t: not _parses(t)), st.booleans(), st.just([1.0]))
NON_FINITE = st.sampled_from([math.nan, math.inf, -math.inf])
NEGATIVE = st.one_of(st.integers(max_value=-1), st.floats(max_value=-1e-9, allow_nan=False, allow_infinity=False))


def _parses(text):
    try:
        float(text)
        return True
    except ValueError:
        return False


def toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, str):
        return '"' + "".join(c if c.isalnum() or c in " .-_" else "" for c in value) + '"'
    return repr(value) if isinstance(value, float) else str(value) if isinstance(value, int) else "[1.0]"


# (the section's text before the key, the key, whether a negative value is bad too)
STUDY_KEYS = [
    ("[numerics]", "growth_dt", True), ("[numerics]", "signaling_dt", True), ("[numerics]", "accuracy", True),
    ("[numerics]", "max_halvings", True), ("[numerics]", "quadrature_degree", True), ("[numerics]", "refine", True),
    ("[output]", "snapshot_every", True), ("[signaling]", "a10", True), ("[material]", "c1", True),
    ("[heterogeneity]\nseed = 1", "epsilon", True), ("[heterogeneity]", "seed", True),
    ('[heterogeneity]\nmodel = "matern"\nseed = 1', "length", True),
    ("[sobol]", "at", True), ("[sobol]", "samples", True), ('[sobol]\nnames = ["kM"]', "num_vars", True),
    ('[[protocol]]\nname = "r"\n[protocol.repeat]\nduration = 1\nintensity = 0.5\nweeks = 1', "every_days", True),
    ('[[protocol]]\nname = "r"\n[protocol.repeat]\nevery_days = 2\nintensity = 0.5\nweeks = 1', "duration", True),
    ('[[protocol]]\nname = "r"\n[protocol.repeat]\nevery_days = 2\nduration = 1\nintensity = 0.5', "weeks", True),
    ('[[protocol]]\nname = "r"\n[protocol.repeat]\nweekdays = ["mon"]\nduration = 1\nintensity = 0.5\nweeks = 1',
     "lead_in_days", True),
]


def refused(capsys, argv, out):
    """The job's answer to ``argv`` is bad input: exit 2, one error line, nothing else, nothing written."""
    code = cli.main(argv)
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert code == cli.EXIT_INPUT and len(lines) == 1 and lines[0].startswith("error: "), (argv, captured.err)
    assert captured.out == "" and not out.exists(), argv


@PROPERTY
@given(where=st.sampled_from(STUDY_KEYS), data=st.data())
def test_any_malformed_number_in_a_study_file_is_refused(tmp_path, capsys, where, data):
    section, key, positive = where
    bad = data.draw(st.one_of(HUGE_INTS, NOT_NUMBERS, NON_FINITE, *([NEGATIVE] if positive else [])))
    base = 'geometries = ["cylinder"]\n' + ("" if section.startswith("[[protocol]]") else 'protocols = ["mwf"]\n')
    path = tmp_path / "s.toml"
    path.write_text(f"{base}{section}\n{key} = {toml_value(bad)}\n")
    refused(capsys, ["study", str(path), "--output", str(tmp_path / "out")], tmp_path / "out")


# (job, its command, the option, whether a negative value is bad too); {out} its output
OPTIONS = [
    *[("study", ["{study}"], o, True) for o in ("--growth-dt", "--signaling-dt", "--accuracy", "--max-halvings",
                                                "--snapshot-every", "--quadrature-degree", "--refine")],
    *[("signaling", ["--protocol", "mwf"], o, True) for o in ("--signaling-dt", "--sample-every")],
    *[("sobol", [], o, True) for o in ("--samples", "--at", "--seed", "--chunk", "--resamples", "--signaling-dt")],
    *[("ensemble", ["--geometry", "cylinder"], o, True) for o in ("--epsilon", "--samples", "--first-seed", "--nu",
                                                                  "--growth-dt")],
    *[("cohort", ["--geometries", "cylinder"], o, True) for o in ("--growth-dt", "--max-halvings", "--refine")],
    ("dose", [], "--seed", True), ("dose", [], "--accuracy", False), ("dose", [], "--budgets", True),
    *[("design", ["--target", "5", "--week", "8"], o, True) for o in ("--target", "--week", "--draws")],
    *[("contraction", ["--geometry", "cylinder"], o, True) for o in ("--steps", "--refine")],
    ("mesh", ["{surface}"], "--end-band", True), ("mesh", ["{surface}"], "--cells", True),
]


@PROPERTY
@given(where=st.sampled_from(OPTIONS), data=st.data())
def test_any_malformed_number_in_an_option_is_refused(tmp_path, capsys, where, data):
    job, base, option, positive = where
    bad = data.draw(st.one_of(HUGE_INTS.map(str), st.sampled_from(["nan", "inf", "-inf", "1e400", "-1e400"]),
                              st.text(max_size=8).filter(lambda t: not _parses(t) and not t.startswith("-")),
                              *([NEGATIVE.map(str)] if positive else [])))
    study = tmp_path / "s.toml"
    study.write_text('geometries = ["cylinder"]\nprotocols = ["mwf"]\n')
    out = tmp_path / "out"
    fill = {"study": str(study), "surface": str(tmp_path / "absent.stl")}
    argv = [job, *(a.format(**fill) for a in base), "--output", str(out if job != "contraction" else out / "c.h5")]
    refused(capsys, [*argv, f"{option}={bad}"], out)


@PROPERTY
@given(components=st.lists(st.one_of(st.sampled_from(["nan", "inf", "-inf", "1e400", "x", ""]),
                                     st.just("0")), min_size=3, max_size=3))
def test_any_malformed_direction_is_refused(tmp_path, capsys, components):
    """Each component is not a finite number, or all three are zero."""
    out = tmp_path / "out"
    for option in ("--axis", "--origin-toward"):
        refused(capsys, ["mesh", str(tmp_path / "absent.stl"), "--output", str(out), option, *components], out)


def every_parser():
    """(name, parser) of every job and benchmark, with the subcommands' parsers."""
    import importlib

    from hyper.commands import bench

    found = [(job, importlib.import_module(f"hyper.commands.{job}").parser()) for job in cli.JOBS if job != "bench"]
    found += [(f"bench {name}", importlib.import_module(f"hyper.commands.bench.{name}").parser())
              for name in bench.available()]
    for name, parser in list(found):
        for action in parser._actions:
            for sub, subparser in getattr(action, "_name_parser_map", {}).items():
                found.append((f"{name} {sub}", subparser))
    return found


def test_every_numeric_option_of_every_job_is_read_by_the_numeric_reader():
    """The property tests draw from some options; this holds the rest to the same reader:
    no option of any job or benchmark reads numbers with a bare float() or int()."""
    def bare(parsers):
        return [f"{name} {action.option_strings}" for name, parser in parsers for action in parser._actions
                if action.type in (float, int)]

    loose = cli.Parser("loose")
    loose.add_argument("--dt", type=float)
    assert bare([("loose", loose)]) == ["loose ['--dt']"]  # the check sees a bare float
    parsers = every_parser()
    assert len(parsers) > len(cli.JOBS)
    assert bare(parsers) == []
