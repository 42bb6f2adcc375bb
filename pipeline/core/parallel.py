"""Independent jobs run in one forked process per core: the one home of the stages' process parallelism.

A job is a callable without arguments. The workers are forked (Linux), so they inherit the job and its
data without pickling; only results are pickled back. Each job computes what it would compute alone
(figures byte for byte, networks bit for bit: every torch process runs the same single-threaded
kernels). Where the OS cannot fork, or for one job or one core, the jobs run here, one by one.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any

_JOBS: list[Callable[[], Any]] = []  # the jobs of the running `forked_map` (read by its forked workers)


def _run(index: int) -> Any:
    return _JOBS[index]()


def forked_map(jobs: Sequence[Callable[[], Any]], workers: int | None = None) -> Iterator[Any]:
    """The results of `jobs`, in order, computed in up to `workers` (default: one per core) forked
    processes; yields each as soon as it and the ones before it are done."""
    global _JOBS
    n = min(workers or os.cpu_count() or 1, len(jobs))
    if n < 2 or "fork" not in multiprocessing.get_all_start_methods():
        for job in jobs:
            yield job()
        return
    _JOBS = list(jobs)
    try:
        with ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("fork")) as pool:
            yield from pool.map(_run, range(len(jobs)))
    finally:
        _JOBS = []
