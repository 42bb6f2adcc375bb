"""Latency of the fused calibration graph of all 8 FT sensors, one sample at a time (a 1 kHz control loop).

Builds a synthetic export of iCubGenova09's 8 sensors (`benchmarks/export_fixture.py`: six groups of
13-input networks of the thesis's size, a worst case) and measures, on one thread:

1. onnxruntime, fused float32 graph, one call per sample for all 8 sensors: p50 / p99 latency (us), through
   ``InferenceSession.run`` and with I/O binding (buffers bound once, as a control loop would: "bound");
2. the same in float64;
3. torch eager (the project's `GroupNet` modules, float32, ``torch.no_grad``), one call per group:
   p50 / p99 latency of all 8 sensors (us);
4. batch throughput (samples/s) of both on 10,000-sample batches;
5. for scale, the same call of a graph that only copies its input (onnxruntime's per-call floor from
   Python on this machine at this load).

Both agree on the outputs first. Then 1. and 2. for the real export's fused graph (``--export DIR``,
default ``exported/`` when present; ``--export ''`` skips it), on random inputs of plausible size (the
latency of these graphs does not depend on the values). Targets: onnxruntime float32 bound p50 <= 20 us
and p99 <= 50 us. The machine's load average (1 min) is printed before and after (the figures depend on
what else runs; the p99 most). The last line is the ratio torch / onnxruntime of the synthetic export's
p50 latencies (onnxruntime float32 bound).

    python benchmarks/infer_speed.py [--calls 20000] [--rows 1000] [--export exported]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.export_fixture import SCALE, random_inputs, synthetic_export, synthetic_models  # noqa: E402
from pipeline.export.check import run, session  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def latencies(call, inputs: np.ndarray, calls: int, warmup: int = 500) -> np.ndarray:
    """Wall time (us) of each of `calls` calls on one sample (rows of `inputs` in turn)."""
    for k in range(warmup):
        call(inputs[k % len(inputs)])
    out = np.empty(calls)
    for k in range(calls):
        x = inputs[k % len(inputs)]
        t = time.perf_counter_ns()
        call(x)
        out[k] = (time.perf_counter_ns() - t) / 1e3
    return out


def _bound(sess: Any, n_out: int) -> Callable[[np.ndarray], None]:
    """One call as a control loop makes it: input and output buffers bound once (I/O binding), the input
    row overwritten in place before each run."""
    inp, out = sess.get_inputs()[0], sess.get_outputs()[0]
    dtype = np.float32 if inp.type == "tensor(float)" else np.float64
    x_buf, y_buf = np.zeros((1, inp.shape[1]), dtype), np.zeros((1, n_out), dtype)
    binding = sess.io_binding()
    binding.bind_input(inp.name, "cpu", 0, x_buf.dtype, x_buf.shape, x_buf.ctypes.data)
    binding.bind_output(out.name, "cpu", 0, y_buf.dtype, y_buf.shape, y_buf.ctypes.data)

    def call(x: np.ndarray) -> None:
        x_buf[...] = x
        sess.run_with_iobinding(binding)

    return call


def _empty_session(n: int) -> Any:
    """A float32 graph that only copies its input: the per-call floor of onnxruntime from Python."""
    from onnx import TensorProto, helper

    io = [helper.make_tensor_value_info(k, TensorProto.FLOAT, ["N", n]) for k in ("inputs", "calibrated")]
    graph = helper.make_graph(
        [helper.make_node("Identity", ["inputs"], ["calibrated"])], "empty", io[:1], io[1:]
    )
    return session(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), threads=1)


def _onnxruntime(
    sessions: dict[str, Any], pool: np.ndarray, n_out: int, calls: int, label: str = ""
) -> dict[str, np.ndarray]:
    """Single-sample latencies (us) of each session (dtype -> session), through run and bound."""
    out = {}
    for dtype, sess in sessions.items():
        name = sess.get_inputs()[0].name
        rows = pool.astype(dtype).reshape(len(pool), 1, -1)
        out[f"{label}onnxruntime {dtype}"] = latencies(
            lambda x, s=sess, n=name: s.run(None, {n: x}), rows, calls
        )
        out[f"{label}onnxruntime {dtype} bound"] = latencies(_bound(sess, n_out), rows, calls)
    return out


def _real_export(directory: Path, calls: int, rows: int) -> tuple[str, int, dict[str, np.ndarray]]:
    """(description, number of sensors, latencies) of an export directory's fused graph, random inputs."""
    doc = json.loads((directory / "manifest.json").read_text(encoding="utf-8"))
    fused = doc["graphs"][doc["fused"]]
    sessions = {d: session(directory / f, threads=1) for d, f in fused["files"].items()}
    position, inputs = {}, []
    for entry in fused["inputs"]:  # each input's place among its sensor's (the models' order)
        inputs.append(position.setdefault(entry["sensor"], -1) + 1)
        position[entry["sensor"]] += 1
    k = np.array(inputs)
    pool = np.random.default_rng(3).normal(size=(rows, len(k))) * SCALE[k] + np.where(k == 6, 30.0, 0.0)
    models = ", ".join(f"{g} {m}" for g, m in fused["models"].items())
    about = f"{directory}: {len(fused['sensors'])} sensors ({models}), {len(fused['inputs'])} inputs"
    return (
        about,
        len(fused["sensors"]),
        _onnxruntime(sessions, pool, fused["output_shape"][1], calls, "real "),
    )


