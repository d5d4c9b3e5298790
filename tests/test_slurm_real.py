"""The Slurm templates on a real single-node Slurm, started here on loopback.

Recipe: ../shared/RECIPES.md (munged as its own user, a minimal slurm.conf, slurmctld and
slurmd as root). `.ci/run` installs slurm-wlm and munge where apt-get works as root;
where Slurm cannot be started, every test here is skipped with the reason.

Each template's job is stopped mid-run the way a time limit stops it: the test sends the
batch script USR1, which is what Slurm does `--warn-s` seconds before the limit
(`#SBATCH --signal=B:USR1@WARN`), rather than waiting minutes for a real limit. The job
sends TERM to its ranks, the run stops and requeues itself; the cluster makes a requeued
job wait 10 s instead of 120 (cred_expire), and the resumed result is compared with an
uninterrupted run on the same number of ranks.
"""

from __future__ import annotations

import datetime
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from hyper.commands import slurm
from hyper.core.io import is_complete

PYTHON = sys.executable
SRC = Path(slurm.__file__).resolve().parents[2]  # src/, holding hyper/ (this module is hyper/commands/slurm.py)
# the runs: short, but long enough (about 6 s of growth steps) for a TERM to land mid-run
# a growth step of 2 h keeps a run going (about 15 s) until the test has warned it; the
# tests wait for the progress lines, so they come every second
GROW_ARGS = ["--geometry", "cylinder", "--growth-dt", "2", "--checkpoint-every", "0", "--progress-every", "1"]
PROTOCOLS = ("weekly", "every3days")
# How long a requeued job waits (Slurm's default is 120 s); short for the tests.
CRED_EXPIRE_S = 10
SOBOL_ARGS = ["--samples", "32", "--chunk", "16"]  # 60 chunks, about 5 s on 2 ranks


def _tool(name: str) -> str | None:
    """The path of a Slurm or munge program; the daemons live in /usr/sbin, often not on PATH."""
    return shutil.which(name) or shutil.which(name, path="/usr/sbin:/sbin")


def _run(*command, env=None, timeout=60, check=True):
    return subprocess.run(command, env=env, capture_output=True, text=True, timeout=timeout, check=check)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _why_not() -> str | None:
    """Why Slurm cannot be started here, or None."""
    if not sys.platform.startswith("linux"):
        return "Slurm runs on Linux only"
    missing = [tool for tool in ("slurmctld", "slurmd", "sbatch", "scontrol", "scancel", "munged", "munge")
               if _tool(tool) is None]
    if missing:
        return (f"not installed: {', '.join(missing)} (Debian: slurm-wlm munge; .ci/run installs them where "
                "apt-get works as root)")
    if os.geteuid() != 0:
        return "slurmctld and slurmd of a test cluster must run as root (SlurmUser=root)"
    if not Path("/etc/munge/munge.key").is_file():
        return "no /etc/munge/munge.key (the munge package creates it)"
    return None


def _munge_works() -> bool:
    try:
        return subprocess.run("munge -n | unmunge", shell=True, capture_output=True, timeout=10).returncode == 0
    except subprocess.TimeoutExpired:
        return False


