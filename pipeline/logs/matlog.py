"""Low-level access to YarpRobotLoggerDevice ``.mat`` files (MATLAB v7.3 = HDF5, or v5/v7 re-saved).

The logger (bipedal-locomotion-framework, through robometry and matioCpp) writes one top-level struct,
normally ``robot_logger_device`` (``robot_logger_device_<tag>`` when saved with a tag), holding
``description_list`` (cell of joint names), ``yarp_robot_name`` (char) and a tree of structs whose
leaves are channels: ``data`` (MATLAB ``k x 1 x N`` doubles, sample t at linear indices ``k t .. k t +
k - 1``), ``timestamps`` (``1 x N`` seconds), ``elements_names`` (cell of k labels), ``name``. A channel
empty at save time is a struct without fields. Channels have their own N (a sample is written only when
the read succeeded), so every channel keeps its own stamps.

Channels are named by their struct path below the top-level struct, with ``/`` between levels
(``FTs/l_leg_ft``, ``joints_state/positions``). v7.3 files are read with h5py one window of samples
at a time, in whole HDF5 chunks (HDF5 reverses MATLAB's axes: ``data`` is ``(N, 1, k)``, time first);
v5/v7 files through ``scipy.io.loadmat``, which reads the whole file at once (they are small: MATLAB's
v7 format caps variables at 2 GiB, which is why the logger writes v7.3).

Timestamps are float64 seconds since the epoch: about 0.24 us apart at today's epoch. They become
int64 ns with `seconds_to_ns` (at most 0.12 us from the value the float stands for).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.errors import DataError

DESCRIPTION_LIST = "description_list"
ROBOT_NAME = "yarp_robot_name"
_HEADER_BYTES = 128  # MATLAB's text header (then subsystem offset, version, endian) at the file start
_SKIP = ("#refs#", "#subsystem#")  # HDF5 groups MATLAB keeps for references / class data, not variables


def seconds_to_ns(seconds: np.ndarray) -> np.ndarray:
    """(N,) float64 s -> (N,) int64 ns, splitting off whole seconds so that no precision is lost beyond
    the float's own (a plain ``t * 1e9`` at 1.7e18 ns rounds to 256 ns)."""
    t = np.asarray(seconds, dtype=np.float64).reshape(-1)
    whole = np.floor(t)
    return whole.astype(np.int64) * 10**9 + np.round((t - whole) * 1e9).astype(np.int64)


def ns_to_seconds(stamps_ns: np.ndarray) -> np.ndarray:
    """(N,) int64 ns -> (N,) float64 s, correctly rounded to within one float step (~0.24 us today)."""
    ns = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    whole = ns // 10**9
    return whole.astype(np.float64) + (ns - whole * 10**9).astype(np.float64) / 1e9


class Leaf:
    """One channel: its stamps (read at open) and its samples (read by slices on demand)."""

    def __init__(self, channel: str, stamps_ns: np.ndarray, width: int, reader: Any, names: list[str]):
        self.channel = channel
        self.stamps_ns = stamps_ns  # (N,) int64 ns
        self.width = width  # k values per sample
        self._reader = reader  # (start, stop) -> (n, k) float64
        self.elements_names = names  # k labels, [] when the file has none

    def __len__(self) -> int:
        return len(self.stamps_ns)

    def read(self, start: int, stop: int) -> np.ndarray:
        """(stop - start, k) float64: samples [start, stop)."""
        if stop <= start:
            return np.empty((0, self.width))
        return self._reader(start, stop)


