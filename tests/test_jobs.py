"""The Slurm templates in jobs/: rendered, syntax-checked, and run with a fake srun.

With a responding Slurm controller, ``sbatch --test-only`` checks the scripts too.
"""

import os
import re
import shutil
import signal
import subprocess
import sys
import time

import pytest

from hyper import io, slurm
from hyper.params import InputError

KINDS = ("cohort", "grow-array", "sobol")
COMMAND = {"cohort": "hyper.cohort", "grow-array": "hyper.grow", "sobol": "hyper.sobol"}
SBATCH_LINE = re.compile(r"#SBATCH --([a-z][a-z-]*)(?:=(\S+))?")


def render(kind, tmp_path, *options):
    script = tmp_path / f"{kind}.sbatch"
    rc = slurm.main([kind, "-o", str(script), "--workdir", str(tmp_path), "--log-dir", "logs", *options])
    assert rc == 0
    return script


def sbatch_options(text):
    options = {}
    for line in text.splitlines():
        if line.startswith("#SBATCH"):
            m = SBATCH_LINE.fullmatch(line)
            assert m, f"malformed: {line!r}"
            options[m.group(1)] = m.group(2)
    return options


@pytest.fixture
def fake_slurm(tmp_path, monkeypatch):
    """srun and scontrol stand-ins that record their arguments in tmp_path/fake."""
    fake = tmp_path / "fake"
    fake.mkdir()
    (fake / "srun").write_text('#!/bin/bash\necho "$@" > "$FAKE/srun.args"\nexec sleep "${FAKE_SLEEP:-0}"\n')
    (fake / "scontrol").write_text('#!/bin/bash\necho "$@" >> "$FAKE/scontrol.args"\n')
    for tool in ("srun", "scontrol"):
        (fake / tool).chmod(0o755)
    env = dict(os.environ, PATH=f"{fake}:{os.environ['PATH']}", FAKE=str(fake),
               SLURM_JOB_ID="4242", SLURM_JOB_NODELIST="node1")
    env.pop("SLURM_RESTART_COUNT", None)
    return fake, env


@pytest.mark.parametrize("kind", KINDS)
def test_template_renders_to_a_valid_script(kind, tmp_path):
    text = render(kind, tmp_path).read_text()
    assert not slurm.placeholders(text) and not re.search(r"\{[a-z][a-z0-9_]*\}", text)
    subprocess.run(["bash", "-n", str(tmp_path / f"{kind}.sbatch")], check=True)
    options = sbatch_options(text)
    assert {"job-name", "ntasks", "time", "chdir", "output", "signal", "requeue"} <= set(options)
    assert re.fullmatch(r"B:TERM@\d+", options["signal"]) and options["requeue"] is None
    assert options["chdir"] == str(tmp_path) and (tmp_path / "logs").is_dir()
    assert "export OMP_NUM_THREADS=1" in text
    assert f"source {sys.prefix}/bin/activate" in text
    assert f"srun --mpi=pmi2 python -m {COMMAND[kind]} " in text
    if kind == "grow-array":
        assert options["array"] == "0-35"  # 12 geometries x 3 protocols
    if kind == "sobol":
        assert "--samples 10000 --output results/sobol" in text


def test_array_index_selects_its_run(tmp_path, fake_slurm):
    fake, env = fake_slurm
    script = render("grow-array", tmp_path, "--max-parallel", "4")
    assert sbatch_options(script.read_text())["array"] == "0-35%4"
    runs = slurm.cohort_runs(None, None)
    assert len(runs) == 36 and len(set(runs)) == 36
    for index in (0, 17, 35):
        subprocess.run(["bash", str(script)], cwd=tmp_path, check=True, capture_output=True,
                       env=dict(env, SLURM_ARRAY_TASK_ID=str(index)))
        geometry, protocol = runs[index]
        args = (fake / "srun.args").read_text().split()
        assert args[:6] == ["--mpi=pmi2", "python", "-m", "hyper.grow", "--geometry", geometry]
        assert args[6:10] == ["--protocol", protocol, "--output", "results/grow"]
    # A task whose result is complete does not run again.
    (fake / "srun.args").unlink()
    io.write_series(tmp_path / "results/grow" / f"{runs[17][0]}_{runs[17][1]}.h5", {"t": [0.0]})
    done = subprocess.run(["bash", str(script)], cwd=tmp_path, check=True, capture_output=True, text=True,
                          env=dict(env, SLURM_ARRAY_TASK_ID="17"))
    assert "is complete: nothing to do" in done.stdout and not (fake / "srun.args").exists()


