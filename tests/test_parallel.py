"""pipeline.core.parallel: forked jobs give the results of the jobs run one by one, in order."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.errors import JobError
from pipeline.core.parallel import forked_map


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
