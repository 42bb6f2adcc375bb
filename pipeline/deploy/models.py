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
    """(the group's sensors, model name -> predictor) of a train output directory ``models/<group>``: every
    model it trained that its family can run (`pipeline.calib.families.base.Family.loaded`; raw has none),
    and the plain least-squares affine map where the group has one.
    A predictor takes one log's table, its rows in time order (a model with memory starts afresh at the
    first)."""
    from pipeline.calib.families.closed_form import read_baseline
    from pipeline.calib.params import LS_AFFINE
    from pipeline.calib.registry import family_of

    try:
        metrics = json.loads((model_dir / "metrics.json").read_text(encoding="utf-8"))
        sensors = list(metrics["sensors"])
    except (OSError, ValueError, KeyError) as exc:
        raise DataError(f"{model_dir}/metrics.json: not a trained group: {exc}") from None
    out: dict[str, Predictor] = {}
    for name in metrics.get("test") or {}:
        family = family_of(name)
        if name == LS_AFFINE:
            out[name] = _predictor(read_baseline(model_dir, name).predict_log, 7, sensors)
        elif family is not None and (loaded := family.loaded(model_dir, name, sensors)) is not None:
            out[name] = _predictor(*loaded, sensors)
    return sensors, out


def _predictor(predict: Callable[[np.ndarray], np.ndarray], n: int, sensors: list[str]) -> Predictor:
    """A model's predictor over one log's table: its `n` inputs per sensor -> sensor -> (N, 6) wrench."""

    def run(table: pd.DataFrame) -> dict[str, np.ndarray]:
        y = predict(_inputs(table, sensors, n))
        return {s: y[:, i] for i, s in enumerate(sensors)}

    return run


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