def _stop(pid_file: Path) -> None:
    """Stop a daemon by the PID in its pid file, and wait until it is gone."""
    if not pid_file.is_file():
        return
    pid = int(pid_file.read_text().split()[0])
    try:
        os.kill(pid, 15)
    except ProcessLookupError:
        return
    end = time.monotonic() + 20
    while time.monotonic() < end:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.1)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A one-node Slurm cluster of our own (own ports and folders): the environment that
    reaches it. Skips, with the reason, where it cannot be started."""
    reason = _why_not()
    if reason:
        pytest.skip(f"no real Slurm: {reason}")
    folder = tmp_path_factory.mktemp("slurm")
    started_munge = None
    if not _munge_works():
        # munged refuses to run as root ("Logfile is insecure"): run it as its own user
        Path("/run/munge").mkdir(exist_ok=True)
        shutil.chown("/run/munge", "munge", "munge")
        _run("runuser", "-u", "munge", "--", _tool("munged"), check=False)
        started_munge = Path("/run/munge/munged.pid")
        if not _munge_works():
            pytest.skip("no real Slurm: munged did not start (`munge -n | unmunge` fails)")
    host = socket.gethostname().split(".")[0]
    for sub in ("state", "spool"):
        (folder / sub).mkdir()
    conf = folder / "slurm.conf"
    conf.write_text("\n".join([
        "ClusterName=hypertest", f"SlurmctldHost={host}", f"SlurmctldPort={_free_port()}",
        f"SlurmdPort={_free_port()}", "SlurmUser=root", "SlurmdUser=root", "AuthType=auth/munge",
        f"StateSaveLocation={folder}/state", f"SlurmdSpoolDir={folder}/spool",
        f"SlurmctldPidFile={folder}/slurmctld.pid", f"SlurmdPidFile={folder}/slurmd.pid",
        f"SlurmctldLogFile={folder}/ctld.log", f"SlurmdLogFile={folder}/d.log",
        f"AuthInfo=cred_expire={CRED_EXPIRE_S}", "ProctrackType=proctrack/linuxproc", "TaskPlugin=task/none",
        "SchedulerType=sched/builtin",
        "SelectType=select/cons_tres", "SelectTypeParameters=CR_Core", "ReturnToService=2", "MpiDefault=none",
        f"NodeName={host} CPUs={os.cpu_count()} State=UNKNOWN",
        f"PartitionName=debug Nodes={host} Default=YES MaxTime=INFINITE State=UP", ""]))
    env = dict(os.environ, SLURM_CONF=str(conf), PYTHONPATH=f"{SRC}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
               OMP_NUM_THREADS="1")
    try:
        _run(_tool("slurmctld"), env=env)
        _run(_tool("slurmd"), env=env)
        end = time.monotonic() + 30
        while _run("sinfo", "-h", "-o", "%T", env=env, check=False).stdout.strip() != "idle":
            if time.monotonic() > end:
                log = (folder / "ctld.log").read_text()[-800:] + (folder / "d.log").read_text()[-800:]
                pytest.skip(f"no real Slurm: the node did not become idle within 30 s; logs end:\n{log}")
            time.sleep(0.5)
        yield env
    except subprocess.CalledProcessError as err:
        pytest.skip(f"no real Slurm: {' '.join(err.cmd)} failed: {err.stderr.strip()}")
    finally:
        _stop(folder / "slurmd.pid")
        _stop(folder / "slurmctld.pid")
        if started_munge is not None:
            _stop(started_munge)


# ------------------------------------------------------------------------------ helpers


ENDED = ("COMPLETED", "FAILED", "TIMEOUT", "CANCELLED")


def job(env, job_id: str) -> dict:
    """`scontrol show job` of one job (or array task) as a dict."""
    text = _run("scontrol", "-o", "show", "job", job_id, env=env).stdout
    return dict(re.findall(r"(\w+)=(\S*)", text))


def wait_until(what: str, test, timeout: float):
    end = time.monotonic() + timeout
    while not (found := test()):
        assert time.monotonic() < end, f"timed out after {timeout:g} s waiting for {what}"
        time.sleep(0.25)
    return found


def progress(log: Path) -> float:
    """The last progress percentage a run printed to ``log`` (0 if none yet)."""
    found = re.findall(r": +([\d.]+)% ", log.read_text()) if log.is_file() else []
    return float(found[-1]) if found else 0.0


def warn(env, job_id: str) -> None:
    """What Slurm does --warn-s seconds before the time limit (--signal=B:USR1@WARN)."""
    _run("scancel", "--batch", "--signal=USR1", job_id, env=env)


def requeued_then_released(env, job_id: str) -> None:
    """Wait for the job to stop and requeue itself, then start it as soon as Slurm allows."""
    state = wait_until(f"job {job_id} requeued", lambda: (s := job(env, job_id))["JobState"] in
                       ("PENDING", *ENDED) and s, timeout=60)
    log = Path(state["StdOut"])
    assert state["JobState"] == "PENDING" and state["Restarts"] == "1", (
        f"{state['JobState']} instead of requeued; its log ends:\n{log.read_text()[-2000:] if log.is_file() else ''}")
    # slurmd refuses a job id it killed until the credential lifetime (cred_expire, here
    # CRED_EXPIRE_S) has passed ("Job credential revoked"); Slurm makes the job eligible
    # only then. Once it is, start it now rather than at the scheduler's next pass.
    eligible = datetime.datetime.fromisoformat(state["EligibleTime"])
    wait_until(f"job {job_id} eligible", lambda: datetime.datetime.now() > eligible, timeout=CRED_EXPIRE_S + 30)
    _run("scontrol", "update", f"JobId={job_id}", "StartTime=now", env=env)


def completed(env, job_id: str, timeout: float = 90) -> None:
    state = wait_until(f"job {job_id} ended", lambda: (s := job(env, job_id))["JobState"] in ENDED and s, timeout)
    assert state["JobState"] == "COMPLETED" and state["ExitCode"] == "0:0", state


def render(env, kind: str, workdir: Path, *options) -> Path:
    script = workdir / f"{kind}.sbatch"
    _run(PYTHON, "-m", "hyper.slurm", kind, "-o", str(script), "--workdir", str(workdir), "--log-dir", "logs",
         "--time", "10", "--warn-s", "60", "--max-requeue", "1", *options, env=env)
    return script


def submit(env, script: Path) -> str:
    return _run("sbatch", "--parsable", str(script), env=env).stdout.strip().split(";")[0]


def series(path: Path) -> dict[str, np.ndarray]:
    """Every dataset of a result but its wall-clock times, and its attributes."""
    with h5py.File(path, "r") as f:
        data = {k: f[k][()] for k in f if isinstance(f[k], h5py.Dataset) and k != "wall_s"}
        return data, dict(f.attrs)


def assert_in_order(text: str, lines: list[str]) -> None:
    """Each of ``lines`` occurs in ``text``, after the one before it."""
    at = 0
    for line in lines:
        found = text.find(line, at)
        assert found >= 0, f"not found after position {at}: {line!r} in\n{text}"
        at = found + len(line)


def assert_same_series(resumed: Path, whole: Path) -> int:
    """The resumed result has the uninterrupted one's series, bit for bit; its length."""
    got, attrs = series(resumed)
    want, whole_attrs = series(whole)
    assert attrs["run_digest"] == whole_attrs["run_digest"] and attrs["segments"] == 2
    assert sorted(got) == sorted(want)
    for name in want:
        assert got[name].tobytes() == want[name].tobytes(), name
    return len(want["t"])


