"""The text of a YARP dataDumper port: ``data.log`` lines parsed into arrays (format:
docs/recorded-logs.md, reference).

Every line is ``<seq> <time> [<time>] <payload>``, separated by single spaces. ``seq`` is the sender's
counter (not a time base); the first time is the sender's stamp (float s since the epoch, 6 decimals),
the optional second one the dumper's reception time. Which form a port uses is read from its first line's
field count, never guessed per line. Payloads:

- ``analog:o`` of an FT part: 6 floats ``fx fy fz tx ty tz`` (N, Nm);
- ``stateExt:o`` of a control board: parenthesised groups, each followed by a status word (``[ok]``):
  joint positions (deg), velocities (deg/s), accelerations, motor positions, motor velocities, motor
  accelerations, joint torques (Nm), PWM, modes. Only `GROUPS` are read, by position;
- ``state:o`` of a control board: the joint positions alone (deg), one plain vector of the board's axes
  (YARP's control-board wrapper writes a ``yarp::sig::Vector`` of its encoders there, which the dumper
  prints as a Bottle: the numbers separated by spaces). Its field count does not tell the two time forms
  apart (the board's axis count is not known): the ``Stamp:`` line of info.log does (``tx``, ``rx`` or
  ``tx+rx``, written by dumpers since YARP 3.2), else the first line's third field is the reception time
  when it lies within a minute of an epoch stamp (no joint angle in degrees does).

A malformed line (field count, a non-number, a positions group whose status word is not ``ok``, too few
joint values) is an error naming the file and line; a group of velocities or torques whose status word is
not ``ok`` is NaN for that message. A last line cut short without its newline (a dumper killed while
writing) is dropped with a warning.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.core.errors import DataError
from pipeline.logs.matlog import seconds_to_ns

WRENCH_VALUES = 6
GROUPS = {"position": 0, "velocity": 1, "effort": 6}  # stateExt:o group index of each field read
_GROUP = re.compile(r"\(([^()]*)\)\s*\[([^\[\]]*)\]")
_DEG = np.pi / 180.0


@dataclass
class PortData:
    """One port's messages in file order. stamp_ns (M,) int64: sender stamps; recv_ns (M,) int64: the
    dumper's reception time (two-time form), else the largest stamp so far (the file order is the
    arrival order); values: field -> (M, K) float64 (wrench N/Nm; position rad, velocity rad/s,
    effort Nm)."""

    path: Path
    stamp_ns: np.ndarray
    recv_ns: np.ndarray
    values: dict[str, np.ndarray]
    two_times: bool
    warnings: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.stamp_ns)


def _float(token: str, path: Path, line: int, what: str) -> float:
    try:
        return float(token)
    except ValueError:
        raise DataError(f"{path}:{line}: {what} {token!r} is not a number") from None


def _lines(path: Path, warnings: list[str]) -> list[str]:
    try:
        text = path.read_text(encoding="ascii", errors="strict")
    except UnicodeDecodeError as exc:
        line = text_line_of(path, exc.start)
        raise DataError(f"{path}:{line}: not text (byte {exc.object[exc.start]:#04x})") from None
    except OSError as exc:
        raise DataError(f"{path}: cannot read: {exc.strerror or exc}") from None
    lines = text.split("\n")
    if lines and lines[-1] == "":
        lines.pop()
    elif lines:
        warnings.append(f"{path}: last line has no newline (dumper stopped while writing?): dropped")
        lines.pop()
    return lines


def text_line_of(path: Path, offset: int) -> int:
    """1-based line number of byte `offset` of a file."""
    with open(path, "rb") as f:
        return f.read(offset).count(b"\n") + 1


def _times(tokens: list[str], n_times: int, path: Path, line: int) -> tuple[float, float | None]:
    if len(tokens) < 1 + n_times:
        raise DataError(f"{path}:{line}: expected <seq> and {n_times} time(s), got {len(tokens)} fields")
    if not tokens[0].lstrip("-").isdigit():
        raise DataError(f"{path}:{line}: sequence number {tokens[0]!r} is not an integer")
    t = _float(tokens[1], path, line, "time")
    recv = _float(tokens[2], path, line, "reception time") if n_times == 2 else None
    return t, recv


def _rows(values: list | np.ndarray, m: int) -> np.ndarray:
    """(m, K) float64 of `m` rows (an empty data.log: (0, 0))."""
    a = np.asarray(values, dtype=np.float64)
    return a.reshape(m, -1) if m else a.reshape(0, a.shape[1] if a.ndim == 2 else 0)


def _finish(path: Path, stamps: list[float], recv: list[float | None], values: dict, two: bool, warnings):
    stamp_ns = seconds_to_ns(np.asarray(stamps, dtype=np.float64))
    if two:
        recv_ns = seconds_to_ns(np.asarray(recv, dtype=np.float64))
    else:
        recv_ns = np.maximum.accumulate(stamp_ns) if len(stamp_ns) else stamp_ns.copy()
    arrays = {k: _rows(v, len(stamps)) for k, v in values.items()}
    return PortData(path, stamp_ns, recv_ns, arrays, two, warnings)


def _vectors(path: Path, lines: list[str], n_times: int, what: str) -> tuple[list, list, list]:
    """(stamps, reception times, values) of plain-vector lines ``<seq> <time> [<time>] v1 ... vn``, every
    line with the field count of the first."""
    width = len(lines[0].split(" ")) if lines else 0
    stamps, recv, rows = [], [], []
    for k, text in enumerate(lines, start=1):
        tokens = text.split(" ")
        if len(tokens) != width:
            raise DataError(f"{path}:{k}: {len(tokens)} fields, expected {width} (as on line 1)")
        t, r = _times(tokens, n_times, path, k)
        stamps.append(t)
        recv.append(r)
        rows.append([_float(v, path, k, what) for v in tokens[1 + n_times :]])
    return stamps, recv, rows


def read_analog(path: Path) -> PortData:
    """An FT ``analog:o`` data.log: wrench (M, 6), N and Nm."""
    warnings: list[str] = []
    lines = _lines(path, warnings)
    width = len(lines[0].split(" ")) if lines else 2 + WRENCH_VALUES
    if width not in (2 + WRENCH_VALUES, 3 + WRENCH_VALUES):
        raise DataError(
            f"{path}:1: {width} fields, expected {2 + WRENCH_VALUES} (<seq> <time> and 6 wrench values) "
            f"or {3 + WRENCH_VALUES} (with the reception time)"
        )
    n_times = width - 1 - WRENCH_VALUES
    stamps, recv, wrench = _vectors(path, lines, n_times, "wrench value")
    return _finish(path, stamps, recv, {"wrench": wrench}, n_times == 2, warnings)


def _state_times(path: Path, first: str, stamp: str) -> int:
    """How many times (1 or 2) a ``state:o`` line carries: from info.log's `stamp` form, else from the
    first line (module docstring)."""
    if stamp:
        return 2 if stamp == "tx+rx" else 1
    tokens = first.split(" ")
    if len(tokens) < 3:
        return 1
    t = _float(tokens[1], path, 1, "time")
    try:
        third = float(tokens[2])
    except ValueError:
        return 1
    return 2 if t > 1e8 and -1.0 <= third - t <= 60.0 else 1


def read_positions(path: Path, n_axes: int, stamp: str = "") -> PortData:
    """A control board's ``state:o`` data.log: position (M, A) rad of its first `n_axes` axes; velocity
    and effort (M, A) NaN (the port has none). `stamp`: info.log's ``Stamp:`` form ('' if absent)."""
    warnings: list[str] = []
    lines = _lines(path, warnings)
    n_times = _state_times(path, lines[0], stamp) if lines else 1
    stamps, recv, rows = _vectors(path, lines, n_times, "joint position")
    if rows and len(rows[0]) < n_axes:
        raise DataError(f"{path}:1: {len(rows[0])} joint positions, the joint map needs {n_axes} axes")
    q = np.asarray(rows, dtype=np.float64)[:, :n_axes] * _DEG if rows else np.zeros((0, n_axes))
    values = {"position": q, "velocity": np.full_like(q, np.nan), "effort": np.full_like(q, np.nan)}
    return _finish(path, stamps, recv, values, n_times == 2, warnings)