class MatLog:
    """An open logger .mat file: the top-level struct, its joint names and its channels.

    Raises DataError naming the file when it is not a MATLAB file, is truncated or corrupted, or
    holds no logger struct (a top-level struct with a ``description_list``).
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        try:
            with open(self.path, "rb") as f:
                header = f.read(_HEADER_BYTES)
            self.size_bytes = self.path.stat().st_size
        except OSError as exc:
            raise DataError(f"{self.path}: cannot open: {exc.strerror or exc}") from None
        if header.startswith(b"MATLAB 7.3") or _is_hdf5(self.path):
            self.format = "7.3"
            self._backend: _Backend = _H5Backend(self.path, self.error)
        elif header.startswith(b"MATLAB 5.0"):
            self.format = "5"
            self._backend = _Mat5Backend(self.path, self.error)
        else:
            raise self.error("not a MATLAB .mat file (no 'MATLAB 5.0'/'MATLAB 7.3' header, not HDF5)")
        try:
            self.root = self._backend.root()
            self.joints = self._backend.strings(DESCRIPTION_LIST)
            self.robot_name = self._backend.string(ROBOT_NAME)
        except BaseException:
            self.close()
            raise

    def error(self, problem: str) -> DataError:
        return DataError(f"{self.path}: {problem}")

    def leaf(self, channel: str) -> Leaf | None:
        """The channel at this struct path, or None if the file has no such struct.

        A channel present but empty at save time is a Leaf of 0 samples.
        """
        return self._backend.leaf(channel)

    def children(self, group: str) -> list[str]:
        """Names of the structs under `group` (e.g. the sensors under ``FTs``); [] if absent."""
        return self._backend.children(group)

    def close(self) -> None:
        self._backend.close()

    def __enter__(self) -> MatLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _is_hdf5(path: Path) -> bool:
    import h5py

    try:
        return bool(h5py.is_hdf5(str(path)))
    except OSError:
        return False


class _Backend:
    def root(self) -> str: ...
    def strings(self, key: str) -> list[str]: ...
    def string(self, key: str) -> str | None: ...
    def leaf(self, channel: str) -> Leaf | None: ...
    def children(self, group: str) -> list[str]: ...
    def close(self) -> None: ...


def _check_stamps(error: Any, channel: str, stamps: np.ndarray, n: int) -> np.ndarray:
    if len(stamps) != n:
        raise error(f"channel {channel}: {len(stamps)} timestamps for {n} samples")
    if not np.isfinite(stamps).all():
        raise error(f"channel {channel}: non-finite timestamps")
    return seconds_to_ns(stamps)


class _H5Backend(_Backend):
    """MATLAB v7.3: HDF5 with MATLAB_class attributes; cell arrays are object references into #refs#."""

    def __init__(self, path: Path, error: Any):
        import h5py

        self._h5py, self.error = h5py, error
        try:
            # No HDF5 chunk cache: every channel is read forwards in whole chunks (`_BlockReader`), so a
            # cache would only keep up to rdcc_nbytes of spent chunks per open dataset (8 MiB each).
            self.file = h5py.File(path, "r", rdcc_nbytes=0)
        except OSError as exc:
            raise error(f"cannot read as HDF5 (truncated or corrupted MATLAB v7.3 file?): {exc}") from None
        self._root: Any = None

    def _guard(self, what: str, fn: Any, *args: Any) -> Any:
        try:
            return fn(*args)
        except (OSError, KeyError, ValueError, RuntimeError) as exc:
            raise self.error(f"cannot read {what} (truncated or corrupted file?): {exc}") from None

    def root(self) -> str:
        def find() -> str | None:
            for key in self.file:
                node = self.file[key]
                if key not in _SKIP and isinstance(node, self._h5py.Group) and DESCRIPTION_LIST in node:
                    return key
            return None

        key = self._guard("the top-level variables", find)
        if key is None:
            names = ", ".join(k for k in self.file if k not in _SKIP) or "none"
            raise self.error(
                f"not a YarpRobotLoggerDevice log: no top-level struct with a {DESCRIPTION_LIST} "
                f"(top-level variables: {names})"
            )
        self._root = self.file[key]
        return key

    def _text(self, node: Any) -> str:
        if node.attrs.get("MATLAB_empty", 0):
            return ""
        return "".join(map(chr, np.asarray(node[()]).ravel(order="F")))

    def _cellstr(self, node: Any) -> list[str]:
        if node.attrs.get("MATLAB_empty", 0):
            return []
        refs = np.asarray(node[()]).ravel(order="F")
        return [self._text(self.file[r]) for r in refs]

    def strings(self, key: str) -> list[str]:
        return self._guard(f"{self._root.name}/{key}", self._cellstr, self._root[key])

    def string(self, key: str) -> str | None:
        if key not in self._root:
            return None
        return self._guard(f"{self._root.name}/{key}", self._text, self._root[key])

    def _node(self, channel: str) -> Any:
        node = self._root
        for part in channel.split("/"):
            if not isinstance(node, self._h5py.Group) or part not in node:
                return None
            node = node[part]
        return node

    def children(self, group: str) -> list[str]:
        node = self._node(group)
        return list(node) if isinstance(node, self._h5py.Group) else []

    def leaf(self, channel: str) -> Leaf | None:
        node = self._guard(f"channel {channel}", self._node, channel)
        if node is None:
            return None
        if not isinstance(node, self._h5py.Group) or "data" not in node or "timestamps" not in node:
            return Leaf(channel, np.empty(0, dtype=np.int64), 0, None, [])  # empty at save time
        data = node["data"]
        if data.attrs.get("MATLAB_empty", 0) or data.size == 0:
            return Leaf(channel, np.empty(0, dtype=np.int64), 0, None, [])
        stamps = self._guard(f"{channel}/timestamps", lambda: np.asarray(node["timestamps"][()]).ravel())
        n = int(data.shape[0])  # HDF5 reverses MATLAB's k x 1 x N: time is the first axis
        width = int(np.prod(data.shape[1:], dtype=np.int64))
        stamps_ns = _check_stamps(self.error, channel, stamps, n)
        names = (
            self._guard(f"{channel}/elements_names", self._cellstr, node["elements_names"])
            if ("elements_names" in node)
            else []
        )

        def read_rows(start: int, stop: int) -> np.ndarray:
            block = self._guard(f"{channel}/data", lambda: np.asarray(data[start:stop], dtype=np.float64))
            return block.reshape(stop - start, width)

        rows = int(data.chunks[0]) if data.chunks else 1  # HDF5 chunk: rows decompressed together
        return Leaf(channel, stamps_ns, width, _BlockReader(read_rows, n, rows, width), names)

    def close(self) -> None:
        self.file.close()