@pytest.fixture(scope="module")
def uninterrupted(cluster, tmp_path_factory):
    """hyper grow of each protocol, run straight through on 1 rank (both at once)."""
    folder = tmp_path_factory.mktemp("whole")
    runs = [subprocess.Popen([PYTHON, "-m", "hyper.grow", *GROW_ARGS, "--protocol", p, "--output", str(folder),
                              "--quiet"], env=cluster) for p in PROTOCOLS]
    assert [r.wait(timeout=120) for r in runs] == [0, 0]
    return {p: folder / f"cylinder_{p}.h5" for p in PROTOCOLS}


# -------------------------------------------------------------------------------- tests


@pytest.mark.parametrize("kind", ["cohort", "grow-array", "sobol"])
def test_sbatch_accepts_the_scripts(cluster, kind, tmp_path):
    script = render(cluster, kind, tmp_path, "--ntasks", "1")
    done = _run("sbatch", "--test-only", str(script), env=cluster, check=False)
    assert done.returncode == 0 and "to start at" in done.stderr, done.stderr


def test_srun_kills_its_tasks_on_term(cluster, tmp_path):
    # Why the scripts never signal srun, and what the stand-in srun of test_jobs.py copies.
    handler = tmp_path / "handler.py"
    handler.write_text("import signal, sys, time\n"
                       "signal.signal(signal.SIGTERM, lambda *a: sys.exit(143))\n"
                       "print('ready', flush=True)\ntime.sleep(60)\n")
    script = tmp_path / "srun.sbatch"
    script.write_text(f"#!/bin/bash\n#SBATCH --output={tmp_path}/srun.out\nsrun {PYTHON} {handler}\n")
    job_id = submit(cluster, script)
    log = tmp_path / "srun.out"
    wait_until("the task to start", lambda: log.is_file() and "ready" in log.read_text(), timeout=60)
    srun = _run("pgrep", "-f", f"^srun {PYTHON} {handler}", env=cluster).stdout.split()[0]
    os.kill(int(srun), 15)
    state = wait_until("srun's job ended", lambda: (s := job(cluster, job_id))["JobState"] != "RUNNING" and s, 60)
    assert state["ExitCode"] == "137:0", state
    text = log.read_text()
    assert "srun: forcing job termination" in text and "task 0: Killed" in text


