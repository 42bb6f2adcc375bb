"""Latency of the fused calibration graph of all 8 FT sensors, one sample at a time (a 1 kHz control loop).

Builds a synthetic export of iCubGenova09's 8 sensors (`benchmarks/export_fixture.py`: six groups of
13-input networks of the thesis's size, two hidden layers of 100; ``--hidden`` changes it: the training
search may pick 64, 100 or 128) and measures, on one thread:

1. onnxruntime, fused float32 graph, one call per sample for all 8 sensors, p50 / p99 latency (us):
   through onnxruntime's C API, as a robot's C/C++ loop calls it (`benchmarks/ort_latency.c`, built here
   with the system's C compiler against the wheel's libonnxruntime; input and output tensors created once
   over the loop's buffers); from Python through ``InferenceSession.run`` and with I/O binding (buffers
   bound once: "bound");
2. the same from Python in float64;
3. torch eager (the project's `GroupNet` modules, float32, ``torch.no_grad``), one call per group:
   p50 / p99 latency of all 8 sensors (us);
4. batch throughput (samples/s) on 10,000-sample batches: torch, the fused graph (laid out for one
   sample per call) and the groups' graphs (laid out for batches, as `ftcal calibrate` runs them);
5. for scale, the same call of a graph that only copies its input (onnxruntime's per-call floor, from C
   and from Python, on this machine at this load).
6. the linear families fused for the 8 sensors through the C API: affine (memoryless), play and arx (with
   memory: their state carried from call to call), and the windowed network (`win`: the play model, its
   filters and a network per sensor, of the params' size).
7. the generated C calibrator of each of those exports (`pipeline.export.csource`: plain C99, the
   export's ``c/ftcal_calibrator.c``), built here with the system's C compiler and called one sample at a
   time on the same rows (`benchmarks/c_latency.c`), and its p50 against onnxruntime's C API in the same run
   (target: at least 5x below).

Both agree on the outputs first. Then 1. and 2. for the real export's fused graph (``--export DIR``,
default ``exported/`` when present; ``--export ''`` skips it), on random inputs of plausible size (the
latency of these graphs does not depend on the values). Targets: onnxruntime float32 p50 <= 20 us and p99
<= 50 us; each case's verdict is printed. Calls are back to back (caches warm; a loop that does other work
between calls may see more). The machine's load average (1 min) is printed before and after (the figures
depend on what else runs; the p99 most). The last line is the ratio torch / onnxruntime of the synthetic
export's p50 latencies, both called from Python (onnxruntime float32 bound).

    python benchmarks/infer_speed.py [--calls 20000] [--rows 1000] [--hidden 100] [--export exported]
    python benchmarks/infer_speed.py --quick    # 100 calls, batches of 500, no export: for the test suite
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
import onnx
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks import QUICK  # noqa: E402
from benchmarks.export_fixture import (  # noqa: E402
    SCALE,
    random_inputs,
    synthetic_export,
    synthetic_linear,
    synthetic_models,
    synthetic_window,
)
from pipeline.export.check import run, session  # noqa: E402
from pipeline.export.linear import STATE, STATE_OUT  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TARGET_P50, TARGET_P99 = 20.0, 50.0  # us, one sample of all sensors on 1 thread


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
    row overwritten in place before each run; a graph's state carried (its output copied to its input)."""
    inp, out = sess.get_inputs()[0], sess.get_outputs()[0]
    dtype = np.float32 if inp.type == "tensor(float)" else np.float64
    x_buf, y_buf = np.zeros((1, inp.shape[1]), dtype), np.zeros((1, n_out), dtype)
    binding = sess.io_binding()
    binding.bind_input(inp.name, "cpu", 0, x_buf.dtype, x_buf.shape, x_buf.ctypes.data)
    binding.bind_output(out.name, "cpu", 0, y_buf.dtype, y_buf.shape, y_buf.ctypes.data)
    state = next((i for i in sess.get_overridable_initializers() if i.name == STATE), None)
    if state is not None:
        s_in, s_out = np.full(state.shape, np.nan, dtype), np.full(state.shape, np.nan, dtype)
        binding.bind_input(STATE, "cpu", 0, dtype, s_in.shape, s_in.ctypes.data)
        binding.bind_output(STATE_OUT, "cpu", 0, dtype, s_out.shape, s_out.ctypes.data)

    def call(x: np.ndarray) -> None:
        x_buf[...] = x
        sess.run_with_iobinding(binding)
        if state is not None:
            s_in[...] = s_out

    return call


