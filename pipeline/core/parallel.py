"""Independent jobs run in one forked process per core: the one home of the stages' process parallelism.

A job is a callable without arguments. The workers are forked (Linux), so they inherit the job and its
data without pickling; only results are pickled back, through one pipe per worker. Each job computes what
it would compute alone (figures byte for byte, networks bit for bit: every torch process runs the same
single-threaded kernels, `pipeline.core.kernels`). Where the OS cannot fork, or for one job or one core,
the jobs run here, one by one.

A job's error reaches the caller as one line: an `FtcalError` as it is (it names its file or key); any
other exception (a library's ValueError or RuntimeError on the data) as a `JobError` naming the job's label
(the file or name it works on), the exception, and the file under ``TRACEBACK_DIR`` of the working
directory that holds its full traceback; the CLI prints that line, never the traceback.

Nothing outlives its caller. When a job fails, when the caller stops reading the results (an exception of
its own, Ctrl-C, a SIGTERM that `pipeline.cli` turns into `Terminated`), every worker still running is
asked to stop (SIGTERM: its temporary files are removed as an exception unwinds it), killed after
``GRACE_S`` if it has not, and reaped. Workers ignore Ctrl-C themselves (the terminal sends it to the whole
process group; the caller ends them) and die with their parent if it is killed outright
(``PR_SET_PDEATHSIG``). `end_workers` ends the workers of results a caller left unread, for the CLI to call
before its process exits without unwinding (`pipeline.cli.entry`).
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import os
import pickle
import signal
import sys
import tempfile
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from multiprocessing.connection import Connection, Pipe, wait
from pathlib import Path
from typing import Any

from pipeline.core.errors import FtcalError, JobError

TRACEBACK_DIR = Path(".ftcal") / "tracebacks"  # under the working directory (the repo root under DVC)
GRACE_S = 1.0  # how long a worker asked to stop (SIGTERM) may take to unwind before it is killed
_PR_SET_PDEATHSIG = 1  # prctl(2): the signal a process gets when its parent thread ends (Linux)


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


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the process is (`stop_on_sigterm`): it unwinds like Ctrl-C, every ``finally``
    and temporary-file cleanup on the way, and the CLI exits with 143."""


def _raise_terminated(signum: int, frame: Any) -> None:
    raise Terminated()


def stop_on_sigterm() -> None:
    """From now on SIGTERM raises `Terminated` in this process's main thread."""
    signal.signal(signal.SIGTERM, _raise_terminated)


class _Workers:
    """`n` forked processes serving the jobs `jobs` by index over one duplex pipe each."""

    def __init__(self, jobs: Sequence[tuple[Callable[[], Any], str]], n: int) -> None:
        self.owner = os.getpid()
        self.pids: dict[Connection, int] = {}
        for _ in range(n):
            here, there = Pipe()
            pid = os.fork()
            if pid == 0:  # the worker: serve, then out without unwinding into the caller's frames
                here.close()
                for conn in self.pids:  # the other workers' pipes: not this one's to hold open
                    conn.close()
                _LIVE.clear()
                os._exit(_serve(there, jobs, self.owner))
            there.close()
            self.pids[here] = pid
        _LIVE.append(self)

    def end(self, stop: bool) -> None:
        """Tell each worker to leave (its jobs all done), or with `stop` end it (SIGTERM; SIGKILL after
        `GRACE_S`); then reap every one and close the pipes."""
        for conn, pid in self.pids.items():
            with contextlib.suppress(OSError):
                if stop:
                    os.kill(pid, signal.SIGTERM)
                else:
                    conn.send(None)
        left = set(self.pids.values())
        deadline = time.monotonic() + GRACE_S
        while left := {pid for pid in left if not _reaped(pid)}:
            if time.monotonic() > deadline:
                for pid in left:
                    with contextlib.suppress(OSError):
                        os.kill(pid, signal.SIGKILL)
                for pid in left:
                    with contextlib.suppress(ChildProcessError):
                        os.waitpid(pid, 0)
                break
            time.sleep(0.005)
        for conn in self.pids:
            conn.close()
        self.pids.clear()
        with contextlib.suppress(ValueError):
            _LIVE.remove(self)


def _reaped(pid: int) -> bool:
    """Whether the child `pid` has ended (and is reaped now)."""
    try:
        return os.waitpid(pid, os.WNOHANG)[0] != 0
    except ChildProcessError:  # reaped already
        return True


