"""One group's test samples for evaluation: train's predictions joined with labelled and truth extras.

Against truth: ``true.<sensor>.<axis>`` and ``oracle.<sensor>.<axis>`` of ``<log>.truth.parquet`` aligned on
``stamp_ns``; a foot pair's true and oracle sums are ``sum_s sole_X_s w_s`` with the 6x6 transforms of the
labelled metadata ``ftcal.label`` (the same that `label` and `train` use).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.calib.registry import RAW
from pipeline.core.errors import DataError
from pipeline.evaluation.noise import board_speed, segment_ids
from pipeline.evaluation.params import (
    EXPERIMENT,
    ORACLE,
    PHASE,
    PREDICTIONS,
    SPEED,
    TRAIN_METRICS,
    EvaluateParams,
)
from pipeline.evaluation.phases import feet_of, phases_of
from pipeline.logs import schema as S
from pipeline.logs.schema import LOG, PRED, prediction_cols

# --- inputs --------------------------------------------------------------------------------------


@dataclass
class GroupInputs:
    """One group's test samples with everything evaluate needs.

    `frame` holds, per test sample (rows of predictions.parquet, sorted by log and stamp): ``log``,
    ``stamp_ns``, ``time_s``, labels ``exp.<name>.<axis>`` and switches ``sw.<name>``, predictions
    ``pred.<model>.<name>.<axis>`` (the oracle's too where truth exists), ``true.<name>.<axis>`` (NaN
    without truth), EXPERIMENT, SPEED, PHASE (`pipeline.evaluation.phases`), ``contacts`` and ``guard``.
    Names: the sensor, or the pair (sum in the sole frame) then front and rear.
    """

    group: str
    sensors: tuple[str, ...]
    pair: str | None
    headline: str
    names: list[str]
    models: list[str]  # in predictions order, then ORACLE if any truth
    train: dict[str, Any]  # models/<group>/metrics.json
    frame: pd.DataFrame
    fs: float  # Hz, sampling rate of the logs
    segments: np.ndarray  # (N,) contiguous stretch ids
    transforms: np.ndarray | None  # (2, 6, 6) sole_X_front, sole_X_rear
    has_truth: bool
    experiments: list[str]  # experiment types of the test logs, in log order
    headlines: list[str] | None = None  # several headlines (legs and feet trained together), else None


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except OSError:
        raise DataError(f"{path}: missing or unreadable") from None
    except ValueError as exc:
        raise DataError(f"{path}: not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise DataError(f"{path}: expected a JSON object")
    return data


def _pair_transforms(schema: pa.Schema, pair: str, path: Path) -> np.ndarray:
    meta = S.read_metadata(schema, S.META_LABEL) or {}
    entry = (meta.get("pairs") or {}).get(pair)
    try:
        return np.array([entry["sole_X_front"], entry["sole_X_rear"]], dtype=np.float64).reshape(2, 6, 6)
    except (TypeError, KeyError, ValueError):
        raise DataError(f"{path}: metadata ftcal.label has no 6x6 pairs.{pair}.sole_X_front/rear") from None


def wrench_of(df: pd.DataFrame, quantity: str, name: str) -> np.ndarray:
    return df[S.wrench_cols(quantity, name)].to_numpy(dtype=np.float64)


def _read_log_extras(
    log: str, labelled_dir: Path, truth_dir: Path | None, sensors: Sequence[str], pairs: Sequence[str]
) -> tuple[pd.DataFrame, str, dict[str, np.ndarray], bool]:
    """A test log's labelled extras (stamp, gyroscopes, contacts, guard) joined with its truth if any.

    Returns (table keyed by stamp_ns, experiment type, pair -> transforms, truth found).
    """
    path = labelled_dir / f"{log}{S.PARQUET_SUFFIX}"
    if not path.is_file():
        raise DataError(f"{path}: labelled table of test log {log} not found (predictions name it)")
    try:
        schema = pq.read_schema(path)
        cols = [S.STAMP, S.CONTACTS, S.GUARD] + [c for s in sensors for c in S.vector_cols(S.GYR, s)]
        missing = [c for c in cols if c not in schema.names]
        cols += [c for s in sensors for c in S.wrench_cols(S.FT, s) if c in schema.names]  # the noise floor
        if missing:
            raise DataError(f"{path}: not a labelled table: missing column {missing[0]}")
        table = pq.read_table(path, columns=cols).to_pandas()
    except (OSError, pa.ArrowException) as exc:
        raise DataError(f"{path}: cannot read Parquet table: {exc}") from None
    experiment = S.read_metadata(schema, S.META_EXPERIMENT) or {}
    kind = str(experiment.get("type", "")).strip() or "unknown"
    transforms = {pair: _pair_transforms(schema, pair, path) for pair in pairs}
    table[PHASE] = phases_of(
        table[S.CONTACTS].to_numpy(object), feet_of(S.read_metadata(schema, S.META_LABEL) or {})
    )
    found = False
    truth_path = truth_dir / f"{log}{S.TRUTH_SUFFIX}{S.PARQUET_SUFFIX}" if truth_dir is not None else None
    if truth_path is not None and truth_path.is_file():
        want = [S.STAMP]
        for s in sensors:
            want += (
                S.wrench_cols(S.TRUE, s)
                + S.wrench_cols(S.ORACLE, s)
                + [S.ok_col(S.TRUE, s), S.ok_col(S.ORACLE, s)]
            )
        try:
            names = pq.read_schema(truth_path).names
            missing = [c for c in want if c not in names]
            if missing:
                raise DataError(f"{truth_path}: not a truth table: missing column {missing[0]}")
            # the noise-free reading, for the noise floor (`pipeline.evaluation.floors`) where recorded
            want += [c for s in sensors for c in S.wrench_cols(S.DISTORTED, s) if c in names]
            truth = pq.read_table(truth_path, columns=want).to_pandas()
        except (OSError, pa.ArrowException) as exc:
            raise DataError(f"{truth_path}: cannot read Parquet table: {exc}") from None
        for s in sensors:
            for kind_ in (S.TRUE, S.ORACLE):
                bad = ~truth[S.ok_col(kind_, s)].to_numpy(bool)
                truth.loc[bad, S.wrench_cols(kind_, s)] = np.nan
        truth = truth.drop(columns=[c for c in truth.columns if c.startswith(S.OK + ".")])
        table = table.merge(truth, on=S.STAMP, how="left", validate="one_to_one")
        found = True
    return table, kind, transforms, found


def load_group(
    group: str, gdir: Path, labelled_dir: Path, truth_dir: Path | None, cfg: EvaluateParams
) -> GroupInputs:
    """Read one group's predictions and metrics and join the labelled and truth extras (see GroupInputs).

    Raises:
        DataError: the group's directory, metrics or predictions are missing or unusable, or a test log's
            labelled table is missing.
    """
    train, frame, names, models = _read_predictions(group, gdir)
    sensors, pair = tuple(train["sensors"]), train.get("pair")
    pairs = {pair: list(sensors)} if pair else dict(train.get("pairs") or {})
    pred_path = gdir / PREDICTIONS
    frame, kinds, all_transforms, any_truth = _join_extras(
        frame, pred_path, labelled_dir, truth_dir, sensors, list(pairs)
    )
    frame[EXPERIMENT] = frame[LOG].map(kinds)
    frame = _truth_and_oracle(frame, sensors, pairs, names, all_transforms)
    transforms = all_transforms.get(pair) if pair else None
    if any_truth:
        models.append(ORACLE)
    segments, fs = segment_ids(frame[LOG].to_numpy(), frame[S.STAMP].to_numpy())
    gyro = [frame[S.vector_cols(S.GYR, s)].to_numpy(np.float64) for s in sensors]
    frame[SPEED] = board_speed(gyro, segments, fs, cfg.highpass_hz, cfg.highpass_order)
    logs = list(dict.fromkeys(frame[LOG].tolist()))
    return GroupInputs(
        group=group,
        sensors=sensors,
        pair=pair,
        headline=str(train.get("headline") or names[0]),
        names=names,
        models=models,
        train=train,
        frame=frame,
        fs=fs,
        segments=segments,
        transforms=transforms,
        has_truth=any_truth,
        experiments=list(dict.fromkeys(kinds[log] for log in logs)),
        headlines=[str(h) for h in train["headlines"]] if len(train.get("headlines") or []) > 1 else None,
    )


def _read_predictions(group: str, gdir: Path) -> tuple[dict[str, Any], pd.DataFrame, list[str], list[str]]:
    """(train metrics, predictions sorted by log and stamp, names, models) of a group's model directory."""
    if not gdir.is_dir():
        raise DataError(f"{gdir}: no models for group {group} (run `dvc repro train@{group}`)")
    pred_path = gdir / PREDICTIONS
    if not pred_path.is_file():
        raise DataError(f"{pred_path}: group {group} has no test predictions (run `dvc repro train@{group}`)")
    train = _read_json(gdir / TRAIN_METRICS)
    sensors = tuple(train.get("sensors") or ())
    pair = train.get("pair")
    if not sensors or train.get("group", group) != group:
        raise DataError(f"{gdir / TRAIN_METRICS}: not the training metrics of group {group}")
    try:
        schema = pq.read_schema(pred_path)
        meta = json.loads((schema.metadata or {}).get(b"ftcal.train", b"{}"))
    except (OSError, pa.ArrowException, ValueError) as exc:
        raise DataError(f"{pred_path}: cannot read the predictions: {exc}") from None
    names = [pair, *sensors] if pair else list(sensors)
    headlines = [str(h) for h in train.get("headlines") or []]
    if len(headlines) > 1:  # several sensors trained together: the headlines (legs, foot sums) first
        names = [*headlines, *(s for s in sensors if s not in headlines)]
    models = list(meta.get("models") or [])
    if not models:
        prefix = f"{PRED}."
        suffix = f".{names[0]}.{S.WRENCH_AXES[0]}"
        models = [
            c[len(prefix) : -len(suffix)] for c in schema.names if c.startswith(prefix) and c.endswith(suffix)
        ]
    needed = [LOG, S.STAMP, S.TIME]
    for name in names:
        needed += S.wrench_cols(S.EXPECTED, name) + [S.switch_col(name)]
        for model in models:
            needed += prediction_cols(model, name)
    missing = [c for c in needed if c not in schema.names]
    if RAW not in models or missing:
        detail = f"missing column {missing[0]}" if missing else f"no {RAW} predictions"
        raise DataError(f"{pred_path}: not the predictions of group {group}: {detail}")
    try:  # only the columns of the group's names: train also writes labels of other sensor sets
        frame = pd.read_parquet(pred_path, columns=needed)
    except (OSError, pa.ArrowException, ValueError) as exc:
        raise DataError(f"{pred_path}: cannot read the predictions: {exc}") from None
    if frame.empty:
        raise DataError(f"{pred_path}: no test samples")
    frame = frame.sort_values([LOG, S.STAMP], kind="stable").reset_index(drop=True)
    return train, frame, names, models