def _empty_model(n: int) -> Any:
    """A float32 graph that only copies its input: the per-call floor of onnxruntime."""
    from onnx import TensorProto, helper

    io = [helper.make_tensor_value_info(k, TensorProto.FLOAT, ["N", n]) for k in ("inputs", "calibrated")]
    graph = helper.make_graph(
        [helper.make_node("Identity", ["inputs"], ["calibrated"])], "empty", io[:1], io[1:]
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


def c_api_latency(
    model: Path, pool: np.ndarray, n_out: int, calls: int, work: Path, warmup: int = 500, state: int = 0
) -> dict | str:
    """{"p50_us", "p99_us", "version", "checksum"} of `model` (input ``inputs``, output ``calibrated``)
    called one row of `pool` at a time (cycled, `warmup` calls first) through onnxruntime's C API on 1
    thread (`benchmarks/ort_latency.c`, built into `work` with the system's C compiler against the
    wheel's libonnxruntime), as a robot's C/C++ loop calls it, carrying a graph's `state` values (``state``
    -> ``state_out``) from call to call; or why it could not run (one line)."""
    import shutil
    import subprocess

    import onnxruntime

    compiler = shutil.which("cc") or shutil.which("gcc")
    libraries = sorted((Path(onnxruntime.__file__).parent / "capi").glob("libonnxruntime.so*"))
    if compiler is None or not libraries:
        return "needs a C compiler (cc) and the wheel's capi/libonnxruntime.so"
    exe, rows = work / "ort_latency", work / "rows.f32"
    if not exe.exists():
        build = [compiler, "-O2", "-o", str(exe), str(ROOT / "benchmarks" / "ort_latency.c"), "-ldl"]
        done = subprocess.run(build, capture_output=True, text=True)
        if done.returncode:
            return f"cannot build benchmarks/ort_latency.c: {' '.join(done.stderr.split())[:300]}"
    np.ascontiguousarray(pool, dtype=np.float32).tofile(rows)
    args = [str(libraries[-1]), str(model), "inputs", "calibrated", pool.shape[1], n_out, str(rows)]
    carried = [STATE, STATE_OUT, state] if state else []
    done = subprocess.run(
        [str(exe), *map(str, (*args, len(pool), calls, warmup, *carried))], capture_output=True, text=True
    )
    if done.returncode:
        return (done.stderr.strip().splitlines() or [f"exit status {done.returncode}"])[-1]
    return json.loads(done.stdout)


def c_calibrator_latency(
    directory: Path, pool: np.ndarray, calls: int, work: Path, warmup: int = 500
) -> dict | str:
    """{"p50_us", "p99_us", "checksum"} of the generated C calibrator in `directory` (``c/`` of an
    export) called one row of `pool` at a time, as `c_api_latency` calls onnxruntime on the same rows
    (`benchmarks/c_latency.c`, built with the system's C compiler against the calibrator's source); or why it
    could not run (one line)."""
    import subprocess

    from pipeline.export.cbuild import compiler

    cc = compiler()
    if cc is None or not (directory / "ftcal_calibrator.c").is_file():
        return "needs a C compiler (cc) and the export's c/ftcal_calibrator.c"
    exe, rows = work / f"c_latency_{abs(hash(str(directory)))}", work / "c_rows.f32"
    build = [cc, "-O3", "-std=c99", "-I", str(directory), str(ROOT / "benchmarks" / "c_latency.c")]
    done = subprocess.run(
        [*build, str(directory / "ftcal_calibrator.c"), "-o", str(exe), "-lm"], capture_output=True, text=True
    )
    if done.returncode:
        return f"cannot build benchmarks/c_latency.c: {' '.join(done.stderr.split())[:300]}"
    np.ascontiguousarray(pool, dtype=np.float32).tofile(rows)
    done = subprocess.run(
        [str(exe), str(rows), str(len(pool)), str(calls), str(warmup)], capture_output=True, text=True
    )
    if done.returncode:
        return (done.stderr.strip().splitlines() or [f"exit status {done.returncode}"])[-1]
    return json.loads(done.stdout)


def _ratio(name: str, ort: Any, c: Any) -> str:
    """One line: onnxruntime's C API p50 over the C calibrator's, on the same rows in the same run."""
    if not isinstance(ort, dict) or not isinstance(c, dict):
        return f"{name}: ratio not measured ({ort if isinstance(ort, str) else c})"
    return (
        f"{name}: p50 onnxruntime C API {ort['p50_us']:.2f} us / C calibrator {c['p50_us']:.2f} us = "
        f"{ort['p50_us'] / c['p50_us']:.1f}x (target >= {C_TARGET_RATIO:.0f}x)"
    )


C_TARGET_RATIO = 5.0  # the generated C calibrator's p50 at least this many times below onnxruntime's C API


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


def _real_export(
    directory: Path, calls: int, rows: int, work: Path
) -> tuple[str, int, dict[str, np.ndarray | dict | str]]:
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
    n_out = fused["output_shape"][1]
    state = int(fused["state"]["shape"][0]) if "state" in fused else 0
    about += f", {state} state values carried" if state else ""
    results: dict[str, Any] = {
        "real onnxruntime C API float32": c_api_latency(
            directory / fused["files"]["float32"], pool, n_out, calls, work, state=state
        ),
        "real C calibrator": c_calibrator_latency(directory / "c", pool, calls, work),
    }
    results.update(_onnxruntime(sessions, pool, n_out, calls, "real "))
    return about, len(fused["sensors"]), results


def _p50_p99(result: np.ndarray | dict) -> tuple[float, float]:
    """p50, p99 (us) of an array of latencies or of a C API result."""
    if isinstance(result, dict):
        return result["p50_us"], result["p99_us"]
    return tuple(np.percentile(result, [50, 99]))


def _print(results: dict[str, Any], sensors: int) -> None:
    """One line per runtime: p50 / p99 (us) of arrays of latencies or of C API results (or why not)."""
    for name, t in results.items():
        if isinstance(t, str):
            print(f"{name:33s} not measured: {t}")
            continue
        p50, p99 = _p50_p99(t)
        print(f"{name:33s} {sensors} sensors per call: p50 {p50:7.2f} us  p99 {p99:7.2f} us")


def _verdict(name: str, result: Any) -> str:
    if isinstance(result, str):
        return f"{name}: not measured"
    p50, p99 = _p50_p99(result)
    met = "met" if p50 <= TARGET_P50 and p99 <= TARGET_P99 else "NOT met"
    return f"{name}: p50 {p50:.1f} us, p99 {p99:.1f} us: {met}"


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
    ap.add_argument("--hidden", type=int, default=100, help="hidden units of the synthetic networks")
    ap.add_argument("--batch", type=int, default=10000, help="samples per batch of the throughput lines")
    ap.add_argument(
        "--quick", action="store_true", help=f"{QUICK}: 100 calls of 20 rows, batches of 500, no --export"
    )
    args = ap.parse_args()
    if args.quick:
        args.calls, args.rows, args.batch = 100, 20, 500
        args.export = args.export if "--export" in sys.argv else ""
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores at the start")
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        _measure(args, Path(tmp))


def _measure(args: argparse.Namespace, work: Path) -> None:
    models, nets = synthetic_models(work / "models", hidden=args.hidden)
    doc = synthetic_export(work / "export", models)
    fused = doc["graphs"][doc["fused"]]
    files = {d: work / "export" / fused["files"][d] for d in ("float32", "float64")}
    sessions = {d: session(f, threads=1) for d, f in files.items()}
    n_in, n_out = fused["input_shape"][1], fused["output_shape"][1]
    pool = random_inputs(args.rows)
    assert pool.shape[1] == n_in
    widths = [m.n_inputs * len(m.sensors) for m in models]
    bounds = np.cumsum([0, *widths])

    def torch_all(x: torch.Tensor) -> list[torch.Tensor]:
        with torch.no_grad():
            return [net(x[:, bounds[g] : bounds[g + 1]]) for g, net in enumerate(nets)]

    batch = random_inputs(args.batch, seed=2)
    y_ort = run(sessions["float32"], batch)
    y_torch = torch.cat(torch_all(torch.tensor(batch, dtype=torch.float32)), dim=1).numpy()
    print(f"agreement onnxruntime float32 vs torch: max |diff| {np.abs(y_ort - y_torch).max():.2g} N/Nm")

    onnx.save_model(_empty_model(n_in), work / "empty.onnx")
    results: dict[str, Any] = {
        "onnxruntime C API float32": c_api_latency(files["float32"], pool, n_out, args.calls, work),
        "C calibrator": c_calibrator_latency(work / "export" / "c", pool, args.calls, work),
        "onnxruntime C API empty graph": c_api_latency(work / "empty.onnx", pool, n_in, args.calls, work),
    }
    results.update(_onnxruntime(sessions, pool, n_out, args.calls))
    rows32 = pool.astype(np.float32).reshape(len(pool), 1, -1)
    results["onnxruntime empty graph bound"] = latencies(
        _bound(session(work / "empty.onnx", threads=1), n_in), rows32, args.calls
    )
    rows_t = [torch.tensor(r, dtype=torch.float32).reshape(1, -1) for r in pool]
    results["torch eager float32"] = latencies(torch_all, rows_t, args.calls)

    for name in ("affine", "play", "arx", "win"):  # the linear families and the windowed network, in one run
        made = synthetic_window(work / "win_models") if name == "win" else None
        linear_doc = synthetic_export(work / name, made or synthetic_linear(work / f"{name}_models", name))
        linear = linear_doc["graphs"][linear_doc["fused"]]
        state = int(linear["state"]["shape"][0]) if "state" in linear else 0
        file, pool7 = work / name / linear["files"]["float32"], random_inputs(args.rows, n_inputs=7)
        results[f"{name} 8 sensors C API float32"] = c_api_latency(
            file, pool7, n_out, args.calls, work, state=state
        )
        results[f"{name} 8 sensors C calibrator"] = c_calibrator_latency(
            work / name / "c", pool7, args.calls, work
        )
    shape = f"13-{args.hidden}-{args.hidden}-6"
    print(f"synthetic export (six groups, 8 networks {shape}); 1 thread; {args.calls} calls per line")
    _print(results, 8)
    verdicts = [_verdict("synthetic, C API", results["onnxruntime C API float32"])]
    verdicts.append(_verdict("synthetic, Python", results["onnxruntime float32 bound"]))
    for k in ("affine", "play", "arx", "win"):
        verdicts.append(_verdict(f"synthetic {k}, C API", results[f"{k} 8 sensors C API float32"]))
    ratios = [_ratio("synthetic networks", results["onnxruntime C API float32"], results["C calibrator"])]
    for k in ("affine", "play", "arx", "win"):
        ratios.append(
            _ratio(
                f"synthetic {k}",
                results[f"{k} 8 sensors C API float32"],
                results[f"{k} 8 sensors C calibrator"],
            )
        )
    if args.export:
        about, n_sensors, real = _real_export(Path(args.export), args.calls, args.rows, work)
        print(f"real export {about}")
        _print(real, n_sensors)
        verdicts.append(_verdict("real export, C API", real["real onnxruntime C API float32"]))
        verdicts.append(_verdict("real export, Python", real["real onnxruntime float32 bound"]))
        ratios.append(
            _ratio("real export", real["real onnxruntime C API float32"], real["real C calibrator"])
        )
    groups = [session(work / "export" / doc["graphs"][m.group]["files"]["float32"]) for m in models]
    for name, call in (
        ("onnxruntime float32 fused graph", lambda: run(sessions["float32"], batch)),
        (
            "onnxruntime float32 groups' graphs",
            lambda: [run(g, batch[:, bounds[k] : bounds[k + 1]]) for k, g in enumerate(groups)],
        ),
        ("torch eager float32", lambda: torch_all(torch.tensor(batch, dtype=torch.float32))),
    ):
        call()
        t = time.perf_counter()
        for _ in range(5):
            call()
        print(
            f"{name:35s} batch of {len(batch)}: "
            f"{5 * len(batch) / (time.perf_counter() - t) / 1e6:.2f} M samples/s"
        )
    print(f"load average {os.getloadavg()[0]:.2f} at the end")
    print(f"target p50 <= {TARGET_P50:.0f} us, p99 <= {TARGET_P99:.0f} us (onnxruntime float32, 1 thread):")
    for line in verdicts:
        print(f"  {line}")
    print("the generated C calibrator against onnxruntime's C API, the same rows, one thread:")
    for line in ratios:
        print(f"  {line}")
    ort_p50 = np.percentile(results["onnxruntime float32 bound"], 50)
    torch_p50 = np.percentile(results["torch eager float32"], 50)
    print(f"ratio torch / onnxruntime (p50 latency, 8 sensors, both from Python): {torch_p50 / ort_p50:.1f}")


if __name__ == "__main__":
    main()