_LIVE: list[_Workers] = []  # the pools of this process whose workers have not been reaped yet


def end_workers() -> None:
    """End and reap the workers of every `forked_map` whose results a caller left unread (an exception of
    its own stopped it reading them): nothing of a failed command stays running."""
    for pool in list(_LIVE):
        if pool.owner == os.getpid():
            pool.end(stop=True)


def _serve(conn: Connection, jobs: Sequence[tuple[Callable[[], Any], str]], parent: int) -> int:
    """A worker's loop: run the job of each index received, send back (True, result) or (False, error);
    None: leave. Returns the exit status."""
    libc = ctypes.CDLL(None, use_errno=True) if sys.platform.startswith("linux") else None
    if libc is not None:
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)  # the parent killed outright: this one too
    if os.getppid() != parent:  # the parent ended before the line above
        return 1
    signal.signal(signal.SIGINT, lambda *_: None)  # Ctrl-C is the parent's to handle: it ends this one
    stop_on_sigterm()  # the parent's SIGTERM: unwind (temporary files removed), then leave
    try:
        while (index := conn.recv()) is not None:
            try:
                reply = (True, run_job(*jobs[index]))
            except Terminated:  # the parent ends this worker
                raise
            except BaseException as exc:  # an FtcalError, a JobError naming the job, or the job's own exit
                reply = (False, _portable(exc, jobs[index][1]))
            try:
                conn.send(reply)
            except (pickle.PicklingError, TypeError, AttributeError) as exc:
                why = f"{jobs[index][1]}: its result cannot be sent back: {_what(exc)}"
                conn.send((False, JobError(why)))
    except (KeyboardInterrupt, EOFError, BrokenPipeError):  # ended by the parent, or the parent gone
        return 1
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
    return 0


def _portable(exc: BaseException, label: str) -> BaseException:
    """`exc` if it survives pickling (it crosses the pipe), else a JobError with its message."""
    try:
        pickle.loads(pickle.dumps(exc))
    except Exception:
        return JobError(" ".join(str(exc).split()) or f"{label}: {type(exc).__name__}")
    return exc


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
    If a job raises, the jobs not started yet are dropped, the running ones ended, and its error (module
    docstring) is raised here.
    """
    named = list(labels) if labels is not None else [f"job {k}" for k in range(len(jobs))]
    if len(named) != len(jobs):
        raise ValueError(f"forked_map: {len(named)} labels for {len(jobs)} jobs")
    n = min(workers or os.cpu_count() or 1, len(jobs))
    if n < 2 or not hasattr(os, "fork"):
        for job, label in zip(jobs, named, strict=True):
            yield run_job(job, label)
        return
    order = list(range(len(jobs)))
    if costs is not None:
        ranked = list(costs)
        order.sort(key=lambda i: -ranked[i])  # stable: equal costs keep the jobs' order
    gc.freeze()  # what exists now is out of the workers' collections: they neither scan nor copy it
    pool = _Workers([(job, label) for job, label in zip(jobs, named, strict=True)], n)
    finished = False
    try:
        yield from _results(pool, deque(order), named)
        finished = True
    finally:
        pool.end(stop=not finished)


def _results(pool: _Workers, queue: deque[int], named: Sequence[str]) -> Iterator[Any]:
    """Hand the jobs of `queue` to `pool`'s workers as each comes free; yield the results in job order."""
    running: dict[Connection, int] = {}  # a worker's pipe -> the job it runs

    def give(conn: Connection) -> None:
        if queue:
            running[conn] = queue.popleft()
            conn.send(running[conn])

    for conn in pool.pids:
        give(conn)
    done: dict[int, Any] = {}
    following = 0  # the next job (index into `jobs`) to yield
    while following < len(named):
        for conn in wait(list(running)):
            i = running.pop(conn)
            try:
                ok, value = conn.recv()
            except (EOFError, OSError):  # the worker died: killed (out of memory, a signal) or crashed
                what = "a worker process ended abruptly (killed, out of memory or crashed)"
                raise JobError(f"{named[i]}: {what}") from None
            if not ok:
                raise value
            done[i] = value
            give(conn)
        while following in done:
            yield done.pop(following)
            following += 1
