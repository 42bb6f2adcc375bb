"""evaluate's inputs and outputs, synthetic: a leg sensor's group and the r_foot pair's with labelled and
truth tables and models of known quality (`build_fixture`), both evaluated with the report
(`evaluate_both`), and evaluate's metrics files naming a recommended model (`write_recommended`)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from pipeline.core.config import load_params
from pipeline.logs import schema as S
from pipeline.logs.schema import prediction_cols
from tests.factories.labelled import FRONT, LEG, PAIR, REAR, TRANSFORMS, labelled_metadata, write_table
from tests.factories.params import write_evaluate_params

FS = 100.0  # Hz
NOISE = np.array([0.5, 0.5, 0.5, 0.03, 0.03, 0.03])  # raw white noise std per axis, N and Nm
SENSORS = (LEG, FRONT, REAR)
NOTE = f"{LEG}: no 13-input network: {LEG}: the IMU's axes are (x, y, z) = (-y, -x, z) of the sensor frame"
# Test logs: (name, experiment type, FT boards' angular speed rad/s, contacts alternate every n samples)
LOGS = [("08_pole_test", "pole", 0.01, None), ("11_walking_test", "walking", 0.8, 80)]
N = 600


CV = {
    "folds": [
        {"val": ["01_walking_train"], "train": ["00_pole_train"]},
        {"val": ["00_pole_train"], "train": []},
    ],
    "scores": {"nn7": [0.51, 0.73], "nn13": [0.42, 0.97]},
    "mean": {"nn7": 0.62, "nn13": 0.695},
    "spread": {"nn7": 0.11, "nn13": 0.275},
    "rule": "the lowest mean unless within the spread",
    "chosen": "nn7",
}


def _metadata(kind: str, log: str) -> dict[bytes, Any]:
    """The factories' labelled metadata (the r_foot pair) with a left foot (sole only) for the phases."""
    meta = labelled_metadata(kind, "test", log)
    meta[S.META_LABEL]["pairs"]["l_foot"] = {"sole": "l_sole"}
    return meta


def build_fixture(root: Path) -> dict[str, Path]:
    """labelled/, ingested/ (truth) and models/<group>/ for a leg sensor and a foot pair.

    Per sensor: true wrench w (slow sines), raw = w + offset + white noise, labels = w (NaN where the
    switch is 0), oracle = w + the same noise. Models: raw; affine = raw - offset (ratio 1); nn7 = affine
    + 0.1 N bias; nn13 = nn7 + white noise 3x raw's (ratio ~3.2: flagged). nn13 is best on validation,
    so the recommendation must fall back to nn7.
    """
    rng = np.random.default_rng(7)
    dirs = {k: root / k for k in ("labelled", "ingested", "models")}
    offsets = {s: rng.uniform(-30, 30, 6) * np.r_[1, 1, 1, 0.1, 0.1, 0.1] for s in SENSORS}
    preds: dict[str, list[dict[str, Any]]] = {LEG: [], PAIR: []}
    for li, (log, kind, speed, period) in enumerate(LOGS):
        lab, true, raw = _write_tables(dirs, li, (log, kind, speed, period), offsets, rng)
        extra = rng.normal(size=(N, 6)) * 3 * NOISE
        for group, cols in _predictions(log, lab, true, raw, offsets, extra).items():
            preds[group].append(cols)
    for group, sensors_of, pair in ((LEG, [LEG], None), (PAIR, [FRONT, REAR], PAIR)):
        _write_models(dirs["models"] / group, group, sensors_of, pair, preds[group])
    return dirs


