"""What an exported graph is: its inputs and outputs (names, order, units, topics), provenance, checks.

The same description goes into each ONNX file's metadata (``metadata_props``: ``ftcal.manifest`` holds the
graph's entry as JSON, plus a few flat keys readable with any ONNX viewer) and into ``manifest.json``
beside the files, which `ftcal calibrate` and a lab's own loader read:

    {"format": "ftcal-onnx", "version": 1, "robot": ..., "input": "inputs", "output": "calibrated",
     "fused": "all", "graphs": {"<group>" | "all": {"files": {"float32": ..., "float64": ...},
     "sha256": {...}, "groups": [...], "sensors": [...], "models": {group: name}, "inputs": [...],
     "outputs": [...], "offsets": {...}, "serials": {sensor: serial | null},
     "training": {group: {...}}, "check": {dtype: {max_abs_diff, samples}}}}}

Each input/output entry: ``index`` (column of the tensor), ``column`` (labelled-table name), ``sensor``,
``topic`` and ``field`` (where a ROS 2 log carries the value), ``unit``. A graph whose models have memory
(the ``play``, ``arx`` and ``win`` families) has a ``state`` entry: its input and output names, shape,
initial value and how to carry it (`pipeline.export.linear`), per column the sensor, raw axis and play width
or filter time constant it belongs to (a windowed network's windows are filters), and with filters the
sample period their rows must have (``period_s``).
``offsets`` describes the graph's second input (`pipeline.export.graph`: subtracted from ``inputs``,
default zeros) and the file a re-zeroing writes beside the manifest (`pipeline.export.offsets`);
``serials`` the sensor boards the calibration belongs to (`pipeline.export.identity`). A graph's ``check``
also holds ``c``: its generated C calibrator (``c/`` beside it, `pipeline.export.csource`) against the same
references. ``wholebodydynamics`` (the fused manifest's): the affine maps written as wholeBodyDynamics'
configuration (`pipeline.export.wbd`) and per headline what they cost beside the deployed model.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from pipeline.export.graph import INPUT, OFFSETS, OPSET, OUTPUT
from pipeline.export.trained import GroupModel

FORMAT, VERSION = "ftcal-onnx", 1
MANIFEST_FILE = "manifest.json"
FUSED = "all"  # the graph of every group
_WRENCH_FIELDS = ("force.x", "force.y", "force.z", "torque.x", "torque.y", "torque.z")
_IMU_FIELDS = tuple(f"linear_acceleration.{a}" for a in "xyz") + tuple(f"angular_velocity.{a}" for a in "xyz")


def _source(topics: Any, sensor: str, k: int) -> tuple[str, str]:
    """(topic, message field) of input k of a sensor's inputs (order of `pipeline.calib.models`)."""
    if k < 6:
        return topics.sensor_topic("ft_wrench", sensor), f"wrench.{_WRENCH_FIELDS[k]}"
    if k == 6:
        return topics.sensor_topic("ft_temperature", sensor), "temperature"
    return topics.sensor_topic("ft_imu", sensor), _IMU_FIELDS[k - 7]


def columns(models: Sequence[GroupModel], topics: Any) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """(inputs, outputs) entries of a graph of `models` side by side (module docstring)."""
    from pipeline.logs import schema as S

    inputs, outputs = [], []
    for m in models:
        for s, sensor in enumerate(m.sensors):
            for k in range(m.n_inputs):
                column = m.input_columns[s * m.n_inputs + k]
                topic, name = _source(topics, sensor, k)
                inputs.append(
                    {"index": len(inputs), "column": column, "sensor": sensor, "topic": topic, "field": name}
                    | {"unit": S.unit(column)}
                )
            for k in range(6):
                column = m.output_columns[s * 6 + k]
                outputs.append(
                    {"index": len(outputs), "column": column, "sensor": sensor}
                    | {"topic": topics.sensor_topic("ft_wrench", sensor) + "_calibrated"}
                    | {"field": f"wrench.{_WRENCH_FIELDS[k]}", "unit": S.unit(column)}
                )
    return inputs, outputs


