"""pipeline.core.parallel: forked jobs give the results of the jobs run one by one, in order."""

from __future__ import annotations

import contextlib
import os
import signal
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.errors import DataError, JobError
from pipeline.core.parallel import end_workers, forked_map


def test_forked_jobs_return_what_they_compute_alone_in_order() -> None:
    data = np.random.default_rng(0).normal(size=(200, 50))  # inherited by the workers, never pickled in
    jobs = [lambda k=k: (k, os.getpid(), float(np.linalg.norm(data[k::7]))) for k in range(7)]
    alone = [job()[2] for job in jobs]
    results = list(forked_map(jobs, workers=2))
    assert [r[0] for r in results] == list(range(7))
    assert [r[2] for r in results] == alone  # bit for bit
    assert all(r[1] != os.getpid() for r in results)  # run in other processes
    assert [r[0] for r in forked_map(jobs, workers=1)] == list(range(7))  # one worker: here, in order


def test_costliest_jobs_first_still_yield_in_order() -> None:
    jobs = [lambda k=k: (k, os.getpid()) for k in range(5)]
    results = list(forked_map(jobs, workers=2, costs=[1.0, 5.0, 2.0, 5.0, 0.5]))
    assert [r[0] for r in results] == list(range(5))
    assert [r[0] for r in forked_map(jobs, workers=1, costs=[3.0, 1.0, 2.0, 0.0, 4.0])] == list(range(5))


def test_a_failing_job_raises_in_the_caller(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def fail() -> None:
        raise ValueError("bad value")

    monkeypatch.chdir(tmp_path)  # where the traceback goes (tests/test_job_errors.py)
    with pytest.raises(JobError, match=r"^job 1: ValueError: bad value \(traceback in "):
        list(forked_map([lambda: 0, fail, lambda: 2], workers=2))


def test_workers_start_with_what_the_caller_holds_out_of_their_collections() -> None:
    """The caller's objects are frozen before the fork (`gc.freeze`): a worker's collections neither scan
    them nor copy their pages."""
    import gc

    held = [{"k": k} for k in range(1000)]  # tracked by the collector, alive in the caller
    try:
        counts = list(forked_map([gc.get_freeze_count] * 2, workers=2))
        assert all(c >= len(held) for c in counts)
    finally:
        gc.unfreeze()


def _alive(pid: int) -> bool:
    """Whether `pid` runs (a zombie, ended and waiting for whoever reaps orphans, does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def _sleeper(pid_file: Path, write: Path | None = None) -> None:
    """Note this worker's pid, then sleep for a minute (inside an atomic write of `write`, if given)."""
    import time

    from pipeline.core.io import atomic_path

    with atomic_path(write) if write is not None else contextlib.nullcontext() as tmp:
        if tmp is not None:
            tmp.write_text("half")
        pid_file.write_text(str(os.getpid()))
        time.sleep(60)


def _wait_for(path: Path) -> int:
    import time

    for _ in range(1000):
        if path.is_file() and path.read_text():
            return int(path.read_text())
        time.sleep(0.01)
    raise AssertionError(f"{path} never written")


def test_a_failing_job_ends_the_running_ones_at_once(tmp_path: Path) -> None:
    """A running job is not waited for: its worker is ended (its temporary file removed) and reaped."""
    import time

    def fail() -> None:
        _wait_for(tmp_path / "pid")
        raise DataError("b.mcap: truncated")

    start = time.monotonic()
    with pytest.raises(DataError, match="b.mcap: truncated"):
        list(forked_map([lambda: _sleeper(tmp_path / "pid", tmp_path / "a.parquet"), fail], workers=2))
    assert time.monotonic() - start < 10.0
    assert not _alive(_wait_for(tmp_path / "pid"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pid"]  # no temporary file of a.parquet


def test_results_left_unread_are_ended_by_end_workers(tmp_path: Path) -> None:
    """A caller that stops reading (an exception of its own) leaves its pool's workers; `end_workers` (the CLI
    calls it before exiting) ends and reaps them."""
    results = forked_map([lambda: 0, lambda: _sleeper(tmp_path / "pid")], workers=2)
    assert next(results) == 0
    pid = _wait_for(tmp_path / "pid")
    assert _alive(pid)
    end_workers()
    assert not _alive(pid)
    results.close()  # nothing left to end


def test_a_worker_whose_parent_is_killed_dies_with_it(tmp_path: Path) -> None:
    """SIGKILL of the process that forked the workers (no cleanup can run there) takes its workers with it."""
    import time

    pid = os.fork()
    if pid == 0:  # a parent of workers, killed below
        try:
            list(forked_map([lambda: _sleeper(tmp_path / "pid"), lambda: 0], workers=2))
        finally:
            os._exit(1)
    worker = _wait_for(tmp_path / "pid")
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    for _ in range(500):
        if not _alive(worker):
            break
        time.sleep(0.01)
    assert not _alive(worker)
