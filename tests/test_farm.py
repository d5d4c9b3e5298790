"""The job farm on toy jobs: serial (COMM_SELF) and under mpirun -n 2."""

import time
from pathlib import Path

import pytest
from mpi4py import MPI

from hyper.core.params import InputError
from hyper.runs import farm
from hyper.runs.farm import Job

COSTS = [1, 5, 2, 2, 9, 1, 3, 1]


def toy_jobs(costs=COSTS):
    return [Job(f"job{i}", cost=c, payload=i) for i, c in enumerate(costs)]


class Recorder:
    """``work`` for toy jobs: remembers what this rank ran, in order."""

    def __init__(self, comm, fail=(), sleep_per_cost=0.0, done_dir=None):
        self.comm = comm  # the farm's communicator, to say which rank ran a job
        self.fail = set(fail)
        self.sleep_per_cost = sleep_per_cost
        self.done_dir = done_dir
        self.ran: list[str] = []

    def __call__(self, subcomm, job):
        self.ran.append(job.key)
        time.sleep(self.sleep_per_cost * job.cost)
        if job.key in self.fail:
            raise RuntimeError(f"toy failure in {job.key}")
        total = subcomm.allreduce(job.payload)  # a collective on the group's communicator
        if self.done_dir is not None and subcomm.rank == 0:
            (self.done_dir / job.key).write_text("done")
        return {"rank": self.comm.rank, "size": subcomm.size, "total": total}

    def is_done(self, job):
        return (self.done_dir / job.key).exists()


def all_ran(comm, rec):
    """Every rank's list of jobs run, concatenated (leaders and non-leaders alike)."""
    return [key for part in comm.allgather(rec.ran) for key in part]


def check_ran_once(comm, jobs, results, rec, ranks_per_job=1):
    assert [r.key for r in results] == [j.key for j in jobs]
    assert all(r.status == "done" for r in results)
    ran = all_ran(comm, rec)
    assert sorted(ran) == sorted(j.key for j in jobs for _ in range(ranks_per_job))


# --- serial: COMM_SELF ------------------------------------------------------------------


def test_serial_runs_each_job_once_longest_first():
    comm = MPI.COMM_SELF
    jobs = toy_jobs()
    rec = Recorder(comm)
    results = farm.run(comm, jobs, rec)
    check_ran_once(comm, jobs, results, rec)
    cost = {j.key: j.cost for j in jobs}
    assert [cost[k] for k in rec.ran] == sorted(COSTS, reverse=True)
    assert rec.ran[:2] == ["job4", "job1"]  # ties keep the given order: job2 before job3
    assert rec.ran.index("job2") < rec.ran.index("job3")
    assert [r.result["total"] for r in results] == list(range(len(jobs)))
    assert all(r.group == 0 and r.wall_s >= 0 and r.error == "" for r in results)


def test_serial_failure_is_recorded_and_the_rest_finish():
    comm = MPI.COMM_SELF
    jobs = toy_jobs()
    results = farm.run(comm, jobs, Recorder(comm, fail={"job2"}))
    failed = [r for r in results if r.status == "failed"]
    assert [r.key for r in failed] == ["job2"]
    assert "RuntimeError: toy failure in job2" in failed[0].error
    assert "Traceback" in failed[0].error and failed[0].result is None
    assert sum(r.status == "done" for r in results) == len(jobs) - 1
    line = farm.summary_line(results)
    assert line == "8 jobs: 7 done, 1 failed, 0 skipped (done before); failed: job2"


def test_serial_rerun_skips_finished(tmp_path):
    comm = MPI.COMM_SELF
    jobs = toy_jobs()
    first = Recorder(comm, fail={"job5"}, done_dir=tmp_path)
    farm.run(comm, jobs, first, is_done=first.is_done)
    (tmp_path / "job1").unlink()
    again = Recorder(comm, done_dir=tmp_path)
    results = farm.run(comm, jobs, again, is_done=again.is_done)
    assert sorted(again.ran) == ["job1", "job5"]
    status = {r.key: r.status for r in results}
    assert status == {j.key: "done" if j.key in ("job1", "job5") else "skipped" for j in jobs}
    assert all(r.group == -1 and r.result is None for r in results if r.status == "skipped")


def test_serial_bad_result_is_a_failure():
    comm = MPI.COMM_SELF
    results = farm.run(comm, toy_jobs([1, 1]), lambda c, j: [1] if j.key == "job0" else None)
    assert results[0].status == "failed" and "expected a dict" in results[0].error
    assert results[1].status == "done" and results[1].result is None


def test_serial_invalid_input():
    comm = MPI.COMM_SELF
    for bad in (0, 2, 1.0, True):
        with pytest.raises(InputError, match="ranks per job"):
            farm.run(comm, toy_jobs(), Recorder(comm), ranks_per_job=bad)
    with pytest.raises(InputError, match="unique"):
        farm.run(comm, [Job("a"), Job("b"), Job("a")], Recorder(comm))
    with pytest.raises(InputError, match="cost"):
        Job("a", cost=0)
    assert farm.run(comm, [], Recorder(comm)) == []