def _join_extras(
    frame: pd.DataFrame,
    pred_path: Path,
    labelled_dir: Path,
    truth_dir: Path | None,
    sensors: tuple[str, ...],
    pairs: Sequence[str],
) -> tuple[pd.DataFrame, dict[str, str], dict[str, np.ndarray], bool]:
    """The predictions joined with each test log's labelled and truth extras; (frame, log -> experiment
    type, pair -> transforms, whether any truth was found)."""
    parts, kinds, transforms, any_truth = [], {}, {}, False
    logs = list(dict.fromkeys(frame[LOG].tolist()))
    for log in logs:
        extras, kind, ts, found = _read_log_extras(log, labelled_dir, truth_dir, sensors, pairs)
        kinds[log] = kind
        any_truth |= found
        for pair, t in ts.items():
            if pair in transforms and not np.allclose(t, transforms[pair], rtol=1e-9, atol=1e-12):
                raise DataError(
                    f"{labelled_dir / log}{S.PARQUET_SUFFIX}: pairs.{pair} transforms differ between logs"
                )
            transforms[pair] = t
        extras.insert(0, LOG, log)
        parts.append(extras)
    extras = pd.concat(parts, ignore_index=True)
    n = len(frame)
    frame = frame.merge(extras, on=[LOG, S.STAMP], how="left", validate="one_to_one")
    if len(frame) != n or frame[S.GUARD].isna().any():
        bad = frame.loc[frame[S.GUARD].isna(), LOG]
        raise DataError(
            f"{pred_path}: test samples not in the labelled tables (log {bad.iloc[0] if len(bad) else '?'})"
        )
    frame[S.GUARD] = frame[S.GUARD].astype(bool)
    return frame, kinds, transforms, any_truth