def _print(results: dict[str, np.ndarray], sensors: int) -> None:
    for name, t in results.items():
        print(
            f"{name:33s} {sensors} sensors per call: p50 {np.percentile(t, 50):6.1f} us  "
            f"p99 {np.percentile(t, 99):6.1f} us"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--calls", type=int, default=20000, help="single-sample calls measured per runtime")
    ap.add_argument(
        "--rows",
        type=int,
        default=1000,
        help="distinct input rows the single-sample calls cycle through (one row repeated measures ~5 us "
        "less than varying rows on this machine; 50 or 1000 rows measure alike)",
    )
    ap.add_argument(
        "--export",
        default=str(ROOT / "exported") if (ROOT / "exported" / "manifest.json").is_file() else "",
        help="an export directory whose fused graph is measured too (default exported/ if present; '' none)",
    )
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores at the start")
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        models, nets = synthetic_models(Path(tmp) / "models")
        doc = synthetic_export(Path(tmp) / "export", models)
        fused = doc["graphs"][doc["fused"]]
        sessions = {
            d: session(Path(tmp) / "export" / fused["files"][d], threads=1) for d in ("float32", "float64")
        }
    n_in = fused["input_shape"][1]
    pool = random_inputs(args.rows)
    assert pool.shape[1] == n_in
    widths = [m.n_inputs * len(m.sensors) for m in models]
    bounds = np.cumsum([0, *widths])

    def torch_all(x: torch.Tensor) -> list[torch.Tensor]:
        with torch.no_grad():
            return [net(x[:, bounds[g] : bounds[g + 1]]) for g, net in enumerate(nets)]

    batch = random_inputs(10000, seed=2)
    y_ort = run(sessions["float32"], batch)
    y_torch = torch.cat(torch_all(torch.tensor(batch, dtype=torch.float32)), dim=1).numpy()
    print(f"agreement onnxruntime float32 vs torch: max |diff| {np.abs(y_ort - y_torch).max():.2g} N/Nm")

    results = _onnxruntime(sessions, pool, fused["output_shape"][1], args.calls)
    rows32 = pool.astype(np.float32).reshape(len(pool), 1, -1)
    results["onnxruntime empty graph bound"] = latencies(
        _bound(_empty_session(n_in), n_in), rows32, args.calls
    )
    rows_t = [torch.tensor(r, dtype=torch.float32).reshape(1, -1) for r in pool]
    results["torch eager float32"] = latencies(torch_all, rows_t, args.calls)

    print(f"synthetic export (six groups, 8 networks 13-100-100-6); 1 thread; {args.calls} calls per line")
    _print(results, 8)
    if args.export:
        about, n_sensors, real = _real_export(Path(args.export), args.calls, args.rows)
        print(f"real export {about}")
        _print(real, n_sensors)
    for name, call in (
        ("onnxruntime float32", lambda: run(sessions["float32"], batch)),
        ("torch eager float32", lambda: torch_all(torch.tensor(batch, dtype=torch.float32))),
    ):
        call()
        t = time.perf_counter()
        for _ in range(5):
            call()
        print(
            f"{name:33s} batch of {len(batch)}: "
            f"{5 * len(batch) / (time.perf_counter() - t) / 1e6:.2f} M samples/s"
        )
    print(f"load average {os.getloadavg()[0]:.2f} at the end")
    ort_p50 = np.percentile(results["onnxruntime float32 bound"], 50)
    torch_p50 = np.percentile(results["torch eager float32"], 50)
    print(f"ratio torch / onnxruntime (p50 latency, 8 sensors): {torch_p50 / ort_p50:.1f}")


if __name__ == "__main__":
    main()