def test_grow_array_task_stopped_requeued_and_resumed(cluster, uninterrupted, tmp_path):
    script = render(cluster, "grow-array", tmp_path, "--geometries", "cylinder", "--protocols", *PROTOCOLS,
                    "--args=" + " ".join(GROW_ARGS[2:]))
    array = submit(cluster, script)
    log = tmp_path / "logs" / f"hyper-grow-array-{array}_0.out"
    wait_until("task 0 under way", lambda: progress(log) > 0, timeout=60)
    task0 = job(cluster, f"{array}_0")["JobId"]
    warn(cluster, task0)
    requeued_then_released(cluster, task0)
    for task in (task0, f"{array}_1"):
        completed(cluster, task)
    text = log.read_text()
    stopped = int(re.search(r"weekly: stopped on request at step (\d+)", text).group(1))
    lines = [
        f"time limit in 60 s or less (Slurm's warning signal USR1): sending TERM to the run's ranks "
        f"(scancel --signal=TERM {task0})",
        f"slurmstepd-{socket.gethostname().split('.')[0]}: error: *** STEP {task0}.0 ON",
        "srun: error: ", "task 0: Exited with exit code 143",
        f"the run stopped on the TERM (exit status 143): requeueing job {task0} (restart 1 of at most 1)",
        f"task 0 (job {task0}): cylinder weekly on", "restart 1",
        f"cylinder/weekly: resuming from results/grow/cylinder_weekly.ckpt.h5 at step {stopped}",
        "the run ended with exit status 0",
    ]
    assert_in_order(text, lines)
    out = tmp_path / "results" / "grow"
    steps = assert_same_series(out / "cylinder_weekly.h5", uninterrupted["weekly"])
    assert 0 < stopped < steps - 1
    # the task that was not stopped, and a figure of each run
    got, _ = series(out / "cylinder_every3days.h5")
    assert got["csa_ratio"].tobytes() == series(uninterrupted["every3days"])[0]["csa_ratio"].tobytes()
    assert sorted(p.name for p in out.glob("*.png")) == ["cylinder_every3days_growth.png", "cylinder_weekly_growth.png"]


def test_cohort_stopped_requeued_and_resumed(cluster, uninterrupted, tmp_path):
    # two runs on two ranks of one rank each; the TERM reaches both ranks mid-run
    script = render(cluster, "cohort", tmp_path, "--ntasks", "2", "--ranks-per-job", "1",
                    "--args=--geometries cylinder --protocols weekly every3days --growth-dt 2 --progress-every 1 "
                    "--plot-geometry cylinder")
    job_id = submit(cluster, script)
    runs = tmp_path / "results" / "cohort" / "runs"
    wait_until("both runs under way", lambda: all(progress(runs / f"cylinder_{p}.log") > 0 for p in PROTOCOLS),
               timeout=60)
    warn(cluster, job_id)
    requeued_then_released(cluster, job_id)
    completed(cluster, job_id)
    text = (tmp_path / "logs" / f"hyper-cohort-{job_id}.out").read_text()
    lines = [
        f"time limit in 60 s or less (Slurm's warning signal USR1): sending TERM to the run's ranks "
        f"(scancel --signal=TERM {job_id})",
        f"*** STEP {job_id}.0 ON",
        "stopped by SIGTERM: 2 run(s) not finished (cylinder_every3days, cylinder_weekly)",
        "tasks 0-1: Exited with exit code 143",
        f"requeueing job {job_id} (restart 1 of at most 1)",
        f"job {job_id} on", "restart 1",
        "cohort: 2 to run, 0 skipped",
        "the run ended with exit status 0",
    ]
    assert_in_order(text, lines)
    for p in PROTOCOLS:
        run_log = (runs / f"cylinder_{p}.log").read_text()
        stopped = int(re.search(r"resuming from \S+ at step (\d+)", run_log).group(1))
        assert 0 < stopped < assert_same_series(runs / f"cylinder_{p}.h5", uninterrupted[p]) - 1