class _BlockReader:
    """Samples [start, stop) of one channel, read from the file in whole HDF5 chunks of `rows` samples.

    Windows that move forwards (as ingest reads) decompress every chunk once: the rows of the last
    chunk read that lie past `stop` are kept for the next window. Other windows are read afresh.
    """

    def __init__(self, read_rows: Any, n: int, rows: int, width: int):
        self._read_rows, self._n, self._rows = read_rows, n, max(1, rows)
        self._start = self._stop = 0  # rows held in self._buf: [_start, _stop)
        self._buf = np.empty((0, width))

    def __call__(self, start: int, stop: int) -> np.ndarray:
        if not self._start <= start <= self._stop:
            self._start = self._stop = start - start % self._rows
            self._buf = self._buf[:0]
        if stop > self._stop:
            end = min(self._n, -(-stop // self._rows) * self._rows)
            fresh = self._read_rows(self._stop, end)
            first = min(start, self._stop)  # rows held before it are dropped
            kept = self._buf[first - self._start :]
            self._buf = np.concatenate([kept, fresh]) if len(kept) else fresh
            self._start, self._stop = first, end
        return self._buf[start - self._start : stop - self._start]


class _Mat5Backend(_Backend):
    """MATLAB v5/v7 (re-saved in MATLAB without -v7.3): scipy reads the whole file."""

    def __init__(self, path: Path, error: Any):
        from scipy.io import loadmat

        self.error = error
        try:
            self.vars = loadmat(str(path), simplify_cells=True)
        except Exception as exc:  # noqa: BLE001 (scipy raises ValueError, TypeError, OSError... on bad files)
            raise error(f"cannot read as a MATLAB v5/v7 file (truncated or corrupted?): {exc}") from None
        self._root: dict[str, Any] = {}

    def root(self) -> str:
        names = [k for k in self.vars if not k.startswith("__")]
        for key in names:
            value = self.vars[key]
            if isinstance(value, dict) and DESCRIPTION_LIST in value:
                self._root = value
                return key
        raise self.error(
            f"not a YarpRobotLoggerDevice log: no top-level struct with a {DESCRIPTION_LIST} "
            f"(top-level variables: {', '.join(names) or 'none'})"
        )

    def strings(self, key: str) -> list[str]:
        value = self._root[key]
        return (
            [value] if isinstance(value, str) else [str(v) for v in np.asarray(value, dtype=object).ravel()]
        )

    def string(self, key: str) -> str | None:
        value = self._root.get(key)
        return None if value is None else str(value) if not isinstance(value, np.ndarray) else ""

    def _node(self, channel: str) -> Any:
        node: Any = self._root
        for part in channel.split("/"):
            if not isinstance(node, dict) or part not in node:
                return None
            node = node[part]
        return node

    def children(self, group: str) -> list[str]:
        node = self._node(group)
        return list(node) if isinstance(node, dict) else []

    def leaf(self, channel: str) -> Leaf | None:
        node = self._node(channel)
        if node is None:
            return None
        if not isinstance(node, dict) or "data" not in node or "timestamps" not in node:
            return Leaf(channel, np.empty(0, dtype=np.int64), 0, None, [])
        stamps = np.atleast_1d(np.asarray(node["timestamps"], dtype=np.float64)).ravel()
        n = len(stamps)
        data = np.asarray(node["data"], dtype=np.float64)
        if n == 0 or data.size == 0:
            return Leaf(channel, np.empty(0, dtype=np.int64), 0, None, [])
        # MATLAB k x 1 x N, squeezed by scipy: time is the last axis (or the only one when k = 1).
        if data.size % n or (data.ndim > 1 and data.shape[-1] != n):
            raise self.error(f"channel {channel}: data of shape {data.shape} for {n} timestamps")
        values = data.reshape(-1, n).T if data.ndim > 1 else data.reshape(n, -1)
        stamps_ns = _check_stamps(self.error, channel, stamps, len(values))
        raw = node.get("elements_names", [])
        names = [raw] if isinstance(raw, str) else [str(v) for v in np.asarray(raw, dtype=object).ravel()]
        return Leaf(channel, stamps_ns, values.shape[1], lambda a, b: values[a:b], names)

    def close(self) -> None:
        self.vars = {}


def iter_windows(stamps_ns: np.ndarray, edges_ns: np.ndarray) -> Iterator[tuple[int, int]]:
    """Row ranges of increasing `stamps_ns` between consecutive `edges_ns` (first from -inf, last to
    +inf). Stamps that are not sorted all go to the first window (the consumer re-sorts them)."""
    n = len(stamps_ns)
    if n > 1 and (np.diff(stamps_ns) < 0).any():
        yield 0, n
        for _ in edges_ns:
            yield n, n
        return
    cuts = np.concatenate([[0], np.searchsorted(stamps_ns, edges_ns, side="left"), [n]])
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        yield int(a), int(b)
