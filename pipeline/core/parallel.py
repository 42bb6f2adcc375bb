"""Independent jobs run in one forked process per core: the one home of the stages' process parallelism.

A job is a callable without arguments. The workers are forked (Linux), so they inherit the job and its
data without pickling; only results are pickled back. Each job computes what it would compute alone
(figures byte for byte, networks bit for bit: every torch process runs the same single-threaded
kernels). Where the OS cannot fork, or for one job or one core, the jobs run here, one by one.

A job's error reaches the caller as one line: an `FtcalError` as it is (it names its file or key); any
other exception (a library's ValueError or RuntimeError on the data) as a `JobError` naming the job's label
(the file or name it works on), the exception, and the file under ``TRACEBACK_DIR`` of the working
directory that holds its full traceback; the CLI prints that line, never the traceback.
"""

from __future__ import annotations

import gc
import multiprocessing
import os
import tempfile
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

from pipeline.core.errors import FtcalError, JobError

TRACEBACK_DIR = Path(".ftcal") / "tracebacks"  # under the working directory (the repo root under DVC)
_JOBS: list[tuple[Callable[[], Any], str]] = []  # the running `forked_map`'s (job, label), for its workers


def save_traceback(exc: BaseException, label: str) -> Path:
    """Write `exc`'s full traceback, headed by `label`, to a new file under TRACEBACK_DIR of the working
    directory (else of the temporary directory, when that one is not writable); its path (relative to the
    working directory when inside it)."""
    from pipeline.core.io import write_text

    text = f"{label}\n\n" + "".join(traceback.format_exception(exc))
    name = f"{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}.txt"
    for base in (Path.cwd(), Path(tempfile.gettempdir()) / "ftcal"):
        try:
            write_text(base / TRACEBACK_DIR / name, text)
        except OSError:
            continue
        path = base / TRACEBACK_DIR / name
        return path.relative_to(Path.cwd()) if base == Path.cwd() else path
    raise JobError(f"{label}: {_what(exc)} (and no traceback file could be written)") from None


def _what(exc: BaseException) -> str:
    """``<type>: <message on one line>`` of an exception."""
    message = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {message}" if message else type(exc).__name__


def run_job(job: Callable[[], Any], label: str) -> Any:
    """`job()`; an exception other than an FtcalError becomes a JobError naming `label` and the file of
    its traceback (`save_traceback`)."""
    try:
        return job()
    except FtcalError:
        raise
    except Exception as exc:
        raise JobError(f"{label}: {_what(exc)} (traceback in {save_traceback(exc, label)})") from None


def _run(index: int) -> Any:
    return run_job(*_JOBS[index])


def forked_map(
    jobs: Sequence[Callable[[], Any]],
    workers: int | None = None,
    costs: Sequence[float] | None = None,
    labels: Sequence[str] | None = None,
) -> Iterator[Any]:
    """The results of `jobs`, in order, computed in up to `workers` (default: one per core) forked
    processes; yields each as soon as it and the ones before it are done.

    With `costs` (one per job, e.g. input bytes), the workers take the costliest jobs first, which
    balances the workers when the jobs' sizes differ; the results still come in the order of `jobs`.
    `labels` (one per job: the file or name it works on; default ``job <k>``) name a job in its error.
    If a job raises, the jobs not started yet are dropped and its error (module docstring) is raised here.
    """
    global _JOBS
    named = list(labels) if labels is not None else [f"job {k}" for k in range(len(jobs))]
    if len(named) != len(jobs):
        raise ValueError(f"forked_map: {len(named)} labels for {len(jobs)} jobs")
    n = min(workers or os.cpu_count() or 1, len(jobs))
    if n < 2 or "fork" not in multiprocessing.get_all_start_methods():
        for job, label in zip(jobs, named, strict=True):
            yield run_job(job, label)
        return
    order = list(range(len(jobs)))
    if costs is not None:
        ranked = list(costs)
        order.sort(key=lambda i: -ranked[i])  # stable: equal costs keep the jobs' order
    _JOBS = [(jobs[i], named[i]) for i in order]
    gc.freeze()  # what exists now is out of the workers' collections: they neither scan nor copy it
    pool = ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("fork"))
    done: dict[int, Any] = {}
    try:
        following = 0  # the next job (index into `jobs`) to yield
        for i, result in zip(order, pool.map(_run, range(len(jobs))), strict=True):
            done[i] = result
            while following in done:
                yield done.pop(following)
                following += 1
    except BrokenProcessPool:  # a worker killed (out of memory, a signal) or crashed in a library
        pending = [named[i] for i in order if i not in done and i >= following]
        more = f" and {len(pending) - 3} more" if len(pending) > 3 else ""
        what = "a worker process ended abruptly (killed, out of memory or crashed)"
        raise JobError(f"{', '.join(pending[:3])}{more}: {what}") from None
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        _JOBS = []
