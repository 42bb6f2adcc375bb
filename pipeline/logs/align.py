"""Aligning message streams on the time base of a log (the joint-state stamps).

How the messages of a stream become values at a time-base sample:

- Arrival order is the recorder's (log time, file position). Messages whose stamps go back by less than
  ``ingest.max_reorder_s`` in arrival order are out of order and simply re-sorted by stamp; a larger
  step back is a clock jump and an error. Messages with an already seen stamp are duplicates: the
  first to arrive is kept. Messages with NaN/inf values are dropped (an error beyond
  ``ingest.max_nonfinite_fraction`` of a topic's messages).
- Continuous signals (wrench, IMU, temperature, simulated wrenches) are linearly interpolated between
  the last message at or before the sample and the first after it; the sample is ok when those two
  messages are at most the stream's max gap apart (``ingest.max_gap_s``, ``ingest.max_gap_temperature_s``),
  or one message has exactly its stamp. Otherwise the values are NaN and ``ok.<stream>`` is False:
  too many lost messages, a stream that starts late or stops early; never a silent extrapolation.
- Discrete signals (the simulated contact set) take the latest message at or before the sample.
- Frozen streams: a board that stops updating keeps sending its last reading. For the streams that
  check it (the FT wrenches), a run of consecutive messages with identical values spanning more than
  ``ingest.max_frozen_s`` is frozen; a sample whose latest message at or before it belongs to such a run
  is NaN and not ok, like a gap (`frozen_runs`).

A `Stream` holds the messages of one topic between two writes of the table, so that memory stays bounded
whatever the log's length.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pipeline.core.errors import DataError

# --- pure alignment functions --------------------------------------------------------------------


def align_continuous(
    target_ns: np.ndarray, source_ns: np.ndarray, values: np.ndarray, max_gap_ns: int
) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of a continuous signal at the target stamps, within a max gap.

    Args:
        target_ns: (N,) int64 ns, increasing.
        source_ns: (M,) int64 ns, strictly increasing.
        values: (M, K) float values at `source_ns`, finite.
        max_gap_ns: a target is ok iff a source stamp equals it, or the last source stamp before it
            and the first after it are at most this far apart.

    Returns:
        ((N, K) float64 values, NaN where not ok; (N,) bool ok).
    """
    n = len(target_ns)
    out = np.full((n, values.shape[1]), np.nan)
    if len(source_ns) == 0 or n == 0:
        return out, np.zeros(n, dtype=bool)
    after = np.searchsorted(source_ns, target_ns, side="right")  # first source stamp > target
    before = after - 1
    has_before = before >= 0
    b = np.clip(before, 0, len(source_ns) - 1)
    a = np.clip(after, 0, len(source_ns) - 1)
    exact = has_before & (source_ns[b] == target_ns)
    bracket = has_before & (after < len(source_ns)) & (source_ns[a] - source_ns[b] <= max_gap_ns)
    ok = exact | bracket
    span = (source_ns[a] - source_ns[b]).astype(np.float64)
    w = np.where(bracket & ~exact, (target_ns - source_ns[b]) / np.where(span > 0, span, 1.0), 0.0)
    interp = values[b] + w[:, None] * (values[a] - values[b])
    out[ok] = interp[ok]
    return out, ok


def align_latest(target_ns: np.ndarray, source_ns: np.ndarray, values: np.ndarray) -> np.ndarray:
    """A discrete signal at the target stamps: the latest source value at or before each (None before any).

    target_ns (N,) and source_ns (M,) int64 ns increasing; values (M,) object. Returns (N,) object.
    """
    idx = np.searchsorted(source_ns, target_ns, side="right") - 1
    out = np.full(len(target_ns), None, dtype=object)
    has = idx >= 0
    out[has] = values[idx[has]]
    return out


def arrival_order(log_time_ns: np.ndarray, file_order: np.ndarray) -> np.ndarray:
    """Permutation that puts messages in the recorder's arrival order: log time, then file position."""
    return np.lexsort((file_order, log_time_ns))


def stamp_steps_back(stamps_ns: np.ndarray, previous_max: int | None) -> np.ndarray:
    """(M,) int64: how far each stamp lies behind the largest stamp before it (arrival order), >= 0."""
    if len(stamps_ns) == 0:
        return np.zeros(0, dtype=np.int64)
    start = stamps_ns[0] if previous_max is None else max(int(previous_max), int(stamps_ns[0]))
    running = np.maximum.accumulate(np.concatenate([[start], stamps_ns[:-1]]))
    return np.maximum(running - stamps_ns, 0)


