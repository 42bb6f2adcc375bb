"""The latency benchmark's C API harness (`benchmarks/ort_latency.c`): it calls onnxruntime through fixed
slots of the C API's function table, so it must build, load the wheel's library and compute what the Python
API computes on the same graph and inputs; a bad model is a one-line reason, not a crash."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import onnx
import onnxruntime
import pytest

from benchmarks.export_fixture import random_inputs, synthetic_linear, synthetic_models
from benchmarks.infer_speed import c_api_latency
from pipeline.export import graph
from pipeline.export.check import run, run_state, session

pytestmark = pytest.mark.skipif(
    shutil.which("cc") is None and shutil.which("gcc") is None, reason="no C compiler"
)


def test_c_api_harness_computes_what_python_does(tmp_path: Path) -> None:
    models, _ = synthetic_models(tmp_path / "models", hidden=16)
    path = tmp_path / "all.float32.onnx"
    onnx.save_model(graph.build(models, "float32", {}, "fused", per_sample=True), path)
    pool = random_inputs(7, seed=4).astype(np.float32)
    result = c_api_latency(path, pool, 48, calls=13, work=tmp_path, warmup=3)
    assert isinstance(result, dict), result
    first = run(session(path), pool)[:, 0].astype(np.float64)
    expected = sum(first[k % len(pool)] for k in range(3 + 13))  # the harness's calls, warm-up included
    assert result["checksum"] == pytest.approx(expected, rel=1e-6, abs=1e-9)
    assert result["version"] == onnxruntime.__version__
    assert 0 < result["p50_us"] <= result["p99_us"]


def test_c_api_harness_reports_a_bad_model_in_one_line(tmp_path: Path) -> None:
    path = tmp_path / "broken.onnx"
    path.write_bytes(b"not an onnx model")
    result = c_api_latency(path, np.zeros((2, 104), np.float32), 48, calls=5, work=tmp_path)
    assert isinstance(result, str)
    assert "\n" not in result and "CreateSession" in result


def test_c_api_harness_carries_a_graph_state(tmp_path: Path) -> None:
    """The play models' fused graph (memory): the harness feeds each call's ``state_out`` back as the next
    call's ``state``, as the Python API's loop below does; a loop that does not would sum otherwise."""
    models = synthetic_linear(tmp_path / "models", "play")
    path = tmp_path / "play.float32.onnx"
    onnx.save_model(graph.build(models, "float32", {}, "fused", per_sample=True), path)
    pool = random_inputs(7, n_inputs=7, seed=4).astype(np.float32) * 3
    size = {i.name: i.shape[0] for i in session(path).get_overridable_initializers()}["state"]
    result = c_api_latency(path, pool, 48, calls=13, work=tmp_path, warmup=3, state=size)
    assert isinstance(result, dict), result
    carried, fresh, state = 0.0, 0.0, None
    for k in range(3 + 13):
        y, state = run_state(session(path), pool[k % len(pool)][None], state=state)
        carried += float(y[0, 0])
        fresh += float(run(session(path), pool[k % len(pool)][None])[0, 0])
    assert result["checksum"] == pytest.approx(carried, rel=1e-6, abs=1e-6)
    assert abs(carried - fresh) > 1e-3