def _write_tables(
    dirs: dict[str, Path],
    li: int,
    spec: tuple[str, str, float, int | None],
    offsets: dict[str, np.ndarray],
    rng: np.random.Generator,
) -> tuple[dict[str, Any], dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The labelled and truth tables of log number `li` (`spec`: a row of LOGS), N samples at FS; (the
    labelled table's columns, true wrenches (N, 6) and raw readings (N, 6) per sensor)."""
    log, kind, speed, period = spec
    t = np.arange(N) / FS
    stamp = (1_700_000_000_000_000_000 + li * 10**12 + np.arange(N) * 10_000_000).astype(np.int64)
    lab: dict[str, Any] = {S.STAMP: stamp, S.TIME: t}
    tru: dict[str, Any] = {S.STAMP: stamp, S.TIME: t}
    true, raw = {}, {}
    for k, s in enumerate(SENSORS):
        w = np.column_stack(
            [(40 if a < 3 else 3) * np.sin(2 * np.pi * (0.2 + 0.05 * a) * t + k + a) for a in range(6)]
        )
        noise = rng.normal(size=(N, 6)) * NOISE
        true[s], raw[s], oracle = w, w + offsets[s] + noise, w + noise
        g = rng.normal(size=(N, 3)) * 0.005 + speed / math.sqrt(3)
        for c, v in zip(S.vector_cols(S.GYR, s), g.T, strict=True):
            lab[c] = v
        for quantity, value in ((S.TRUE, w), (S.DISTORTED, w + offsets[s]), (S.ORACLE, oracle)):
            for c, v in zip(S.wrench_cols(quantity, s), value.T, strict=True):
                tru[c] = v
            tru[S.ok_col(quantity, s)] = np.ones(N, dtype=bool)
    if period is None:  # on the pole
        contacts = np.full(N, "root_link", dtype=object)
    else:  # single support on the right foot, double support
        contacts = np.where((np.arange(N) // period) % 2 == 0, "r_sole", "l_sole,r_sole").astype(object)
    changed = np.r_[False, contacts[1:] != contacts[:-1]]
    guard = changed | np.r_[changed[1:], False]  # the samples on either side of a contact change
    lab[S.CONTACTS] = contacts
    lab[S.GUARD] = guard
    tru[S.CONTACTS] = contacts
    switch = (contacts != "l_sole,r_sole") & ~guard
    lab[S.switch_col(LEG)] = switch.astype(np.uint8)
    lab[S.switch_col(PAIR)] = np.ones(N, dtype=np.uint8)
    write_table(dirs["labelled"] / f"{log}.parquet", lab, S.KIND_LABELLED, _metadata(kind, log))
    write_table(dirs["ingested"] / f"{log}{S.TRUTH_SUFFIX}.parquet", tru, S.KIND_TRUTH, {})
    return lab, true, raw


def _predictions(
    log: str,
    lab: dict[str, Any],
    true: dict[str, np.ndarray],
    raw: dict[str, np.ndarray],
    offsets: dict[str, np.ndarray],
    extra: np.ndarray,
) -> dict[str, dict[str, Any]]:
    """Each group's prediction columns of one log: labels, switches and the four models' predictions, the
    sample without ok inputs left out."""
    keep = np.ones(N, dtype=bool)
    keep[N // 2] = False  # a sample without ok inputs: not in the predictions
    out = {}
    for group, names in ((LEG, (LEG,)), (PAIR, (PAIR, FRONT, REAR))):
        cols: dict[str, Any] = {
            "log": np.full(keep.sum(), log, dtype=object),
            S.STAMP: lab[S.STAMP][keep],
            S.TIME: lab[S.TIME][keep],
        }
        per = {}
        for s in SENSORS:
            affine = raw[s] - offsets[s]
            per[s] = {"raw": raw[s], "affine": affine, "nn7": affine + 0.1, "nn13": affine + 0.1 + extra}
        per[PAIR] = {m: per[FRONT][m] @ TRANSFORMS[0].T + per[REAR][m] @ TRANSFORMS[1].T for m in per[LEG]}
        label_of = {
            LEG: true[LEG],
            FRONT: true[FRONT],
            REAR: true[REAR],
            PAIR: true[FRONT] @ TRANSFORMS[0].T + true[REAR] @ TRANSFORMS[1].T,
        }
        for name in names:
            sw = lab[S.switch_col(LEG)] if name != PAIR else lab[S.switch_col(PAIR)]
            for c, v in zip(
                S.wrench_cols(S.EXPECTED, name),
                np.where(sw[:, None] == 1, label_of[name], np.nan).T,
                strict=True,
            ):
                cols[c] = v[keep]
            cols[S.switch_col(name)] = sw[keep]
            for m, value in per[name].items():
                for c, v in zip(prediction_cols(m, name), value.T, strict=True):
                    cols[c] = v[keep]
        out[group] = cols
    return out


def _write_models(
    out: Path, group: str, sensors_of: list[str], pair: str | None, preds: list[dict[str, Any]]
) -> None:
    """train's output for `group` in `out`: predictions.parquet of every log, metrics.json (networks with
    their histories, the validation ranking, the cross-validation record or train's notes)."""
    out.mkdir(parents=True)
    frame = pd.concat([pd.DataFrame(c) for c in preds], ignore_index=True)
    table = pa.Table.from_pandas(frame, preserve_index=False).replace_schema_metadata(
        {b"ftcal.train": json.dumps({"group": group, "models": ["raw", "affine", "nn7", "nn13"]}).encode()}
    )
    pq.write_table(table, out / "predictions.parquet")
    networks: dict[str, Any] = {
        "nn7": {"trial": 1, "val_rmse_labelled": 0.5},
        "nn13": {"trial": 2, "val_rmse_labelled": 0.4},
    }
    networks["nn7"]["history"] = [
        {"epoch": e, "loss": 10.0 / (e + 1), "val_rmse": 2.0 / (e + 1)} for e in range(5)
    ]
    networks["nn13"]["history"] = [
        {"epoch": e, "loss": 8.0 / (e + 1), "val_rmse": 1.6 / (e + 1)} for e in range(3)
    ]
    metrics = {
        "group": group,
        "sensors": sensors_of,
        "pair": pair,
        "headline": pair or group,
        "best_on_validation": "nn13",
        "validation_ranking": ["nn13", "nn7", "affine", "raw"],
        "networks": networks,
    }
    if group == PAIR:  # train's cross-validation record (the leg group has none)
        metrics["cv"] = CV
    else:  # train's notes: a network it did not train, and why
        metrics["notes"] = [NOTE]
    (out / "metrics.json").write_text(json.dumps(metrics))


def evaluate_both(root: Path, dirs: dict[str, Path]) -> tuple[dict[str, Any], Path]:
    """evaluate@<group> of both fixture groups and the report into root/reports, in a real MLflow store
    under `root`; (results by group, the reports directory)."""
    from pipeline.stages import evaluate as E
    from pipeline.stages import report as REPORT

    mp = pytest.MonkeyPatch()
    mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{root / 'mlflow.db'}")
    try:
        params = load_params(write_evaluate_params(root))
        out = root / "reports"
        results = {
            g: E.run(params, g, dirs["models"] / g, dirs["labelled"], out, dirs["ingested"], progress=False)
            for g in (LEG, PAIR)
        }
        REPORT.run(params, out, dirs["labelled"])
    finally:
        mp.undo()
    return results, out


def write_recommended(tmp_path: Path, recommended: dict[str, Any]) -> Path:
    """evaluate's reports/metrics: <group>/<headline>.json with the recommended model ("none": flagged)."""
    path = tmp_path / "metrics"
    path.mkdir(exist_ok=True)
    for group, model in recommended.items():
        (path / group).mkdir(exist_ok=True)
        (path / group / f"{group}.json").write_text(
            json.dumps({"deployed": model or "none", "verdict": "at oracle"})
        )
    return path