def training(model: GroupModel, data_sha256: str, mlflow_run: str | None) -> dict[str, Any]:
    """Provenance of one group's model: name, family, training logs and data hash, MLflow run, test errors."""
    info = dict(model.info)
    return {
        "model": model.name,
        "family": model.family,  # `pipeline.calib.registry`: raw, affine, poly, play, arx, nn, win
        "kind": model.kind,  # identity, linear, network or window
        "memory": model.memory,  # a state carried from sample to sample (the graph's ``state``)
        "sensors": list(model.sensors),
        "inputs_per_sensor": model.n_inputs,
        "separable": True,  # each sensor's output depends on its own inputs only (every family here)
        "best_on_validation": info.pop("best_on_validation", None),
        "training_data_sha256": data_sha256,
        "mlflow_run": mlflow_run or info.pop("mlflow_run", None),
        "logs": info.pop("logs", None),
        "samples": info.pop("samples", None),
        "test_metrics": info.pop("test_metrics", None),
        "details": {k: v for k, v in info.items() if k != "mlflow_run"},
    }


def graph_entry(
    models: Sequence[GroupModel],
    topics: Any,
    trainings: Mapping[str, Mapping[str, Any]],
    serials: Mapping[str, str | None] | None = None,
    imu_axes: Mapping[str, Sequence[str] | None] | None = None,
) -> dict[str, Any]:
    """A graph's manifest entry, without files and checks (added once written and checked); `serials`:
    sensor -> the serial of the board its calibration belongs to (None: not recorded); `imu_axes`: sensor ->
    its board's IMU axes in the sensor frame that ingest mapped in training (`ingest.imu_axes`; None: the
    board reads in the sensor frame), which a runtime applies to the board's IMU before the graph."""
    from pipeline.export.offsets import FILE

    inputs, outputs = columns(models, topics)
    sensors = [s for m in models for s in m.sensors]
    return {
        "groups": [m.group for m in models],
        "sensors": sensors,
        "models": {m.group: m.name for m in models},
        "input": INPUT,
        "output": OUTPUT,
        "input_shape": ["N", len(inputs)],
        "output_shape": ["N", len(outputs)],
        "inputs": inputs,
        "outputs": outputs,
        "offsets": {
            "input": OFFSETS,
            "shape": [1, len(inputs)],
            "default": 0.0,
            "file": FILE,
            "meaning": "subtracted from inputs: per sensor its raw wrench's offset change since training "
            "(N, Nm; zero on the other columns), from a re-zeroing (ftcal rezero)",
        },
        "serials": {s: (serials or {}).get(s) for s in sensors},
        "imu_axes": {s: _axes(imu_axes, s) for s in sensors},
        "training": {m.group: dict(trainings[m.group]) for m in models},
    } | _state(models)


def _state(models: Sequence[GroupModel]) -> dict[str, Any]:
    """{"state": ...} of a graph with memory (module docstring), else {}."""
    from pipeline.export.linear import STATE, STATE_OUT, state_layout, state_period

    layout = state_layout(models)
    if not layout:
        return {}
    period = state_period(models)
    state: dict[str, Any] = {
        "input": STATE,
        "output": STATE_OUT,
        "shape": [len(layout)],
        "initial": "NaN (the input's default): each operator and window starts at its sensor's first reading",
        "carry": f"feed {STATE_OUT} of a call as {STATE} of the next; the rows of a call are "
        "consecutive samples of the sensors, in stamp order (1 per call in a control loop); a sensor's "
        "columns may be carried alone (NaN restarts it: after a re-zeroing, a reboot of its board)",
        "columns": layout,
    }
    if period is not None:  # the filters (arx) and windows (win) assume their training logs' rate
        state["period_s"] = period
        state["carry"] += (
            f"; the rows of its filters must be {period:g} s apart (the training logs' sample period)"
        )
    return {"state": state}


def _axes(imu_axes: Mapping[str, Sequence[str] | None] | None, sensor: str) -> list[str] | None:
    axes = (imu_axes or {}).get(sensor)
    return list(axes) if axes else None