def _truth_and_oracle(
    frame: pd.DataFrame,
    sensors: tuple[str, ...],
    pairs: dict[str, list[str]],
    names: list[str],
    transforms: dict[str, np.ndarray],
) -> pd.DataFrame:
    """Truth and oracle columns per name (a pair's sums in the sole frame); the oracle as a model's.
    `pairs`: foot pair -> its (front, rear) sensors."""
    n = len(frame)
    new_cols: dict[str, np.ndarray] = {}
    for quantity in (S.TRUE, S.ORACLE):
        per_sensor = {}
        for s in sensors:
            cols = S.wrench_cols(quantity, s)
            per_sensor[s] = frame[cols].to_numpy(np.float64) if cols[0] in frame else np.full((n, 6), np.nan)
        for pair, members in pairs.items():
            stacked = np.stack([per_sensor[s] for s in members], axis=1)
            per_sensor[pair] = np.einsum("sij,nsj->ni", transforms[pair], stacked)
        target = S.TRUE if quantity == S.TRUE else f"{PRED}.{ORACLE}"
        for name in names:
            for a, c in enumerate(S.wrench_cols(target, name)):
                new_cols[c] = per_sensor[name][:, a]
    from pipeline.evaluation.floors import noise_columns

    new_cols.update(noise_columns(frame, sensors, pairs, names, transforms))
    frame = frame.drop(columns=[c for c in frame.columns if c.startswith((S.TRUE + ".", S.ORACLE + "."))])
    return pd.concat([frame, pd.DataFrame(new_cols, index=frame.index)], axis=1)