@pytest.mark.parametrize("restarts, requeued", [(None, True), ("3", False)])
def test_term_before_the_limit_requeues(tmp_path, fake_slurm, restarts, requeued):
    fake, env = fake_slurm
    script = render("cohort", tmp_path, "--ntasks", "4", "--ranks-per-job", "2", "--args", "--protocols mwf")
    env = dict(env, FAKE_SLEEP="60")
    if restarts is not None:
        env["SLURM_RESTART_COUNT"] = restarts
    job = subprocess.Popen(["bash", str(script)], cwd=tmp_path, env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    for _ in range(200):  # until the fake srun runs
        if (fake / "srun.args").exists():
            break
        time.sleep(0.05)
    job.send_signal(signal.SIGTERM)
    out, _ = job.communicate(timeout=30)
    assert job.returncode == 143, out
    assert (fake / "srun.args").read_text().split() == [
        "--mpi=pmi2", "python", "-m", "hyper.cohort", "--ranks-per-job", "2",
        "--output", "results/cohort", "--protocols", "mwf"]
    assert "time limit near" in out
    scontrol = fake / "scontrol.args"
    assert (scontrol.read_text() == "requeue 4242\n") if requeued else not scontrol.exists()


def test_stale_jit_locks_are_removed(tmp_path, fake_slurm):
    # A lock older than a minute without its .c.cached mark is a compile that was killed.
    fake, env = fake_slurm
    cache = tmp_path / "cache" / "fenics"
    cache.mkdir(parents=True)
    old = time.time() - 300
    for name in ("stale.c", "done.c", "done.c.cached", "fresh.c"):
        (cache / name).touch()
        if name != "fresh.c":
            os.utime(cache / name, (old, old))
    script = render("sobol", tmp_path)
    subprocess.run(["bash", str(script)], cwd=tmp_path, check=True, capture_output=True,
                   env=dict(env, XDG_CACHE_HOME=str(tmp_path / "cache")))
    assert sorted(p.name for p in cache.iterdir()) == ["done.c", "done.c.cached", "fresh.c"]


def test_render_checks_values(tmp_path, capsys):
    with pytest.raises(InputError, match="no value for placeholder"):
        slurm.render("a {x} b {y}", {"x": 1})
    with pytest.raises(InputError, match="no placeholder for value"):
        slurm.render("a {x}", {"x": 1, "z": 2})
    assert slurm.render("${RUNS[$I]} {x}", {"x": 7}) == "${RUNS[$I]} 7"
    base = ["-o", str(tmp_path / "s.sbatch"), "--workdir", str(tmp_path)]
    for bad, message in [
        (["cohort", "--time", "2 hours"], "not a Slurm time"),
        (["cohort", "--ntasks", "4", "--ranks-per-job", "3"], "must divide"),
        (["cohort", "--output", "my results"], "without spaces"),
        (["grow-array", "--geometries", "BFLH_XYZ"], "unknown geometry"),
        (["grow-array", "--protocols", "hourly"], "unknown protocol"),
        (["sobol", "--samples", "0"], "--samples"),
    ]:
        assert slurm.main([*bad[:1], *base, *bad[1:]]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "s.sbatch").exists()


def slurm_controller_responds() -> bool:
    if not (shutil.which("sbatch") and shutil.which("scontrol")):
        return False
    try:
        return subprocess.run(["scontrol", "ping"], capture_output=True, timeout=10).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


@pytest.mark.skipif(not slurm_controller_responds(), reason="no responding Slurm controller")
@pytest.mark.parametrize("kind", KINDS)
def test_sbatch_test_only_accepts(kind, tmp_path):
    script = render(kind, tmp_path, "--ntasks", "1", "--time", "10:00")
    done = subprocess.run(["sbatch", "--test-only", str(script)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert "to start at" in done.stderr
