"""pipeline.core.parallel: forked jobs give the results of the jobs run one by one, in order."""

from __future__ import annotations

import os

import numpy as np

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
