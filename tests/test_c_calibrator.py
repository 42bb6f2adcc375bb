"""The generated C calibrator (`pipeline.export.csource`) against the ONNX float32 graph of the same models.

Every family ftcal deploys (raw, affine, polynomials, play, arx, the networks, the windowed network), of a
single sensor and of a foot pair: compiled with the system's cc as strict C99 (every warning an error,
libm only), run on every test sample of the group (each test log from a fresh state) in one call, in
calls of 97 rows carrying the state, and after one sensor's state is reset by ``ftcal_reset_sensor``
against the graph with that sensor's state columns set to NaN: within the export's float32 tolerance
(8 float32 steps at each sensor's largest output). Skipped with the reason where there is no compiler.
"""

from __future__ import annotations

import ctypes
import subprocess
from pathlib import Path

import numpy as np
import pytest

from pipeline.export import cbuild, csource, graph
from pipeline.export.check import load_samples, max_ulps, run_state, session
from pipeline.export.linear import state_layout
from pipeline.export.trained import read_group
from tests.factories.labelled import LEG, PAIR

FAMILIES = ["raw", "affine", "poly1", "poly2", "play", "arx", "nn7", "nn13", "win"]
TOLERANCE_ULPS = 8  # params.yaml export.tolerance_float32_ulps

pytestmark = pytest.mark.skipif(
    cbuild.compiler() is None, reason="no C compiler (cc) to build the calibrator"
)


def _built(model, tmp_path: Path) -> tuple[cbuild.CSession, Path]:
    entry = {"sensors": list(model.sensors), "serials": {model.sensors[0]: "SN-0001"}, "inputs": []}
    for name, text in csource.generate([model], entry).items():
        (tmp_path / name).write_text(text)
    strict = [cbuild.compiler(), "-std=c99", "-pedantic", "-Wall", "-Wextra", "-Werror", "-c"]
    done = subprocess.run(
        [*strict, str(tmp_path / csource.SOURCE), "-o", str(tmp_path / "x.o")], capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    n_state = sum(getattr(p, "state_size", 0) for p in model.parts)
    library = cbuild.compile_calibrator(tmp_path, tmp_path)
    return cbuild.CSession(library, len(model.input_columns), 6 * len(model.sensors), n_state), library


@pytest.mark.parametrize("group", [LEG, PAIR])
@pytest.mark.parametrize("name", FAMILIES)
def test_the_c_calibrator_computes_the_float32_graph(
    trained_models: dict, tmp_path: Path, group: str, name: str
) -> None:
    model = read_group(trained_models["models"] / group, name, group)
    samples = load_samples(trained_models["models"] / group, model, trained_models["labelled"])
    onnx = session(graph.build([model], "float32", {}, "check", per_sample=True))
    c, library = _built(model, tmp_path)
    bounds = [0] if samples.bounds is None else list(samples.bounds)
    edges = [*bounds, len(samples.x)]
    for a, b in zip(edges[:-1], edges[1:], strict=True):  # each test log from a fresh state
        x = samples.x[a:b]
        expected, state = run_state(onnx, x)
        got, c_state = run_state(c, x)
        assert max_ulps(got, expected) <= TOLERANCE_ULPS, (name, max_ulps(got, expected))
        if state is None:
            continue
        np.testing.assert_allclose(c_state, state, rtol=1e-6, atol=1e-5)
        carried, s = [], None  # calls of 97 rows, the state carried from call to call
        for k in range(0, len(x), 97):
            y, s = run_state(c, x[k : k + 97], None, s)
            carried.append(y)
        assert max_ulps(np.concatenate(carried), expected) <= TOLERANCE_ULPS
        # one sensor reset half-way: ftcal_reset_sensor against the graph with its state columns NaN
        half = len(x) // 2
        _, s_half = run_state(onnx, x[:half])
        columns = [e["index"] for e in state_layout([model]) if e["sensor"] == model.sensors[-1]]
        reset = np.array(s_half, dtype=np.float64)
        reset[columns] = np.nan
        expected_after, _ = run_state(onnx, x[half:], None, reset)
        lib = ctypes.CDLL(str(library))
        buffer = (ctypes.c_double * len(s_half))(*np.asarray(s_half, dtype=np.float64))
        assert lib.ftcal_reset_sensor(ctypes.byref(buffer), len(model.sensors) - 1) == 0
        assert lib.ftcal_reset_sensor(ctypes.byref(buffer), len(model.sensors)) == -1  # no such sensor
        np.testing.assert_array_equal(np.isnan(np.array(buffer[:])), np.isnan(reset))
        after, _ = run_state(c, x[half:], None, np.array(buffer[:]))
        assert max_ulps(after, expected_after) <= TOLERANCE_ULPS


def test_the_calibrator_names_its_sensors_and_serials(trained_models: dict, tmp_path: Path) -> None:
    model = read_group(trained_models["models"] / PAIR, "affine", PAIR)
    _, library = _built(model, tmp_path)
    lib = ctypes.CDLL(str(library))
    names = (ctypes.c_char_p * 2).in_dll(lib, "ftcal_sensors")
    serials = (ctypes.c_char_p * 2).in_dll(lib, "ftcal_serials")
    assert [n.decode() for n in names] == list(model.sensors)
    assert [s.decode() for s in serials] == ["SN-0001", ""]
    lib.ftcal_sensor_index.argtypes = [ctypes.c_char_p]
    assert lib.ftcal_sensor_index(model.sensors[1].encode()) == 1 and lib.ftcal_sensor_index(b"nope") == -1