# --- mpirun -n 2 --------------------------------------------------------------------------


def shared_tmp(comm, tmp_path):
    """One folder for all ranks: rank 0's pytest tmp_path."""
    return Path(comm.bcast(str(tmp_path) if comm.rank == 0 else None, root=0))


@pytest.mark.mpi
def test_mpi_every_job_once_on_both_ranks():
    comm = MPI.COMM_WORLD
    assert comm.size == 2
    jobs = toy_jobs()
    # Sleeping makes rank 0's first job (cost 9) long enough for rank 1 to ask for work.
    rec = Recorder(comm, sleep_per_cost=0.02)
    results = farm.run(comm, jobs, rec)
    check_ran_once(comm, jobs, results, rec)
    assert {r.result["rank"] for r in results} == {0, 1}
    assert {r.group for r in results} == {0, 1}
    # Each rank's results were recorded by the rank that ran the job.
    assert all(r.result["rank"] == r.group for r in results)
    # Longest first: each group takes from one queue sorted by decreasing cost.
    cost = {j.key: j.cost for j in jobs}
    assert [cost[k] for k in rec.ran] == sorted((cost[k] for k in rec.ran), reverse=True)
    # The same list on every rank.
    assert comm.allgather(results) == [results] * comm.size


@pytest.mark.mpi
def test_mpi_failure_is_recorded_and_the_rest_finish():
    comm = MPI.COMM_WORLD
    jobs = toy_jobs()
    rec = Recorder(comm, fail={"job4", "job6"}, sleep_per_cost=0.01)
    results = farm.run(comm, jobs, rec)
    failed = {r.key: r for r in results if r.status == "failed"}
    assert sorted(failed) == ["job4", "job6"]
    assert all(f"toy failure in {k}" in r.error for k, r in failed.items())
    assert sum(r.status == "done" for r in results) == len(jobs) - 2
    assert sorted(all_ran(comm, rec)) == sorted(j.key for j in jobs)


@pytest.mark.mpi
def test_mpi_failure_on_one_rank_of_a_group_does_not_hang():
    comm = MPI.COMM_WORLD

    def work(subcomm, job):
        assert subcomm.size == 2
        if job.key == "job1" and subcomm.rank == 1:
            raise ValueError("only rank 1 fails")
        return {"n": subcomm.allreduce(1) if job.key != "job1" else 0}

    results = farm.run(comm, toy_jobs([1, 1, 1]), work, ranks_per_job=2)
    assert [r.status for r in results] == ["done", "failed", "done"]
    assert "[rank 1 of group 0]" in results[1].error and "only rank 1 fails" in results[1].error
    assert results[0].result == {"n": 2}


@pytest.mark.mpi
def test_mpi_rerun_skips_finished(tmp_path):
    comm = MPI.COMM_WORLD
    folder = shared_tmp(comm, tmp_path)
    jobs = toy_jobs()
    first = Recorder(comm, fail={"job3"}, done_dir=folder)
    farm.run(comm, jobs, first, is_done=first.is_done)
    comm.barrier()
    if comm.rank == 0:
        (folder / "job0").unlink()
    comm.barrier()
    again = Recorder(comm, done_dir=folder)
    results = farm.run(comm, jobs, again, is_done=again.is_done)
    assert sorted(all_ran(comm, again)) == ["job0", "job3"]
    status = {r.key: r.status for r in results}
    assert status == {j.key: "done" if j.key in ("job0", "job3") else "skipped" for j in jobs}


@pytest.mark.mpi
def test_mpi_two_ranks_per_job():
    comm = MPI.COMM_WORLD
    jobs = toy_jobs()
    rec = Recorder(comm)
    results = farm.run(comm, jobs, rec, ranks_per_job=2)
    check_ran_once(comm, jobs, results, rec, ranks_per_job=2)
    assert all(r.result["size"] == 2 and r.group == 0 for r in results)
    assert [r.result["total"] for r in results] == [2 * i for i in range(len(jobs))]


@pytest.mark.mpi
def test_mpi_invalid_ranks_per_job():
    comm = MPI.COMM_WORLD
    with pytest.raises(InputError, match="divide the number of MPI ranks"):
        farm.run(comm, toy_jobs(), Recorder(comm), ranks_per_job=3)


@pytest.mark.mpi
def test_mpi_groups_wait_for_each_others_compiles():
    """Groups that compile the same form wait for the first one's cache file: longer than
    DOLFINx's default 10 s, which a loaded machine exceeded."""
    import dolfinx_solver  # noqa: F401
    from dolfinx import jit

    comm = MPI.COMM_WORLD
    jobs = toy_jobs()
    farm.run(comm, jobs, Recorder(comm))
    assert jit.get_options()["timeout"] >= farm.JIT_WAIT_S == 600
