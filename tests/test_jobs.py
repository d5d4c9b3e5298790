"""The Slurm templates in jobs/: rendered, syntax-checked, and run with stand-ins for
srun, scancel and scontrol. tests/test_slurm_real.py runs them on a real Slurm."""

import mmap
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hyper.commands import slurm
from hyper.core import io
from hyper.core.params import InputError

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


FAKE_TOOLS = {
    # Like the real srun (checked against it in test_slurm_real.py): a TERM sent to srun
    # kills its tasks (SIGKILL) and srun exits with 137; otherwise srun exits as its task.
    "srun": """#!/bin/bash
echo "$@" > "$FAKE/srun.args"
"$FAKE/task" &
TASK=$!
echo "$TASK" > "$FAKE/task.pid"
trap 'echo "srun: forcing job termination"; kill -KILL "$TASK"; exit 137' TERM
wait "$TASK"
""",
    # The run: FAKE_SLEEP seconds of work; on TERM it notes it and exits with FAKE_TERM_RC
    # (143, as hyper's jobs do after their checkpoint).
    "task": """#!/bin/bash
trap 'echo TERM > "$FAKE/task.term"; exit "${FAKE_TERM_RC:-143}"' TERM
for _ in $(seq "$((${FAKE_SLEEP:-0} * 10))"); do sleep 0.1; done
""",
    # `scancel --signal=SIG JOB`, as Slurm does it: the signal goes to the steps' tasks.
    "scancel": """#!/bin/bash
echo "$@" >> "$FAKE/scancel.args"
kill -"${1#--signal=}" "$(cat "$FAKE/task.pid")"
""",
    "scontrol": """#!/bin/bash
echo "$@" >> "$FAKE/scontrol.args"
""",
}


@pytest.fixture
def fake_slurm(tmp_path):
    """srun, scancel and scontrol stand-ins that record their arguments in tmp_path/fake."""
    fake = tmp_path / "fake"
    fake.mkdir()
    for tool, text in FAKE_TOOLS.items():
        (fake / tool).write_text(text)
        (fake / tool).chmod(0o755)
    env = dict(os.environ, PATH=f"{fake}:{os.environ['PATH']}", FAKE=str(fake),
               SLURM_JOB_ID="4242", SLURM_JOB_NODELIST="node1")
    env.pop("SLURM_RESTART_COUNT", None)
    return fake, env


def wait_for(path, timeout=10.0):
    end = time.monotonic() + timeout
    while not path.exists():
        assert time.monotonic() < end, f"{path} did not appear within {timeout} s"
        time.sleep(0.05)


@pytest.mark.parametrize("kind", KINDS)
def test_template_renders_to_a_valid_script(kind, tmp_path):
    text = render(kind, tmp_path).read_text()
    assert not slurm.placeholders(text) and not re.search(r"\{[a-z][a-z0-9_]*\}", text)
    subprocess.run(["bash", "-n", str(tmp_path / f"{kind}.sbatch")], check=True)
    options = sbatch_options(text)
    assert {"job-name", "ntasks", "time", "chdir", "output", "signal", "requeue"} <= set(options)
    # Slurm's warning goes to the batch script alone; it passes TERM to the ranks (scancel)
    assert re.fullmatch(r"B:USR1@\d+", options["signal"]) and options["requeue"] is None
    assert 'scancel --signal=TERM "$SLURM_JOB_ID"' in text and "kill -TERM" not in text
    assert options["chdir"] == str(tmp_path) and (tmp_path / "logs").is_dir()
    assert "export OMP_NUM_THREADS=1" in text
    assert f"source {sys.prefix}/bin/activate" in text
    assert f"srun --mpi=pmi2 python -m {COMMAND[kind]} " in text
    if kind == "grow-array":
        assert options["array"] == "0-35"  # 12 geometries x 3 protocols
    if kind == "sobol":
        assert "--samples 8192 --output results/sobol" in text


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


def test_stand_in_srun_kills_its_task_on_term(tmp_path, fake_slurm):
    # What the old scripts did (kill -TERM "$PID" to srun): the task dies without its TERM handler.
    fake, env = fake_slurm
    srun = subprocess.Popen([str(fake / "srun"), "python"], env=dict(env, FAKE_SLEEP="30"),
                            stdout=subprocess.PIPE, text=True)
    wait_for(fake / "task.pid")
    time.sleep(0.2)  # the trap is set right after task.pid is written
    srun.send_signal(signal.SIGTERM)
    out, _ = srun.communicate(timeout=30)
    assert srun.returncode == 137 and "forcing job termination" in out
    assert not (fake / "task.term").exists()