def metadata(entry: Mapping[str, Any], robot: str) -> dict[str, str]:
    """ONNX metadata_props of a graph: the whole entry as JSON and flat keys for viewers."""
    runs = {g: t.get("mlflow_run") or "" for g, t in entry["training"].items()}
    hashes = {g: t.get("training_data_sha256") or "" for g, t in entry["training"].items()}
    metrics = {g: t.get("test_metrics") for g, t in entry["training"].items()}
    return {
        "ftcal.format": f"{FORMAT}/{VERSION}",
        "ftcal.robot": robot,
        "ftcal.sensors": ",".join(entry["sensors"]),
        "ftcal.models": json.dumps(entry["models"]),
        "ftcal.inputs": ",".join(f"{c['column']}[{c['unit']}]" for c in entry["inputs"]),
        "ftcal.offsets": f"{OFFSETS}: (1, K) subtracted from {INPUT}, default zeros",
        "ftcal.state": (
            f"{entry['state']['input']} -> {entry['state']['output']}: {entry['state']['shape']}, "
            "default NaN (fresh); carry it from call to call"
            if "state" in entry
            else "none (memoryless)"
        ),
        "ftcal.serials": json.dumps(entry.get("serials") or {}),
        "ftcal.imu_axes": json.dumps(entry.get("imu_axes") or {}),
        "ftcal.outputs": ",".join(f"{c['column']}[{c['unit']}]" for c in entry["outputs"]),
        "ftcal.training_data_sha256": json.dumps(hashes),
        "ftcal.mlflow_runs": json.dumps(runs),
        "ftcal.test_metrics": json.dumps(metrics),
        "ftcal.manifest": json.dumps(entry),
    }


def document(robot: str, graphs: Mapping[str, Any], fused: str | None = FUSED) -> dict[str, Any]:
    """The content of manifest.json (`fused`: the fused graph's name, None for one group's export)."""
    return {
        "format": FORMAT,
        "version": VERSION,
        "robot": robot,
        "opset": OPSET,
        "input": INPUT,
        "output": OUTPUT,
        "fused": fused,
        "graphs": dict(graphs),
    }


def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def data_sha256(paths: Sequence[Path]) -> str:
    """One hash of several files: sha256 over each file's name and sha256, in name order."""
    digest = hashlib.sha256()
    for path in sorted(paths, key=lambda p: p.name):
        digest.update(f"{path.name}\0{sha256_file(path)}\n".encode())
    return digest.hexdigest()


def build_graph(
    name: str,
    models: Sequence[GroupModel],
    topics: Any,
    robot: str,
    trainings: Mapping[str, Mapping[str, Any]],
    serials: Mapping[str, str | None] | None = None,
    imu_axes: Mapping[str, Sequence[str] | None] | None = None,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """(manifest entry, {dtype: ONNX ModelProto}) of a group's graph, or of the fused graph of `models`
    (`name` FUSED: laid out for one sample per call)."""
    from pipeline.export import graph

    entry = graph_entry(models, topics, trainings, serials, imu_axes)
    props = metadata(entry, robot)
    graphs = {
        dtype: graph.build(models, dtype, props, f"ftcal_{name}", per_sample=name == FUSED)
        for dtype in graph.DTYPES
    }
    return entry, graphs


def write_graphs(
    out_dir: Path, name: str, entry: Mapping[str, Any], graphs: Mapping[str, Any]
) -> dict[str, Any]:
    """Write a graph's files ``<name>.<dtype>.onnx`` into `out_dir`; its entry with ``files`` (relative to
    `out_dir`) and their ``sha256``."""
    import onnx

    entry = dict(entry)
    entry["files"] = {dtype: f"{name}.{dtype}.onnx" for dtype in graphs}
    for dtype, model in graphs.items():
        onnx.save_model(model, out_dir / entry["files"][dtype])
    entry["sha256"] = {d: sha256_file(out_dir / f) for d, f in entry["files"].items()}
    return entry


def read_manifest(path: Path) -> dict[str, Any]:
    """manifest.json of an export directory `path`; DataError naming the file if absent or not one."""
    from pipeline.core.errors import DataError
    from pipeline.core.io import read_json

    file = path / MANIFEST_FILE
    doc = read_json(file, "a manifest", f"not found (is {path} an export directory?)")
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or "graphs" not in doc:
        raise DataError(f"{file}: not an ftcal export manifest (format {FORMAT!r})")
    return doc
