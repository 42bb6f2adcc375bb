"""Independent jobs run in one forked process per core: the one home of the stages' process parallelism.

A job is a callable without arguments. The workers are forked (Linux), so they inherit the job and its
data without pickling; only results are pickled back. Each job computes what it would compute alone
(figures byte for byte, networks bit for bit: every torch process runs the same single-threaded
kernels). Where the OS cannot fork, or for one job or one core, the jobs run here, one by one.
"""

from __future__ import annotations

import gc
import multiprocessing
import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any

_JOBS: list[Callable[[], Any]] = []  # the jobs of the running `forked_map` (read by its forked workers)


def _run(index: int) -> Any:
    return _JOBS[index]()


def forked_map(
    jobs: Sequence[Callable[[], Any]], workers: int | None = None, costs: Sequence[float] | None = None
) -> Iterator[Any]:
    """The results of `jobs`, in order, computed in up to `workers` (default: one per core) forked
    processes; yields each as soon as it and the ones before it are done.

    With `costs` (one per job, e.g. input bytes), the workers take the costliest jobs first, which
    balances the workers when the jobs' sizes differ; the results still come in the order of `jobs`.
    If a job raises, the jobs not started yet are dropped and its exception is raised here.
    """
    global _JOBS
    n = min(workers or os.cpu_count() or 1, len(jobs))
    if n < 2 or "fork" not in multiprocessing.get_all_start_methods():
        for job in jobs:
            yield job()
        return
    order = list(range(len(jobs)))
    if costs is not None:
        ranked = list(costs)
        order.sort(key=lambda i: -ranked[i])  # stable: equal costs keep the jobs' order
    _JOBS = [jobs[i] for i in order]
    gc.freeze()  # what exists now is out of the workers' collections: they neither scan nor copy it
    pool = ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("fork"))
    try:
        done: dict[int, Any] = {}
        following = 0  # the next job (index into `jobs`) to yield
        for i, result in zip(order, pool.map(_run, range(len(jobs))), strict=True):
            done[i] = result
            while following in done:
                yield done.pop(following)
                following += 1
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        _JOBS = []
