"""The trained models of a group applied to a deployment log, and the calibrated wrenches of a log.

`group_models` reads every model a group trained (networks and baselines) as a predictor on a table's
inputs: Test A measures each one's output noise. `calibrated_wrenches` is the one place where a log gets
the deployed calibration: the recommended model of each group (``<group>/deployed.txt`` if present, else
``nn7``) on the log's table. Swapping in the export's causal `ftcal calibrate` changes this function only.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.core.errors import DataError
from pipeline.logs import schema as S

Predictor = Callable[[pd.DataFrame], dict[str, np.ndarray]]  # table -> sensor -> (N, 6) N / Nm
DEFAULT_DEPLOYED = "nn7"  # the thesis's deployed model (7 inputs: no IMU noise in the output)


def _inputs(table: pd.DataFrame, sensors: list[str], n: int) -> np.ndarray:
    """(N, S, n) model inputs: raw wrench, temperature[, accelerometer, gyroscope]."""
    from pipeline.calib.data import input_cols

    return np.stack([table[input_cols(s, n)].to_numpy(np.float64) for s in sensors], axis=1)


def group_models(model_dir: Path) -> tuple[list[str], dict[str, Predictor]]:
    """(the group's sensors, model name -> predictor) of a train output directory ``models/<group>``."""
    from pipeline.calib.models import LinearBaseline, load_model

    try:
        metrics = json.loads((model_dir / "metrics.json").read_text(encoding="utf-8"))
        sensors = list(metrics["sensors"])
    except (OSError, ValueError, KeyError) as exc:
        raise DataError(f"{model_dir}/metrics.json: not a trained group: {exc}") from None
    out: dict[str, Predictor] = {}
    for file in sorted(model_dir.glob("nn*.json")):
        net, config = load_model(file.with_suffix(""))
        out[file.stem] = _net_predictor(net, sensors, int(config["net"]["n_inputs"]))
    baselines = model_dir / "baselines.json"
    if baselines.is_file():
        for name, d in json.loads(baselines.read_text(encoding="utf-8")).items():
            base = LinearBaseline(
                name, *(np.asarray(d[k], dtype=np.float64) for k in ("offset", "scale", "powers", "weights"))
            )
            out[name] = _linear_predictor(base, sensors)
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


def _linear_predictor(base, sensors: list[str]) -> Predictor:
    def predict(table: pd.DataFrame) -> dict[str, np.ndarray]:
        y = base.predict(_inputs(table, sensors, 7))
        return {s: y[:, i] for i, s in enumerate(sensors)}

    return predict


def deployed_model(model_dir: Path) -> str:
    """The model a lab deploys for this group: ``deployed.txt`` of the group, else the default."""
    file = model_dir / "deployed.txt"
    return file.read_text(encoding="utf-8").strip() if file.is_file() else DEFAULT_DEPLOYED


def calibrated_wrenches(models: Path, table: pd.DataFrame) -> dict[str, np.ndarray]:
    """Sensor -> (N, 6) calibrated wrench (N, Nm, sensor frame) of every modelled sensor of `table`'s log."""
    out: dict[str, np.ndarray] = {}
    for group_dir in sorted(p for p in models.iterdir() if (p / "metrics.json").is_file()):
        sensors, predictors = group_models(group_dir)
        if not all(c in table for s in sensors for c in S.wrench_cols(S.FT, s)):
            continue
        name = deployed_model(group_dir)
        if name not in predictors:
            raise DataError(f"{group_dir}: deployed model {name!r} not found")
        out.update(predictors[name](table))
    if not out:
        raise DataError(f"{models}: no trained group models the sensors of this log")
    return out
