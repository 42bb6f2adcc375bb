"""The trained models of a group applied to a deployment log, and the calibrated wrenches of a log.

`group_models` reads every model a group trained (networks and baselines) as a predictor on a table's
inputs: Test A measures each one's output noise. `calibrated_wrenches` is the one place where a log gets
the deployed calibration: the exported graphs (the export stage's manifest: each group's recommended
model) run on the log's raw messages as `ftcal calibrate` runs them, with causal inputs (the latest
temperature and IMU message stamped at or before each wrench), then brought onto the table's joint-state
stamps by linear interpolation between neighbouring calibrated messages, as ingest does for raw.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.core.errors import DataError
from pipeline.export.offsets import Offsets
from pipeline.logs import schema as S

Predictor = Callable[[pd.DataFrame], dict[str, np.ndarray]]  # table -> sensor -> (N, 6) N / Nm


def _inputs(table: pd.DataFrame, sensors: list[str], n: int) -> np.ndarray:
    """(N, S, n) model inputs: raw wrench, temperature[, accelerometer, gyroscope]."""
    from pipeline.calib.data import input_cols

    return np.stack([table[input_cols(s, n)].to_numpy(np.float64) for s in sensors], axis=1)


def group_models(model_dir: Path) -> tuple[list[str], dict[str, Predictor]]:
    """(the group's sensors, model name -> predictor) of a train output directory ``models/<group>``: its
    networks (a family of kind network, `pipeline.calib.registry`), every linear model of baselines.json and
    the windowed network (win.json).
    A predictor takes one log's table, its rows in time order (a model with memory starts afresh at the
    first)."""
    from pipeline.calib.linear import LinearBaseline
    from pipeline.calib.models import load_model
    from pipeline.calib.registry import NETWORK, WIN, kind_of
    from pipeline.calib.window import read_window

    try:
        metrics = json.loads((model_dir / "metrics.json").read_text(encoding="utf-8"))
        sensors = list(metrics["sensors"])
    except (OSError, ValueError, KeyError) as exc:
        raise DataError(f"{model_dir}/metrics.json: not a trained group: {exc}") from None
    out: dict[str, Predictor] = {}
    for file in sorted(model_dir.glob("*.json")):
        if kind_of(file.stem) == NETWORK:
            net, config = load_model(file.with_suffix(""))
            out[file.stem] = _net_predictor(net, sensors, int(config["net"]["n_inputs"]))
    baselines = model_dir / "baselines.json"
    if baselines.is_file():
        for name, d in json.loads(baselines.read_text(encoding="utf-8")).items():
            out[name] = _log_predictor(LinearBaseline.from_dict(d), sensors)
    window = model_dir / f"{WIN}.json"
    if window.is_file():
        out[WIN] = _log_predictor(read_window(window), sensors)
    return sensors, out


def _net_predictor(net, sensors: list[str], n: int) -> Predictor:
    def predict(table: pd.DataFrame) -> dict[str, np.ndarray]:
        import torch

        x = _inputs(table, sensors, n)
        bad = ~np.isfinite(x).all(axis=(1, 2))
        with torch.no_grad():
            y = net(torch.as_tensor(np.nan_to_num(x).reshape(len(x), -1), dtype=torch.float32)).numpy()
        y = y.astype(np.float64).reshape(len(x), len(sensors), 6)
        y[bad] = np.nan
        return {s: y[:, i] for i, s in enumerate(sensors)}

    return predict


def _log_predictor(model, sensors: list[str]) -> Predictor:
    """A model with `predict_log` (a linear model, the windowed network) over one log's rows."""

    def predict(table: pd.DataFrame) -> dict[str, np.ndarray]:
        y = model.predict_log(_inputs(table, sensors, 7))
        return {s: y[:, i] for i, s in enumerate(sensors)}

    return predict


def deployed_models(exported: Path) -> dict[str, str]:
    """group -> the exported (deployed) model, from the export manifest."""
    from pipeline.export.runtime import Deployment

    deployment = Deployment.load(exported, offsets=False)
    return {group: str(entry["models"][group]) for group, entry in deployment.groups().items()}


def calibrated_wrenches(
    exported: Path, log: Path, table: pd.DataFrame, topics: object, offsets: Offsets | None = None
) -> dict[str, np.ndarray]:
    """Sensor -> (N, 6) calibrated wrench (N, Nm, sensor frame) at `table`'s stamps, for every sensor of
    the log that the export models (module docstring), with a re-zeroing's `offsets` (None: as delivered,
    whatever lies beside the export). NaN where no calibrated message brackets a stamp."""
    from pipeline.export.runtime import Deployment, calibrated_messages
    from pipeline.logs.rosmsg import LogReader

    deployment = Deployment.load(exported, offsets=False).with_offsets(offsets or Offsets())
    with LogReader(log) as reader:
        messages = calibrated_messages(deployment, reader, topics)
    stamps = table[S.STAMP].to_numpy(np.int64)
    out = {}
    for sensor, (t, w) in messages.items():
        x = (stamps - t[0]).astype(np.float64)
        xp = (t - t[0]).astype(np.float64)
        axes = [np.interp(x, xp, w[:, a], left=np.nan, right=np.nan) for a in range(6)]
        out[sensor] = np.column_stack(axes)
    if not out:
        raise DataError(f"{log}: the export in {exported} models none of its sensors")
    return out