def read_joint_port(path: Path, n_axes: int, stamp: str = "") -> PortData:
    """A control board's joint port, ``stateExt:o`` (groups in parentheses: `read_state`) or ``state:o``
    (a plain vector of positions: `read_positions`), told apart by its first line."""
    with open(path, "rb") as f:
        first = f.readline()
    return read_state(path, n_axes) if b"(" in first else read_positions(path, n_axes, stamp)


def read_state(path: Path, n_axes: int) -> PortData:
    """A control board's ``stateExt:o`` data.log: position (M, A) rad, velocity (M, A) rad/s, effort
    (M, A) Nm for its first `n_axes` axes (a line with fewer joint values is an error)."""
    warnings: list[str] = []
    lines = _lines(path, warnings)
    n_times = 0
    if lines:
        head = lines[0].split("(", 1)[0].split()
        n_times = len(head) - 1
        if n_times not in (1, 2):
            raise DataError(
                f"{path}:1: {len(head)} fields before the first group, expected 2 (<seq> <time>) or 3 "
                "(with the reception time)"
            )
    stamps, recv = [], []
    values: dict[str, list[list[float]]] = {k: [] for k in GROUPS}
    for k, text in enumerate(lines, start=1):
        head, _, rest = text.partition("(")
        tokens = head.split()
        if len(tokens) != 1 + n_times:
            raise DataError(
                f"{path}:{k}: {len(tokens)} fields before the first group, expected {1 + n_times} "
                "(as on line 1)"
            )
        t, r = _times(tokens, n_times, path, k)
        groups = _GROUP.findall("(" + rest)
        if len(groups) <= GROUPS["position"]:
            raise DataError(f"{path}:{k}: no '(values) [status]' group of joint positions")
        for name, g in GROUPS.items():
            numbers, status = groups[g] if g < len(groups) else ("", "missing")
            row = [_float(v, path, k, f"{name} value") for v in numbers.split()]
            if name == "position":
                if status != "ok":
                    raise DataError(f"{path}:{k}: joint positions have status [{status}], not [ok]")
                if len(row) < n_axes:
                    raise DataError(
                        f"{path}:{k}: {len(row)} joint positions, the joint map needs {n_axes} axes"
                    )
            if status != "ok" or len(row) < n_axes:
                row = [np.nan] * n_axes  # an invalid group: no value in this message
            scale = 1.0 if name == "effort" else _DEG
            values[name].append([v * scale for v in row[:n_axes]])
        stamps.append(t)
        recv.append(r)
    return _finish(path, stamps, recv, values, n_times == 2, warnings)


def read_info(path: Path) -> dict[str, str]:
    """``info.log``: the type line, the stamp line (``tx``, ``rx``, ``tx+rx``; dumpers since YARP 3.2) and
    the full port name of the first connection, {"type", "stamp", "port"} ('' when not found)."""
    out = {"type": "", "stamp": "", "port": ""}
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return out
    for line in text.splitlines():
        if line.startswith("Type:"):
            out["type"] = line[len("Type:") :].strip().rstrip(";").strip()
        elif line.startswith("Stamp:"):
            out["stamp"] = line[len("Stamp:") :].strip().rstrip(";").strip()
        elif "]" in line and not out["port"]:
            words = line.split("]", 1)[1].split()
            out["port"] = words[0] if words else ""
    return out