def sort_unique(stamps_ns: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Sort by stamp (stable) and drop repeated stamps, keeping the first.

    Returns (stamps, values, number of messages dropped).
    """
    perm = np.argsort(stamps_ns, kind="stable")
    s, v = stamps_ns[perm], values[perm]
    keep = np.ones(len(s), dtype=bool)
    keep[1:] = s[1:] != s[:-1]
    return s[keep], v[keep], int((~keep).sum())


def frozen_runs(
    stamps_ns: np.ndarray, values: np.ndarray, first_run_start: int | None, max_frozen_ns: int
) -> tuple[np.ndarray, np.ndarray]:
    """Runs of identical readings: each message's run start and whether its run is frozen.

    Args:
        stamps_ns: (M,) int64 ns, strictly increasing.
        values: (M, K) readings at those stamps.
        first_run_start: ns, the run start of the first message when its run began before these
            messages (a stream read in pieces), else None.
        max_frozen_ns: a run whose stamps span more than this is frozen.

    Returns:
        ((M,) int64 run start of each message, (M,) bool frozen). The last run may still grow: its span
        is the one known so far.
    """
    m = len(stamps_ns)
    if m == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool)
    starts = np.ones(m, dtype=bool)
    starts[1:] = ~np.all(values[1:] == values[:-1], axis=1)
    first = np.maximum.accumulate(np.where(starts, np.arange(m), 0))  # index of each run's first message
    run_start = stamps_ns[first]
    if first_run_start is not None:
        run_start[first == 0] = first_run_start
    last = np.minimum.accumulate(np.where(np.r_[starts[1:], True], np.arange(m), m - 1)[::-1])[::-1]
    return run_start, stamps_ns[last] - run_start > max_frozen_ns


def median_rate_hz(stamps_ns: np.ndarray) -> float:
    """1 / median stamp step, in Hz (NaN with fewer than 2 stamps)."""
    if len(stamps_ns) < 2:
        return float("nan")
    return 1e9 / float(np.median(np.diff(stamps_ns)))


def joint_permutation(names: Sequence[str], joints: Sequence[str]) -> tuple[np.ndarray, list[str], list[str]]:
    """Column indices that reorder a JointState's arrays into `joints` order.

    Returns (perm (len(joints),) int, names not in `joints`, `joints` missing from names).
    """
    index = {name: k for k, name in enumerate(names)}
    unknown = [n for n in names if n not in set(joints)]
    missing = [j for j in joints if j not in index]
    perm = np.array([index.get(j, -1) for j in joints], dtype=np.int64)
    return perm, unknown, missing


# --- streams -------------------------------------------------------------------------------------


@dataclass
class StreamStats:
    """Counts of one topic over a log (reported in the Parquet metadata and MLflow)."""

    topic: str
    msgtype: str
    messages: int = 0
    duplicates: int = 0  # same stamp as an earlier message: dropped
    reordered: int = 0  # arrived after a message with a later stamp: re-sorted
    nonfinite: int = 0  # NaN/inf values: dropped
    late: int = 0  # arrived after the samples around its stamp were written (too late to be used)
    frozen_samples: int = 0  # time-base samples inside a frozen run (not ok)
    zero_stamps: int = 0  # header stamp 0: a driver that does not stamp
    usable_samples: int = 0  # time-base samples at which the stream has a value (ok)
    rate_hz: float = float("nan")  # 1 / median stamp step
    first_stamp_ns: int | None = None
    last_stamp_ns: int | None = None


class Stream:
    """Messages of one topic between two writes: kept sorted, unique and finite."""

    def __init__(
        self,
        name: str,
        topic: str,
        msgtype: str,
        width: int,
        max_gap_ns: int,
        where: str,
        max_reorder_ns: int,
        discrete: bool = False,
        time_base: bool = False,
        finite_columns: int | np.ndarray | None = None,
        max_frozen_ns: int | None = None,
    ):
        self.name, self.topic, self.where = name, topic, where
        self.width, self.max_gap_ns, self.max_reorder_ns = width, max_gap_ns, max_reorder_ns
        self.discrete, self.time_base = discrete, time_base
        # The first `finite_columns` values (or these column indices) must be finite for a message to be
        # kept (all by default).
        self._finite = (
            np.arange(width)
            if finite_columns is None
            else np.arange(finite_columns)
            if isinstance(finite_columns, int)
            else np.asarray(finite_columns, dtype=np.intp)
        )
        self.max_frozen_ns = max_frozen_ns  # None: no frozen check
        self._run_start: np.ndarray = np.empty(0, dtype=np.int64)  # per buffered message (frozen check)
        self._frozen: np.ndarray = np.empty(0, dtype=bool)
        self._carry: tuple[int, int] | None = None  # (stamp, run start) of the first message kept by trim
        self.stats = StreamStats(topic, msgtype)
        self.t = np.empty(0, dtype=np.int64)
        self.v: np.ndarray = np.empty(0, dtype=object) if discrete else np.empty((0, width))
        self._new: list[tuple[np.ndarray, np.ndarray]] = []
        self.max_stamp: int | None = None
        self.max_delay: int | None = None  # largest (log time - stamp) seen, ns
        self.written_upto: int | None = None  # last time-base stamp written
        self._steps: list[float] = []  # median stamp step per merge, for the rate

    def add(self, stamps: np.ndarray, log_time: np.ndarray, order: np.ndarray, values: np.ndarray) -> None:
        perm = arrival_order(log_time, order)
        stamps, values = stamps[perm], values[perm]
        back = stamp_steps_back(stamps, self.max_stamp)
        worst = int(np.argmax(back)) if len(back) else 0
        if len(back) and back[worst] > self.max_reorder_ns:
            raise DataError(
                f"{self.where}: non-monotonic stamps on {self.topic}: message {self.stats.messages + worst} "
                f"goes back {back[worst] / 1e9:.3f} s in arrival order (clock jump or reset?; "
                f"ingest.max_reorder_s = {self.max_reorder_ns / 1e9:g} s)"
            )
        self.stats.messages += len(stamps)
        self.stats.reordered += int((back > 0).sum())
        if len(stamps):
            top = int(stamps.max())
            self.max_stamp = top if self.max_stamp is None else max(self.max_stamp, top)
            delay = int((log_time[perm] - stamps).max())
            self.max_delay = delay if self.max_delay is None else max(self.max_delay, delay)
        if not self.discrete:
            finite = np.isfinite(values[:, self._finite]).all(axis=1)
            self.stats.nonfinite += int((~finite).sum())
            stamps, values = stamps[finite], values[finite]
        if self.written_upto is not None:
            # Arrived after the rows around its stamp were written (a stream that lagged beyond _STALL_S):
            # a time-base message is dropped, another one could not change those rows any more.
            late = stamps <= self.written_upto
            self.stats.late += int(late.sum())
            if self.time_base:
                stamps, values = stamps[~late], values[~late]
        if len(stamps):
            self._new.append((stamps, values))

    def horizon(self, log_time_now: int, max_reorder_ns: int) -> int | None:
        """Stamp below which no message of this stream can still arrive (None: unknown yet).

        New messages step back at most the reorder window from the largest stamp seen, and arrive no
        earlier than the latest log time read so far (minus the largest delay seen): the second bound
        keeps a silent stream (a discrete signal that did not change) from holding everything back.
        """
        if self.max_stamp is None or self.max_delay is None:
            return None
        return max(self.max_stamp, log_time_now - self.max_delay) - max_reorder_ns

    def buffered(self) -> int:
        """Number of messages held (before removing duplicates)."""
        return len(self.t) + sum(len(s) for s, _ in self._new)

    def merged(self) -> tuple[np.ndarray, np.ndarray]:
        """All buffered messages, sorted by stamp, duplicates dropped (first arrival kept)."""
        if self._new:
            t = np.concatenate([self.t, *(s for s, _ in self._new)])
            v = np.concatenate([self.v, *(v for _, v in self._new)])
            self._new = []
            self.t, self.v, dropped = sort_unique(t, v)
            self.stats.duplicates += dropped
            if self.max_frozen_ns is not None:
                same_first = self._carry is not None and len(self.t) and self.t[0] == self._carry[0]
                carry = self._carry[1] if same_first else None
                self._run_start, self._frozen = frozen_runs(self.t, self.v, carry, self.max_frozen_ns)
        return self.t, self.v

    def frozen_at(self, target_ns: np.ndarray) -> np.ndarray:
        """(N,) bool: the latest message at or before each target stamp is in a frozen run (call `merged`
        first). All False for a stream without the check."""
        if self.max_frozen_ns is None or len(self.t) == 0:
            return np.zeros(len(target_ns), dtype=bool)
        idx = np.searchsorted(self.t, target_ns, side="right") - 1
        return (idx >= 0) & self._frozen[np.maximum(idx, 0)]

    def trim(self, written_upto: int) -> None:
        """Forget what no later sample can need, once samples up to `written_upto` are written."""
        self.written_upto = written_upto
        if len(self.t) > 1:
            self._steps.append(float(np.median(np.diff(self.t))))
        if self.time_base:
            keep = self.t > written_upto
        elif self.discrete:
            last = np.searchsorted(self.t, written_upto, side="right") - 1
            keep = np.arange(len(self.t)) >= max(last, 0)
        else:
            keep = self.t >= written_upto - self.max_gap_ns
        if len(self.t):
            self.stats.first_stamp_ns = (
                int(self.t[0]) if self.stats.first_stamp_ns is None else self.stats.first_stamp_ns
            )
            self.stats.last_stamp_ns = (
                int(self.t[-1])
                if self.stats.last_stamp_ns is None
                else max(self.stats.last_stamp_ns, int(self.t[-1]))
            )
        self.t, self.v = self.t[keep], self.v[keep]
        if self.max_frozen_ns is not None and len(self._run_start) == len(keep):
            self._run_start, self._frozen = self._run_start[keep], self._frozen[keep]
            self._carry = (int(self.t[0]), int(self._run_start[0])) if len(self.t) else self._carry

    def finish(self) -> StreamStats:
        if self._steps:
            self.stats.rate_hz = 1e9 / float(np.median(self._steps))
        return self.stats