def test_sobol_stopped_requeued_and_resumed(cluster, tmp_path):
    whole = subprocess.Popen([os.path.join(sys.prefix, "bin", "mpirun"), "-n", "2", PYTHON, "-m", "hyper.sobol",
                              *SOBOL_ARGS, "--output", str(tmp_path / "whole"), "--quiet"], env=cluster)
    assert whole.wait(timeout=120) == 0
    script = render(cluster, "sobol", tmp_path, "--ntasks", "2", "--samples", SOBOL_ARGS[1],
                    "--args=" + " ".join(SOBOL_ARGS[2:]))
    job_id = submit(cluster, script)
    chunks = tmp_path / "results" / "sobol" / "chunks"
    wait_until("5 chunks done", lambda: len(list(chunks.glob("*/*.npz"))) >= 5, timeout=60)
    warn(cluster, job_id)
    requeued_then_released(cluster, job_id)
    completed(cluster, job_id)
    text = (tmp_path / "logs" / f"hyper-sobol-{job_id}.out").read_text()
    kept = int(re.findall(r"sobol: (\d+) to run, (\d+) skipped", text)[1][1])
    assert 5 <= kept < 60
    lines = [
        f"sending TERM to the run's ranks (scancel --signal=TERM {job_id})", f"*** STEP {job_id}.0 ON",
        "stopped by SIGTERM", "tasks 0-1: Exited with exit code 143",
        f"requeueing job {job_id} (restart 1 of at most 1)",
        f"sobol: {60 - kept} to run, {kept} skipped (done before)", "the run ended with exit status 0",
    ]
    assert_in_order(text, lines)
    resumed, whole = tmp_path / "results" / "sobol" / "sobol.h5", tmp_path / "whole" / "sobol.h5"
    with h5py.File(resumed) as got, h5py.File(whole) as want:
        for name in ("X", "Y", "S1", "S1_conf", "ST", "ST_conf", "S2", "S2_conf", "S1_bootstrap", "ST_bootstrap"):
            assert got[name][()].tobytes() == want[name][()].tobytes(), name
        assert got.attrs["digest"] == want.attrs["digest"] and got.attrs["evaluations_computed"] == 960 - 16 * kept


def _grow_holds_term(folder: Path) -> bool:
    """Whether a `python -m hyper.grow` of the job in ``folder`` (its --chdir) has started
    and blocked SIGTERM, that is hyper.core.term has taken the signal over.

    Before that (Python's own start, some tens of ms) a TERM kills the rank by the default
    disposition: srun reports 'Terminated', the template still requeues it (exit status
    143), but this test is about the window after, while imports and PETSc start.
    """
    term_bit = 1 << (signal.SIGTERM - 1)
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            argv = cmdline.read_bytes().split(b"\0")
            # the rank itself, not the srun that started it (whose argv names hyper.grow too)
            if b"python" not in os.path.basename(argv[0]) or b"hyper.grow" not in argv:
                continue
            if Path(cmdline.parent / "cwd").resolve() != folder.resolve():
                continue
            status = (cmdline.parent / "status").read_text()
        except OSError:  # ended meanwhile, or not ours to read
            continue
        blocked = int(re.search(r"^SigBlk:\s*([0-9a-f]+)", status, re.M).group(1), 16)
        if blocked & term_bit:
            return True
    return False


def test_grow_array_task_termed_in_its_start_up_is_requeued_and_finishes(cluster, tmp_path):
    # Slurm's warning as soon as the run has started: its TERM reaches the rank while it
    # imports and starts PETSc (some 0.7 s), before its growth steps. PETSc's own handler
    # once ended such a task, TERMed 2 s after its start, with 'PETSC ERROR: Caught
    # signal' and exit status 15 or 59, which the template did not requeue: it was lost.
    script = render(cluster, "grow-array", tmp_path, "--geometries", "cylinder", "--protocols", "weekly",
                    "--args=" + " ".join(GROW_ARGS[2:]))
    array = submit(cluster, script)
    log = tmp_path / "logs" / f"hyper-grow-array-{array}_0.out"
    task = wait_until("task 0 to start", lambda: job(cluster, f"{array}_0")["JobId"], timeout=60)
    wait_until("the run to take TERM over", lambda: _grow_holds_term(tmp_path), timeout=60)
    warn(cluster, task)
    requeued_then_released(cluster, task)
    completed(cluster, task)
    text = log.read_text()
    assert_in_order(text, [
        f"sending TERM to the run's ranks (scancel --signal=TERM {task})",
        "task 0: Exited with exit code 143",
        f"the run stopped on the TERM (exit status 143): requeueing job {task} (restart 1 of at most 1)",
        f"task 0 (job {task}): cylinder weekly on", "restart 1",
        "the run ended with exit status 0",
    ])
    assert "PETSC ERROR" not in text
    # stopped by hyper.core.term's handler, before the run's own (srun may pass its stderr on later)
    first = text.split("requeueing job")[0]
    assert "hyper: stopped by SIGTERM outside a run's growth steps; exit status 143" in first, first
    result = tmp_path / "results" / "grow" / "cylinder_weekly.h5"
    assert is_complete(result), f"{result} is not complete"
