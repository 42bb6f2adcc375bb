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

from benchmarks.export_fixture import random_inputs, synthetic_models
from benchmarks.infer_speed import c_api_latency
from pipeline.export import graph
from pipeline.export.check import run, session

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
