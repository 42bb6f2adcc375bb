"""The generated C calibrator (`pipeline.export.csource`) compiled with the system's C compiler and run.

`compile_calibrator(dir, work)` builds ``dir``'s ``ftcal_calibrator.c`` into a shared library in ``work``
with ``cc`` (C99, -O3, no fast-math, libm); `load_calibrator` compiles and loads it, leaving no file
behind; `CSession` runs it behind the few methods of an onnxruntime session
that ftcal calls (`pipeline.export.check.run_state`): ``get_inputs``, ``get_outputs`` and ``run`` with the
``inputs``, ``offsets`` and ``state`` feeds of a float32 graph, so that the checks, `ftcal calibrate` and
the deployment tests judge the very code a robot runs. `compiler()` is the compiler found (None: none).
`using("c")` makes every `pipeline.export.runtime.Deployment.load` inside run the C calibrators
(`c_runtime`, compiled once per process), the CLI's ``--runtime c``.
"""

from __future__ import annotations

import ctypes
import os
import shutil
import subprocess
import tempfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.cliargs import RUNTIMES
from pipeline.core.errors import DataError
from pipeline.export.csource import HEADER, SOURCE

FLAGS = ("-std=c99", "-O3", "-shared", "-fPIC")  # no fast-math: IEEE arithmetic, as written


def compiler() -> str | None:
    """The C compiler: $CC, else cc, else gcc (None: none on PATH)."""
    for name in (os.environ.get("CC"), "cc", "gcc"):
        if name and shutil.which(name):
            return name
    return None


@dataclass(frozen=True)
class _Arg:
    name: str
    type: str


class CSession:
    """A compiled calibrator with the interface of an onnxruntime session of a float32 graph."""

    def __init__(self, library: Path | ctypes.CDLL, n_inputs: int, n_outputs: int, n_state: int) -> None:
        self._lib = library if isinstance(library, ctypes.CDLL) else ctypes.CDLL(str(library))
        self.n_inputs, self.n_outputs, self.n_state = n_inputs, n_outputs, n_state
        self._state = (ctypes.c_double * max(n_state, 1))()
        f = self._lib.ftcal_calibrate_rows
        f.restype = None
        f.argtypes = [ctypes.c_void_p, ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]

    def get_inputs(self) -> list[_Arg]:
        return [_Arg("inputs", "tensor(float)")]

    def get_outputs(self) -> list[_Arg]:
        names = ["calibrated", "state_out"] if self.n_state else ["calibrated"]
        return [_Arg(n, "tensor(float)") for n in names]

    def run(self, _names: Any, feed: dict[str, np.ndarray]) -> list[np.ndarray]:
        """[outputs (N, 6 S) float32, the state after the last row (M,) float32 if any] of the rows of
        ``feed["inputs"]`` from ``feed["state"]`` (default NaN: a fresh start)."""
        x = np.ascontiguousarray(feed["inputs"], dtype=np.float32)
        if x.ndim != 2 or x.shape[1] != self.n_inputs:
            raise DataError(f"the C calibrator takes rows of {self.n_inputs} inputs, got shape {x.shape}")
        offsets = feed.get("offsets")
        off = None if offsets is None else np.ascontiguousarray(np.reshape(offsets, -1), dtype=np.float32)
        state = np.full(max(self.n_state, 1), np.nan)
        if feed.get("state") is not None:
            state[: self.n_state] = np.reshape(feed["state"], -1)
        self._state[:] = state.tolist()
        out = np.empty((len(x), self.n_outputs), dtype=np.float32)
        self._lib.ftcal_calibrate_rows(
            ctypes.byref(self._state),
            len(x),
            x.ctypes.data,
            None if off is None else off.ctypes.data,
            out.ctypes.data,
        )
        last = np.array(self._state[: self.n_state], dtype=np.float32)
        return [out, last] if self.n_state else [out]


def compile_calibrator(directory: Path, work: Path) -> Path:
    """The shared library built from `directory`'s generated calibrator into `work`. DataError naming the
    file if there is no compiler or it fails."""
    cc = compiler()
    if cc is None:
        raise DataError(f"{directory / SOURCE}: no C compiler (cc, gcc or $CC) to build the C calibrator")
    for name in (HEADER, SOURCE):
        if not (directory / name).is_file():
            raise DataError(f"{directory / name}: not found (re-export with `ftcal export`)")
    library = Path(work) / "libftcal_calibrator.so"
    cmd = [cc, *FLAGS, "-I", str(directory), str(directory / SOURCE), "-o", str(library), "-lm"]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        first = (done.stderr.strip().splitlines() or ["?"])[0]
        raise DataError(f"{directory / SOURCE}: {cc} failed: {first}")
    return library


def load_calibrator(directory: Path) -> ctypes.CDLL:
    """`directory`'s calibrator compiled and loaded; its library file is removed once loaded."""
    with tempfile.TemporaryDirectory(prefix="ftcal-c-") as work:
        return ctypes.CDLL(str(compile_calibrator(directory, Path(work))))


def c_session(directory: Path, n_inputs: int, n_outputs: int, n_state: int) -> CSession:
    """`CSession` of `directory`'s calibrator, compiled afresh."""
    return CSession(load_calibrator(directory), n_inputs, n_outputs, n_state)


_RUNTIME = ["onnxruntime"]
_BUILT: dict[str, ctypes.CDLL] = {}  # the C calibrators loaded in this process, by their source's sha256


def default_runtime() -> str:
    """The runtime `Deployment.load` uses unless told (`using`)."""
    return _RUNTIME[0]


@contextmanager
def using(runtime: str) -> Iterator[None]:
    """Every `Deployment.load` inside runs the export with `runtime` (one of RUNTIMES): the CLI's
    ``--runtime``, for `ftcal calibrate` and the deployment tests alike."""
    if runtime not in RUNTIMES:
        raise DataError(f"--runtime {runtime}: one of {', '.join(RUNTIMES)}")
    previous, _RUNTIME[0] = _RUNTIME[0], runtime
    try:
        yield
    finally:
        _RUNTIME[0] = previous


def c_runtime(directory: Path, entry: Mapping[str, Any]) -> Any:
    """The C calibrator of the graph in `directory` (its ``c`` folder), compiled once per process."""
    from pipeline.export.manifest import sha256_file

    folder = directory / "c"
    if not (folder / SOURCE).is_file():
        raise DataError(f"{folder / SOURCE}: not found (an export without its C calibrator: re-export)")
    key = sha256_file(folder / SOURCE)
    if key not in _BUILT:
        _BUILT[key] = load_calibrator(folder)
    n_state = int(entry["state"]["shape"][0]) if "state" in entry else 0
    return CSession(_BUILT[key], len(entry["inputs"]), len(entry["outputs"]), n_state)