@pytest.mark.parametrize("restarts, term_rc, requeued", [(None, 143, True), ("3", 143, False), (None, 3, False)])
def test_warning_stops_the_ranks_and_requeues(tmp_path, fake_slurm, restarts, term_rc, requeued):
    fake, env = fake_slurm
    script = render("cohort", tmp_path, "--ntasks", "4", "--ranks-per-job", "2", "--args", "--protocols mwf")
    env = dict(env, FAKE_SLEEP="60", FAKE_TERM_RC=str(term_rc))
    if restarts is not None:
        env["SLURM_RESTART_COUNT"] = restarts
    job = subprocess.Popen(["bash", str(script)], cwd=tmp_path, env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    wait_for(fake / "task.pid")
    job.send_signal(signal.SIGUSR1)  # what --signal=B:USR1@WARN does
    out, _ = job.communicate(timeout=30)
    assert job.returncode == term_rc, out
    assert (fake / "srun.args").read_text().split() == [
        "--mpi=pmi2", "python", "-m", "hyper.cohort", "--ranks-per-job", "2",
        "--output", "results/cohort", "--protocols", "mwf"]
    # the TERM went to the task, through scancel, and srun was left alone
    assert (fake / "scancel.args").read_text() == "--signal=TERM 4242\n"
    assert (fake / "task.term").read_text() == "TERM\n" and "forcing job termination" not in out
    assert "time limit in 300 s or less (Slurm's warning signal USR1): sending TERM to the run's ranks" in out
    scontrol = fake / "scontrol.args"
    if requeued:
        assert scontrol.read_text() == "requeue 4242\n"
        assert "requeueing job 4242 (restart 1 of at most 3)" in out
    else:
        assert not scontrol.exists()
        assert ("this was restart 3, the last of --max-requeue 3" in out if term_rc == 143
                else f"the run ended with exit status {term_rc} before it stopped on the TERM: not requeued" in out)


@pytest.mark.skipif(not os.path.isdir("/dev/shm"), reason="no /dev/shm (Linux)")
def test_unmapped_mpich_segments_are_removed(tmp_path, fake_slurm):
    # A requeued job's step has the same segment name, and its MPI_Init would read a stale one.
    fake, env = fake_slurm
    tag = f"/dev/shm/mpich_shm_hypertest{os.getpid()}"
    stale, live = Path(f"{tag}a_0"), Path(f"{tag}b_0")
    stale.write_bytes(bytes(4096))
    live.write_bytes(bytes(4096))
    try:
        with open(live, "r+b") as f, mmap.mmap(f.fileno(), 4096):  # a running job's: mapped
            subprocess.run(["bash", str(render("sobol", tmp_path))], cwd=tmp_path, check=True, capture_output=True,
                           timeout=30, env=env)
            assert live.exists() and not stale.exists()
    finally:
        stale.unlink(missing_ok=True)
        live.unlink(missing_ok=True)


def test_a_term_from_elsewhere_is_not_requeued(tmp_path, fake_slurm):
    # e.g. `scancel --signal=TERM JOB` by hand: the run stops with its checkpoint, the job ends
    fake, env = fake_slurm
    script = render("grow-array", tmp_path, "--geometries", "cylinder", "--protocols", "mwf")
    job = subprocess.Popen(["bash", str(script)], cwd=tmp_path, env=dict(env, FAKE_SLEEP="60", SLURM_ARRAY_TASK_ID="0"),
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    wait_for(fake / "task.pid")
    time.sleep(0.2)
    os.kill(int((fake / "task.pid").read_text()), signal.SIGTERM)
    out, _ = job.communicate(timeout=30)
    assert job.returncode == 143, out
    assert "not Slurm's time-limit warning (e.g. scancel --signal=TERM): not requeued" in out
    assert not (fake / "scontrol.args").exists()


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
        (["sobol", "--samples", "1"], "argument --samples: expected an integer in [2, 10000000], got 1"),
        (["grow-array", "--max-parallel", "0"], "argument --max-parallel: expected an integer >= 1, got 0"),
        (["cohort", "--ntasks", "0"], "argument --ntasks: expected an integer >= 1, got 0"),
        (["cohort", "--warn-s", "70000"], "argument --warn-s: expected an integer in [1, 65535], got 70000"),
        (["cohort", "--max-requeue", "-1"], "argument --max-requeue: expected an integer >= 0, got -1"),
        (["cohort", "--args=--protocols 'mwf"], "--args \"--protocols 'mwf\": No closing quotation"),
        (["sobol", "--args=--seed $(date"], "the rendered script is not valid bash"),
        (["cohort", "--venv", str(tmp_path)], "no bin/activate, not a virtual environment"),
    ]:
        assert slurm.main([*bad[:1], *base, *bad[1:]]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
    # a missing --workdir is refused, not created
    missing = tmp_path / "no" / "such"
    assert slurm.main(["cohort", "-o", str(tmp_path / "s.sbatch"), "--workdir", str(missing)]) == 2
    assert f"--workdir {missing}: no such folder" in capsys.readouterr().err and not missing.parent.exists()
    assert not (tmp_path / "s.sbatch").exists() and not (tmp_path / "results").exists()


@pytest.mark.parametrize("kind", KINDS)
def test_site_options_and_prelude_go_into_a_valid_script(kind, tmp_path):
    prelude = tmp_path / "site.sh"
    prelude.write_text("module load openmpi/4.1 hdf5\nexport HDF5_USE_FILE_LOCKING=FALSE\nif true; then :; fi\n")
    text = render(kind, tmp_path, "--partition", "compute", "--account", "proj42", "--qos", "normal",
                  "--mem", "4G", "--prelude", str(prelude)).read_text()
    subprocess.run(["bash", "-n", str(tmp_path / f"{kind}.sbatch")], check=True)
    options = sbatch_options(text)
    assert (options["partition"], options["account"], options["qos"], options["mem"]) == \
        ("compute", "proj42", "normal", "4G")
    lines = text.splitlines()
    # every #SBATCH line comes before the first command, where sbatch reads them
    first_command = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
    assert max(i for i, line in enumerate(lines) if line.startswith("#SBATCH")) < first_command
    # the prelude runs after the venv is active and before the run
    order = [text.index(s) for s in ("source ", "module load openmpi/4.1 hdf5", "srun --mpi")]
    assert order == sorted(order) and "export HDF5_USE_FILE_LOCKING=FALSE" in text
    # without them: no such lines, and the script is valid all the same
    plain = render(kind, tmp_path).read_text()
    assert not {"partition", "account", "qos", "mem"} & set(sbatch_options(plain)) and "module load" not in plain


def test_bad_site_options_are_refused(tmp_path, capsys):
    bad_prelude = tmp_path / "bad.sh"
    bad_prelude.write_text("if true; then\n")
    base = ["-o", str(tmp_path / "s.sbatch"), "--workdir", str(tmp_path)]
    for bad, message in [
        (["cohort", "--mem", "lots"], "--mem: 'lots' is not a Slurm memory size"),
        (["cohort", "--partition", "a b"], "--partition: 'a b' must be non-empty, without spaces"),
        (["sobol", "--account", "x;rm"], "--account: 'x;rm' must be non-empty"),
        (["grow-array", "--prelude", str(tmp_path / "none.sh")], "none.sh: no such file"),
        (["cohort", "--prelude", str(bad_prelude)], "the rendered script is not valid bash"),
    ]:
        assert slurm.main([*bad[:1], *base, *bad[1:]]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
    assert not (tmp_path / "s.sbatch").exists()


def test_a_single_protocol_run_names_its_figure(tmp_path):
    # grow-array tasks of one geometry share the output folder: each figure is named per run
    from mpi4py import MPI

    from hyper.commands import grow

    folder = ["--geometry", "cylinder", "--output", str(tmp_path)]
    assert grow.plan(MPI.COMM_SELF, [*folder, "--protocol", "weekly"]).plot == tmp_path / "cylinder_weekly_growth.png"
    assert grow.plan(MPI.COMM_SELF, [*folder, "--protocol", "all"]).plot == tmp_path / "cylinder_growth.png"
    one = ["--geometry", "cylinder", "--protocol", "mwf", "--output", str(tmp_path / "x.h5")]
    assert grow.plan(MPI.COMM_SELF, one).plot == tmp_path / "x.png"
