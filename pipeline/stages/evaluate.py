"""Stage `evaluate`: what a researcher reads to decide which calibration goes on the robot.

``ftcal evaluate MODELS LABELLED OUT [--truth INGESTED]`` reads every group of ``train.groups`` from
``MODELS/<group>/`` (the test-set ``predictions.parquet`` and ``metrics.json`` of the train stage), the
labelled test tables (experiment type, FT-board gyroscopes, contact sets, foot-pair transforms) and, for
simulated logs, the truth tables; it writes ``OUT``:

- ``metrics.json`` (for ``dvc metrics show``): per group a summary (raw and best model, the two acceptance
  ratios, noise flags, the model to deploy), and the thesis's tables: per sensor (a foot: the pair's sum in
  the sole frame and each part) and model, MSE/MAE/RMSE global, force, torque and per axis, against the
  labels (where the sensor's switch is 1) and, for simulated logs, against the true wrench (every sample);
  the simulator's ``oracle`` calibration is an extra model (the noise floor); RMSE per experiment type.
- ``index.html`` and ``plots/*.png``: every table and figure (`pipeline.evaluation.report`).
- ``plots_data/``: CSV series for ``dvc plots show`` (RMSE per model, loss curves, noise ratios).

Against truth: ``true.<sensor>.<axis>`` and ``oracle.<sensor>.<axis>`` of ``<log>.truth.parquet`` aligned on
``stamp_ns``; a foot pair's true and oracle sums are ``sum_s sole_X_s w_s`` with the 6x6 transforms of the
labelled metadata ``ftcal.label`` (the same that `label` and `train` use).

Deployment noise (thesis chapter 6, Test A: the 13-input network passed the FT board's IMU noise into its
output and was unusable on the robot, standing still). On quasi-static segments, the high-frequency part
of each model's output (zero-phase Butterworth high-pass at ``highpass_hz``) is compared with raw's:
``ratio = std(HF model) / std(HF raw)`` per sensor (or sum) and axis; a model's ratio is its worst axis, and
a model above ``noise_threshold`` is flagged. A model that copies raw scores 1, one that adds noise more,
a smoother less. Quasi-static: samples where the group's FT boards turn slower than ``still_gyro_rad_s``
(gyroscope norm, low-passed), with a constant contact set and outside guard bands (contact changes make
real high-frequency wrenches), in runs of at least ``still_min_s`` within a contiguous stretch of samples.
The gyroscopes are in the labelled tables, so no further dependency is needed; joint velocities would not
do better on simulated logs, whose joints never stop. For simulated logs the check is validated: the
share of the raw high-frequency content that is true signal (``signal_fraction``) is reported; near 0
means the ratio measures noise only.

Model to deploy: the group's lowest-validation-error model (``best_on_validation`` of `train`) unless
flagged, else the next of ``validation_ranking`` that is not.

Loss curves: ``networks.<nn>.history`` of ``metrics.json`` if `train` writes it, else the per-epoch
``loss``/``val_rmse`` metrics of the best trial's nested MLflow run (found by group, network, trial and
its ``best_val_rmse``). The MLflow run ``evaluate`` gets the metrics, the report and plots as artifacts,
and is linked to the evaluated training runs and registered model versions (tags, and metrics logged with
the logged models' ``model_id``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.calib.models import wrench_errors
from pipeline.core.config import Params, load_params, stage_section
from pipeline.core.errors import ConfigError, DataError
from pipeline.logs import schema as S
from pipeline.logs.schema import LOG, PRED, prediction_cols
from pipeline.calib.params import RAW, nn_name

STAGE = "evaluate"
ORACLE = "oracle"  # the simulator's oracle calibration, an extra model in the tables (truth tables only)
LABELS, TRUTH = "labels", "truth"  # references the errors are computed against
# truth scored on the labelled samples only: like for like with LABELS (TRUTH also covers the samples
# without labels, e.g. double support, where a model interpolates without supervision)
TRUTH_LABELLED = "truth_labelled"
REFERENCES = (LABELS, TRUTH_LABELLED, TRUTH)
REFERENCE_TITLES = {
    LABELS: "labels",
    TRUTH_LABELLED: "truth (labelled samples)",
    TRUTH: "truth (all samples)",
}
NN7, NN13 = nn_name(7), nn_name(13)
METRICS_FILE = "metrics.json"
REPORT_FILE = "index.html"
PLOTS_DIR = "plots"
PLOTS_DATA_DIR = "plots_data"
TRAIN_METRICS = "metrics.json"  # in models/<group>/
PREDICTIONS = "predictions.parquet"
# In-memory columns that evaluate adds to a group's prediction table (never written to Parquet).
EXPERIMENT = "experiment"  # experiment type of the sample's log (pole, balancing, ...)
SPEED = "speed"  # rad/s: angular speed of the group's FT boards (gyroscope norm, low-passed; max over boards)
_MAX_STEP = 1.5  # a stamp step above this many nominal periods splits a contiguous stretch


@dataclass(frozen=True)
class EvaluateParams:
    """Section `evaluate` of params.yaml (see the comments there)."""

    highpass_hz: float  # Hz: noise = what a high-pass at this cutoff keeps
    highpass_order: int  # Butterworth order (applied forward and backward)
    still_gyro_rad_s: float  # rad/s: quasi-static below this angular speed of the FT boards
    still_min_s: float  # s: shortest quasi-static run
    noise_threshold: float  # noise amplification above this (worst axis) flags a model
    zoom_s: float  # s: length of the per-experiment zoom of the time-series plots
    target_raw_over_nn7: float  # acceptance: raw RMSE / NN7 RMSE at least this
    target_nn7_over_oracle: float  # acceptance: NN7 RMSE / oracle RMSE at most this

    def __post_init__(self) -> None:
        for name in (
            "highpass_hz",
            "still_gyro_rad_s",
            "still_min_s",
            "noise_threshold",
            "zoom_s",
            "target_raw_over_nn7",
            "target_nn7_over_oracle",
        ):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, int | float)
                or not math.isfinite(value)
                or value <= 0
            ):
                raise ConfigError(f"evaluate.{name} must be a positive number, got {value!r}")
            object.__setattr__(self, name, float(value))
        order = self.highpass_order
        if isinstance(order, bool) or not isinstance(order, int) or not 1 <= order <= 8:
            raise ConfigError(f"evaluate.highpass_order must be an integer in [1, 8], got {order!r}")


# --- errors --------------------------------------------------------------------------------------


def score(pred: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """Thesis tables 5.1-5.3 of predictions (N, 6) against references (N, 6), N and Nm, on `mask` (N,).

    Keys ``mse``/``mae``/``rmse`` (global: the 6 components pooled, mixed units as in the thesis), with
    suffixes ``_force``, ``_torque``, ``_<axis>``, and ``samples``; NaN where no sample is left. Samples
    where either side is not finite are left out (a label is NaN where its switch is 0).
    """
    pred = np.asarray(pred, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    keep = np.isfinite(pred).all(axis=1) & np.isfinite(ref).all(axis=1)
    if mask is not None:
        keep &= np.asarray(mask, dtype=bool)
    return wrench_errors(pred[keep], ref[keep])


def ratio(numerator: float | None, denominator: float | None) -> float | None:
    """numerator / denominator, or None when either is missing, not finite, or the denominator is 0."""
    if numerator is None or denominator is None:
        return None
    if not (math.isfinite(numerator) and math.isfinite(denominator)) or denominator == 0:
        return None
    return numerator / denominator


# --- deployment noise ----------------------------------------------------------------------------


def segment_ids(log: np.ndarray, stamp_ns: np.ndarray) -> tuple[np.ndarray, float]:
    """Contiguous stretches of samples and the sampling rate.

    Args:
        log: (N,) log of each sample; stamp_ns: (N,) int64 ns, increasing within a log.

    Returns:
        ((N,) int id of the stretch of each sample, sampling rate in Hz). A stretch ends where the log
        changes or the stamp steps by more than 1.5 nominal periods (the median step): a lost sample.
    """
    stamp = np.asarray(stamp_ns, dtype=np.int64)
    log = np.asarray(log)
    if len(stamp) < 2:
        return np.zeros(len(stamp), dtype=np.int64), math.nan
    step = np.diff(stamp).astype(np.float64)
    same = log[1:] == log[:-1]
    nominal = float(np.median(step[same & (step > 0)])) if (same & (step > 0)).any() else math.nan
    new = ~same | (step <= 0) | (step > _MAX_STEP * nominal)
    return np.r_[0, np.cumsum(new)].astype(np.int64), 1e9 / nominal


def _runs(ids: np.ndarray) -> list[tuple[int, int]]:
    """[(start, stop)] of the runs of equal consecutive values of `ids` (N,)."""
    if len(ids) == 0:
        return []
    edges = np.flatnonzero(ids[1:] != ids[:-1]) + 1
    starts = np.r_[0, edges]
    stops = np.r_[edges, len(ids)]
    return list(zip(starts.tolist(), stops.tolist(), strict=True))


def highpass(x: np.ndarray, segments: np.ndarray, fs: float, cutoff_hz: float, order: int) -> np.ndarray:
    """Zero-phase Butterworth high-pass of x (N, C) along time, each stretch of `segments` (N,) alone.

    Stretches too short for the forward-backward filter's padding are NaN. Units are those of x.
    """
    from scipy.signal import butter, sosfiltfilt

    x = np.asarray(x, dtype=np.float64)
    out = np.full_like(x, np.nan)
    if not math.isfinite(fs) or cutoff_hz >= fs / 2:
        return out
    sos = butter(order, cutoff_hz, btype="highpass", fs=fs, output="sos")
    padlen = 3 * (2 * len(sos) + 1 - min(int((sos[:, 2] == 0).sum()), int((sos[:, 5] == 0).sum())))
    for start, stop in _runs(segments):
        chunk = x[start:stop]
        if stop - start > padlen and np.isfinite(chunk).all():
            out[start:stop] = sosfiltfilt(sos, chunk, axis=0)
    return out


def board_speed(
    gyro: Sequence[np.ndarray], segments: np.ndarray, fs: float, cutoff_hz: float, order: int
) -> np.ndarray:
    """(N,) rad/s: the largest angular speed among FT boards, from their gyroscopes (each (N, 3), rad/s).

    Each gyroscope is low-passed (the complement of `highpass`: noise and vibration removed) before its norm.
    """
    speeds = []
    for g in gyro:
        g = np.asarray(g, dtype=np.float64)
        speeds.append(np.linalg.norm(g - highpass(g, segments, fs, cutoff_hz, order), axis=1))
    return np.max(speeds, axis=0)


def quasi_static_mask(
    speed: np.ndarray,
    contacts: np.ndarray,
    guard: np.ndarray,
    segments: np.ndarray,
    fs: float,
    max_speed: float,
    min_s: float,
    edge_s: float,
) -> np.ndarray:
    """(N,) bool: samples in quasi-static runs.

    A run is a maximal stretch of consecutive samples of one segment with one contact set, outside guard
    bands, whose `speed` (N,) rad/s stays below `max_speed`, at least `min_s` long (at `fs` Hz). Samples
    within `edge_s` of a segment's ends are left out (where a zero-phase filter has transients).
    """
    n = len(speed)
    ok = np.isfinite(speed) & (speed < max_speed) & ~np.asarray(guard, dtype=bool)
    edge = int(round(edge_s * fs)) if math.isfinite(fs) else 0
    for start, stop in _runs(segments):
        ok[start : min(stop, start + edge)] = False
        ok[max(start, stop - edge) : stop] = False
    # Run ids change with the segment, the contact set and the ok flag.
    contacts = np.asarray(contacts, dtype=object)
    change = np.ones(n, dtype=bool)
    if n > 1:
        change[1:] = (segments[1:] != segments[:-1]) | (contacts[1:] != contacts[:-1]) | (ok[1:] != ok[:-1])
    ids = np.cumsum(change)
    min_len = max(1, int(math.ceil(min_s * fs))) if math.isfinite(fs) else n + 1
    mask = np.zeros(n, dtype=bool)
    for start, stop in _runs(ids):
        if ok[start] and stop - start >= min_len:
            mask[start:stop] = True
    return mask


def noise_ratio(model_hf: np.ndarray, raw_hf: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(C,) std of a model's high-frequency output over raw's, on the samples of `mask` (N,).

    model_hf, raw_hf: (N, C) high-passed outputs (same units per column). NaN for a column with fewer
    than 2 samples or no raw noise.
    """
    m = np.asarray(mask, dtype=bool) & np.isfinite(model_hf).all(axis=1) & np.isfinite(raw_hf).all(axis=1)
    if m.sum() < 2:
        return np.full(model_hf.shape[1], np.nan)
    num = np.std(model_hf[m], axis=0)
    den = np.std(raw_hf[m], axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 0, num / den, np.nan)


# --- inputs --------------------------------------------------------------------------------------


@dataclass
class GroupInputs:
    """One group's test samples with everything evaluate needs.

    `frame` holds, per test sample (rows of predictions.parquet, sorted by log and stamp): ``log``,
    ``stamp_ns``, ``time_s``, labels ``exp.<name>.<axis>`` and switches ``sw.<name>``, predictions
    ``pred.<model>.<name>.<axis>`` (the oracle's too where truth exists), ``true.<name>.<axis>`` (NaN
    without truth), EXPERIMENT, SPEED, ``contacts`` and ``guard``. Names: the sensor, or the pair (sum in
    the sole frame) then front and rear.
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


def _wrench(df: pd.DataFrame, quantity: str, name: str) -> np.ndarray:
    return df[S.wrench_cols(quantity, name)].to_numpy(dtype=np.float64)


def _read_log_extras(
    log: str, labelled_dir: Path, truth_dir: Path | None, sensors: Sequence[str], pair: str | None
) -> tuple[pd.DataFrame, str, np.ndarray | None, bool]:
    """A test log's labelled extras (stamp, gyroscopes, contacts, guard) joined with its truth if any.

    Returns (table keyed by stamp_ns, experiment type, pair transforms or None, truth found).
    """
    path = labelled_dir / f"{log}{S.PARQUET_SUFFIX}"
    if not path.is_file():
        raise DataError(f"{path}: labelled table of test log {log} not found (predictions name it)")
    try:
        schema = pq.read_schema(path)
        cols = [S.STAMP, S.CONTACTS, S.GUARD] + [c for s in sensors for c in S.vector_cols(S.GYR, s)]
        missing = [c for c in cols if c not in schema.names]
        if missing:
            raise DataError(f"{path}: not a labelled table: missing column {missing[0]}")
        table = pq.read_table(path, columns=cols).to_pandas()
    except (OSError, pa.ArrowException) as exc:
        raise DataError(f"{path}: cannot read Parquet table: {exc}") from None
    experiment = S.read_metadata(schema, S.META_EXPERIMENT) or {}
    kind = str(experiment.get("type", "")).strip() or "unknown"
    transforms = _pair_transforms(schema, pair, path) if pair is not None else None
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
    group: str, models_dir: Path, labelled_dir: Path, truth_dir: Path | None, cfg: EvaluateParams
) -> GroupInputs:
    """Read one group's predictions and metrics and join the labelled and truth extras (see GroupInputs).

    Raises:
        DataError: the group's directory, metrics or predictions are missing or unusable, or a test log's
            labelled table is missing.
    """
    gdir = models_dir / group
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
        frame = pd.read_parquet(pred_path)
        meta = json.loads((pq.read_schema(pred_path).metadata or {}).get(b"ftcal.train", b"{}"))
    except (OSError, pa.ArrowException, ValueError) as exc:
        raise DataError(f"{pred_path}: cannot read the predictions: {exc}") from None
    names = [pair, *sensors] if pair else list(sensors)
    models = list(meta.get("models") or [])
    if not models:
        prefix = f"{PRED}."
        suffix = f".{names[0]}.{S.WRENCH_AXES[0]}"
        models = [
            c[len(prefix) : -len(suffix)]
            for c in frame.columns
            if c.startswith(prefix) and c.endswith(suffix)
        ]
    needed = [LOG, S.STAMP, S.TIME]
    for name in names:
        needed += S.wrench_cols(S.EXPECTED, name) + [S.switch_col(name)]
        for model in models:
            needed += prediction_cols(model, name)
    missing = [c for c in needed if c not in frame.columns]
    if RAW not in models or missing:
        detail = f"missing column {missing[0]}" if missing else f"no {RAW} predictions"
        raise DataError(f"{pred_path}: not the predictions of group {group}: {detail}")
    if frame.empty:
        raise DataError(f"{pred_path}: no test samples")
    frame = frame.sort_values([LOG, S.STAMP], kind="stable").reset_index(drop=True)

    parts, kinds, transforms, any_truth = [], {}, None, False
    logs = list(dict.fromkeys(frame[LOG].tolist()))
    for log in logs:
        extras, kind, t, found = _read_log_extras(log, labelled_dir, truth_dir, sensors, pair)
        kinds[log] = kind
        any_truth |= found
        if t is not None:
            if transforms is not None and not np.allclose(t, transforms, rtol=1e-9, atol=1e-12):
                raise DataError(
                    f"{labelled_dir / log}{S.PARQUET_SUFFIX}: pairs.{pair} transforms differ between logs"
                )
            transforms = t
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
    frame[EXPERIMENT] = frame[LOG].map(kinds)

    # truth and oracle per name (a pair's sums in the sole frame); the oracle becomes a model
    new_cols: dict[str, np.ndarray] = {}
    for quantity in (S.TRUE, S.ORACLE):
        per_sensor = {}
        for s in sensors:
            cols = S.wrench_cols(quantity, s)
            per_sensor[s] = frame[cols].to_numpy(np.float64) if cols[0] in frame else np.full((n, 6), np.nan)
        if pair is not None:
            stacked = np.stack([per_sensor[s] for s in sensors], axis=1)
            per_sensor[pair] = np.einsum("sij,nsj->ni", transforms, stacked)
        target = S.TRUE if quantity == S.TRUE else f"{PRED}.{ORACLE}"
        for name in names:
            for a, c in enumerate(S.wrench_cols(target, name)):
                new_cols[c] = per_sensor[name][:, a]
    frame = frame.drop(columns=[c for c in frame.columns if c.startswith((S.TRUE + ".", S.ORACLE + "."))])
    frame = pd.concat([frame, pd.DataFrame(new_cols, index=frame.index)], axis=1)
    if any_truth:
        models.append(ORACLE)

    segments, fs = segment_ids(frame[LOG].to_numpy(), frame[S.STAMP].to_numpy())
    gyro = [frame[S.vector_cols(S.GYR, s)].to_numpy(np.float64) for s in sensors]
    frame[SPEED] = board_speed(gyro, segments, fs, cfg.highpass_hz, cfg.highpass_order)
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
    )


# --- one group -----------------------------------------------------------------------------------


@dataclass
class NoiseResult:
    """Noise amplification of every model of a group on its quasi-static samples."""

    quasi_static_s: float  # s of quasi-static samples
    windows: int  # quasi-static runs
    ratio: dict[str, float | None]  # model -> worst channel's ratio
    ratio_rms: dict[str, float | None]  # model -> root mean square over channels
    per_channel: dict[str, dict[str, float | None]]  # model -> "<name>.<axis>" -> ratio
    worst_channel: dict[str, str | None]  # model -> its worst "<name>.<axis>"
    signal_fraction: float | None  # max over channels of std(HF truth) / std(HF raw); None without truth
    flagged: list[str]
    mask: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0, bool))


@dataclass
class GroupResult:
    inputs: GroupInputs
    tables: dict[str, dict[str, dict[str, dict[str, float]]]]  # name -> ref -> model -> errors
    by_experiment: dict[
        str, dict[str, dict[str, dict[str, float]]]
    ]  # name -> ref -> experiment -> model -> rmse
    noise: NoiseResult
    best_on_validation: str | None
    validation_ranking: list[str]
    recommended: str | None
    histories: dict[str, list[dict[str, float]]]  # network -> [{epoch, loss, val_rmse}]
    history_source: str
    train_run: str | None = None
    model_versions: dict[str, dict[str, str]] = field(
        default_factory=dict
    )  # network -> {name, version, model_id}

    @property
    def group(self) -> str:
        return self.inputs.group

    def headline_rmse(self, ref: str, model: str, key: str = "rmse") -> float | None:
        value = self.tables.get(self.inputs.headline, {}).get(ref, {}).get(model, {}).get(key)
        return None if value is None or not math.isfinite(value) else float(value)

    def ratios(self) -> dict[str, dict[str, float | None]]:
        """raw / nn7 and nn7 / oracle of the headline's global RMSE, per reference."""
        out: dict[str, dict[str, float | None]] = {"raw_over_nn7": {}, "nn7_over_oracle": {}}
        for ref in REFERENCES:
            nn7 = self.headline_rmse(ref, NN7)
            out["raw_over_nn7"][ref] = ratio(self.headline_rmse(ref, RAW), nn7)
            out["nn7_over_oracle"][ref] = ratio(nn7, self.headline_rmse(ref, ORACLE))
        return out


def _masks(g: GroupInputs, name: str) -> dict[str, np.ndarray]:
    f = g.frame
    out = {LABELS: f[S.switch_col(name)].to_numpy() == 1}
    if g.has_truth:
        out[TRUTH] = np.isfinite(_wrench(f, S.TRUE, name)).all(axis=1)
        out[TRUTH_LABELLED] = out[TRUTH] & out[LABELS]
    return out


def error_tables(g: GroupInputs) -> tuple[dict, dict]:
    """(tables, by_experiment) of a group: see GroupResult. The oracle is scored where it exists."""
    f = g.frame
    tables: dict[str, dict[str, dict[str, dict[str, float]]]] = {}
    by_exp: dict[str, dict[str, dict[str, dict[str, float]]]] = {}
    experiments = f[EXPERIMENT].to_numpy()
    for name in g.names:
        refs = {LABELS: _wrench(f, S.EXPECTED, name)}
        if g.has_truth:
            refs[TRUTH_LABELLED] = refs[TRUTH] = _wrench(f, S.TRUE, name)
        masks = _masks(g, name)
        tables[name], by_exp[name] = {}, {}
        for ref, target in refs.items():
            tables[name][ref], by_exp[name][ref] = {}, {}
            preds = {m: _wrench(f, f"{PRED}.{m}", name) for m in g.models}
            for model, pred in preds.items():
                tables[name][ref][model] = score(pred, target, masks[ref])
            for kind in g.experiments:
                in_kind = masks[ref] & (experiments == kind)
                by_exp[name][ref][kind] = {m: score(p, target, in_kind)["rmse"] for m, p in preds.items()}
    return tables, by_exp


def noise_check(g: GroupInputs, cfg: EvaluateParams) -> NoiseResult:
    """Noise amplification ratios of every model of a group (module docstring)."""
    f = g.frame
    mask = quasi_static_mask(
        f[SPEED].to_numpy(),
        f[S.CONTACTS].fillna("").to_numpy(dtype=object),
        f[S.GUARD].to_numpy(bool),
        g.segments,
        g.fs,
        cfg.still_gyro_rad_s,
        cfg.still_min_s,
        edge_s=1.0 / cfg.highpass_hz,
    )

    def hf(quantity: str) -> np.ndarray:
        x = np.concatenate([_wrench(f, quantity, name) for name in g.names], axis=1)
        return highpass(x, g.segments, g.fs, cfg.highpass_hz, cfg.highpass_order)

    channels = [f"{name}.{axis}" for name in g.names for axis in S.WRENCH_AXES]
    raw_hf = hf(f"{PRED}.{RAW}")
    result = NoiseResult(
        quasi_static_s=float(mask.sum() / g.fs) if math.isfinite(g.fs) else 0.0,
        windows=int(np.sum(np.diff(np.r_[0, mask.astype(np.int8)]) == 1)),  # rising edges
        ratio={},
        ratio_rms={},
        per_channel={},
        worst_channel={},
        signal_fraction=None,
        flagged=[],
        mask=mask,
    )
    for model in g.models:
        r = noise_ratio(hf(f"{PRED}.{model}"), raw_hf, mask)
        finite = np.isfinite(r)
        result.per_channel[model] = {
            c: (float(v) if np.isfinite(v) else None) for c, v in zip(channels, r, strict=True)
        }
        if finite.any():
            worst = int(np.nanargmax(np.where(finite, r, -np.inf)))
            result.ratio[model] = float(r[worst])
            result.worst_channel[model] = channels[worst]
            result.ratio_rms[model] = float(np.sqrt(np.mean(r[finite] ** 2)))
        else:
            result.ratio[model] = result.ratio_rms[model] = result.worst_channel[model] = None
        if model != ORACLE and result.ratio[model] is not None and result.ratio[model] > cfg.noise_threshold:
            result.flagged.append(model)
    if g.has_truth:
        sig = noise_ratio(hf(S.TRUE), raw_hf, mask)
        if np.isfinite(sig).any():
            result.signal_fraction = float(np.nanmax(sig))
    return result


def recommend(ranking: Sequence[str], flagged: Iterable[str], available: Iterable[str]) -> str | None:
    """The first model of the validation ranking that is not flagged and was evaluated (None if none)."""
    flagged, available = set(flagged), set(available)
    return next((m for m in ranking if m not in flagged and m in available), None)


def evaluate_group(g: GroupInputs, cfg: EvaluateParams) -> GroupResult:
    """Tables, per-experiment RMSE, noise check and recommendation of one group (pure: no I/O)."""
    tables, by_exp = error_tables(g)
    noise = noise_check(g, cfg)
    ranking = [str(m) for m in (g.train.get("validation_ranking") or [])]
    best = g.train.get("best_on_validation")
    if best is not None and best not in ranking:
        ranking.insert(0, str(best))
    return GroupResult(
        inputs=g,
        tables=tables,
        by_experiment=by_exp,
        noise=noise,
        best_on_validation=None if best is None else str(best),
        validation_ranking=ranking,
        recommended=recommend(ranking, noise.flagged, g.models),
        histories={},
        history_source="none",
    )


# --- metrics.json --------------------------------------------------------------------------------


def _clean(value: Any) -> Any:
    """JSON-safe copy: NaN and inf become None (null), numpy scalars plain numbers."""
    if isinstance(value, Mapping):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def group_summary(r: GroupResult, cfg: EvaluateParams) -> dict[str, Any]:
    """The numbers of the report's summary table for one group (also in metrics.json)."""
    g = r.inputs
    ratios = r.ratios()
    meets = {}
    for ref in REFERENCES:
        a, b = ratios["raw_over_nn7"][ref], ratios["nn7_over_oracle"][ref]
        meets[ref] = (
            None
            if a is None or b is None
            else bool(a >= cfg.target_raw_over_nn7 and b <= cfg.target_nn7_over_oracle)
        )
    rmse = {
        ref: {m: r.headline_rmse(ref, m) for m in g.models}
        for ref in REFERENCES
        if ref in r.tables[g.headline]
    }
    return {
        "headline": g.headline,
        "sensors": list(g.sensors),
        "samples_test": len(g.frame),
        "rmse": rmse,
        "best_on_validation": r.best_on_validation,
        "recommended": r.recommended,
        "raw_over_nn7": ratios["raw_over_nn7"],
        "nn7_over_oracle": ratios["nn7_over_oracle"],
        "meets_targets": meets,
        "noise_ratio": r.noise.ratio,
        "noise_flagged": r.noise.flagged,
        "quasi_static_s": r.noise.quasi_static_s,
    }


def metrics_document(results: Sequence[GroupResult], cfg: EvaluateParams) -> dict[str, Any]:
    """The content of reports/metrics.json (JSON-safe)."""
    doc: dict[str, Any] = {
        "flagged": [f"{r.group}/{m}" for r in results for m in r.noise.flagged],
        "noise_threshold": cfg.noise_threshold,
        "summary": {r.group: group_summary(r, cfg) for r in results},
        "noise": {},
        "tables": {},
        "by_experiment": {},
    }
    for r in results:
        n = r.noise
        doc["noise"][r.group] = {
            "quasi_static_s": n.quasi_static_s,
            "windows": n.windows,
            "signal_fraction": n.signal_fraction,
            "ratio": n.ratio,
            "ratio_rms": n.ratio_rms,
            "worst_channel": n.worst_channel,
            "per_channel": n.per_channel,
        }
        doc["tables"][r.group] = r.tables
        doc["by_experiment"][r.group] = r.by_experiment
    return _clean(doc)


def mlflow_metrics(doc: Mapping[str, Any]) -> dict[str, float]:
    """A selection of metrics.json for the MLflow run: summaries, noise ratios, and per sensor (or sum),
    reference and model the global/force/torque MSE, MAE and RMSE (the full tables are the artifact)."""
    out: dict[str, float] = {}

    def put(key: str, value: Any) -> None:
        if isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value):
            out[key.replace("@", "_")] = float(value)

    for group, s in doc["summary"].items():
        for key in ("raw_over_nn7", "nn7_over_oracle"):
            for ref, v in s[key].items():
                put(f"{group}.{key}.{ref}", v)
        for model, v in s["noise_ratio"].items():
            put(f"{group}.noise_ratio.{model}", v)
        put(f"{group}.quasi_static_s", s["quasi_static_s"])
    for group, names in doc["tables"].items():
        for name, refs in names.items():
            for ref, models in refs.items():
                for model, errors in models.items():
                    for key in ("rmse", "rmse_force", "rmse_torque", "mae", "mse"):
                        put(f"{group}.{name}.{ref}.{model}.{key}", errors.get(key))
    return out


# --- training history and MLflow links ------------------------------------------------------------


def _history_from_metrics(train: Mapping[str, Any], network: str) -> list[dict[str, float]] | None:
    history = (train.get("networks") or {}).get(network, {}).get("history")
    if not isinstance(history, list) or not history:
        return None
    try:
        return [
            {"epoch": float(h["epoch"]), "loss": float(h["loss"]), "val_rmse": float(h["val_rmse"])}
            for h in history
        ]
    except (KeyError, TypeError, ValueError):
        return None


def _same(a: Any, b: Any) -> bool:
    try:
        return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-12)
    except (TypeError, ValueError):
        return False


def find_histories(
    client: Any, experiment_ids: Sequence[str], group: str, train: Mapping[str, Any]
) -> dict[str, list[dict[str, float]]]:
    """Per-epoch training loss and validation RMSE of each network's best trial, from its nested MLflow run.

    The run is the trial run tagged with the group, network and trial number whose ``best_val_rmse``
    equals the network's ``val_rmse_labelled`` in metrics.json (a study resumed or rerun elsewhere has
    other runs with the same tags). Networks whose run is not found are left out.
    """
    out: dict[str, list[dict[str, float]]] = {}
    for network, info in (train.get("networks") or {}).items():
        trial = info.get("trial")
        filt = f"tags.group = '{group}' and tags.network = '{network}' and tags.trial = '{trial}'"
        runs = client.search_runs(
            experiment_ids, filt, order_by=["attributes.start_time DESC"], max_results=50
        )
        run = next(
            (r for r in runs if _same(r.data.metrics.get("best_val_rmse"), info.get("val_rmse_labelled"))),
            None,
        )
        if run is None:
            continue
        by_step: dict[int, dict[str, float]] = {}
        for key in ("loss", "val_rmse"):
            for m in client.get_metric_history(run.info.run_id, key):
                by_step.setdefault(int(m.step), {"epoch": float(m.step)})[key] = float(m.value)
        rows = [by_step[k] for k in sorted(by_step) if {"loss", "val_rmse"} <= set(by_step[k])]
        if rows:
            out[network] = rows
    return out


def find_train_run(
    client: Any, experiment_ids: Sequence[str], group: str, train: Mapping[str, Any]
) -> str | None:
    """The MLflow run of the training that wrote models/<group>: ``mlflow_run`` of metrics.json if present,
    else the latest ``train@<group>`` run whose logged test RMSE of every model equals metrics.json's."""
    if train.get("mlflow_run"):
        return str(train["mlflow_run"])
    test = train.get("test") or {}
    runs = client.search_runs(
        experiment_ids,
        f"tags.`dvc.stage` = 'train@{group}'",
        order_by=["attributes.start_time DESC"],
        max_results=100,
    )
    for run in runs:
        logged = run.data.metrics
        if test and all(_same(logged.get(f"test.{m}.rmse"), e.get("rmse")) for m, e in test.items()):
            return run.info.run_id
    return None


def _model_id(mv: Any) -> str:
    """The logged model (MLflow 3) behind a model version: its ``model_id``, or the id in its
    ``models:/<model_id>`` source (the sqlite store leaves the attribute empty)."""
    if getattr(mv, "model_id", None):
        return str(mv.model_id)
    source = str(mv.source or "")
    rest = source[len("models:/") :]
    return rest if source.startswith("models:/m-") and "/" not in rest else ""


def link_mlflow(results: Sequence[GroupResult], histories_needed: bool = True) -> None:
    """Fill each result's loss histories (if not in metrics.json), training run and model versions."""
    import mlflow

    from pipeline.core.tracking import EXPERIMENT

    client = mlflow.MlflowClient()
    experiment = client.get_experiment_by_name(EXPERIMENT)
    ids = [experiment.experiment_id] if experiment is not None else []
    for r in results:
        train = r.inputs.train
        histories = {}
        for network in train.get("networks") or {}:
            h = _history_from_metrics(train, network)
            if h is not None:
                histories[network] = h
        if histories:
            r.histories, r.history_source = histories, f"models/{r.group}/{TRAIN_METRICS}"
        elif ids and histories_needed:
            r.histories = find_histories(client, ids, r.group, train)
            r.history_source = "MLflow trial runs" if r.histories else "none"
        if not ids:
            continue
        r.train_run = find_train_run(client, ids, r.group, train)
        if r.train_run is None:
            continue
        for mv in client.search_model_versions(f"run_id = '{r.train_run}'"):
            network = next((n for n in (train.get("networks") or {}) if mv.name.endswith(f"-{n[2:]}")), None)
            if network is not None:
                r.model_versions[network] = {
                    "name": mv.name,
                    "version": str(mv.version),
                    "model_id": _model_id(mv),
                }


# --- the stage -----------------------------------------------------------------------------------


def _write_json(path: Path, obj: Any) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(json.dumps(obj, indent=1, sort_keys=False, allow_nan=False) + "\n", encoding="utf-8")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def group_names(params: Params) -> list[str]:
    """The sensor groups to evaluate: the keys of ``train.groups`` in params.yaml."""
    groups = (
        (params.raw.get("train") or {}).get("groups")
        if isinstance(params.raw.get("train"), Mapping)
        else None
    )
    if not isinstance(groups, Mapping) or not groups:
        raise ConfigError(
            f"{params.raw.get('__file__', 'params.yaml')}: train.groups must list the sensor groups"
        )
    return [str(k) for k in groups]


@dataclass
class EvaluateResult:
    results: list[GroupResult]
    metrics: dict[str, Any]
    files: list[str]
    seconds: float
    run_id: str | None = None


def run(
    params: Params,
    models_dir: str | Path,
    labelled_dir: str | Path,
    out_dir: str | Path,
    truth_dir: str | Path | None = None,
    *,
    progress: bool | None = None,
) -> EvaluateResult:
    """Evaluate every group of params into `out_dir` (module docstring) in one MLflow run ``evaluate``."""
    import mlflow

    from pipeline.core.tracking import stage_run
    from pipeline.evaluation import report

    t0 = time.perf_counter()
    cfg = stage_section(params, STAGE, EvaluateParams)
    models, labelled, out = Path(models_dir), Path(labelled_dir), Path(out_dir)
    truth = Path(truth_dir) if truth_dir is not None else None
    if not models.is_dir():
        raise DataError(f"{models}: models directory not found (run `dvc repro train`)")
    if not labelled.is_dir():
        raise DataError(f"{labelled}: labelled directory not found")
    if truth is not None and not truth.is_dir():
        raise DataError(f"{truth}: truth directory not found")
    groups = group_names(params)
    show = sys.stderr.isatty() if progress is None else progress

    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    console = Console(stderr=True)

    def progress_bar() -> Progress:
        return Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=console,
            transient=True,
            disable=not show,
        )

    results: list[GroupResult] = []
    with progress_bar() as bar:
        task = bar.add_task("evaluate: scoring groups", total=len(groups))
        for group in groups:
            bar.update(task, description=f"evaluate: scoring {group}")
            results.append(evaluate_group(load_group(group, models, labelled, truth, cfg), cfg))
            bar.advance(task)

    stage_params = {STAGE: asdict(cfg), "groups": ",".join(groups)}
    with stage_run(STAGE, stage_params) as active:
        link_mlflow(results)
        doc = metrics_document(results, cfg)
        out.mkdir(parents=True, exist_ok=True)
        with progress_bar() as bar:
            files = report.write_all(out, results, doc, cfg, bar)
        _write_json(out / METRICS_FILE, doc)
        files.append(METRICS_FILE)

        tags = {
            "groups": ",".join(groups),
            "models_dir": str(models),
            "flagged": ",".join(doc["flagged"]) or "none",
        }
        for r in results:
            tags[f"recommended.{r.group}"] = r.recommended or "none"
            if r.train_run:
                tags[f"train_run.{r.group}"] = r.train_run
            for network, mv in r.model_versions.items():
                tags[f"model.{r.group}.{network}"] = f"{mv['name']}/{mv['version']}"
        mlflow.set_tags(tags)
        mlflow.log_metrics(mlflow_metrics(doc))
        mlflow.log_metric("seconds", time.perf_counter() - t0)
        _log_model_metrics(results)
        mlflow.log_artifact(str(out / METRICS_FILE))
        mlflow.log_artifact(str(out / REPORT_FILE))
        mlflow.log_artifacts(str(out / PLOTS_DIR), PLOTS_DIR)
        run_id = active.info.run_id
    return EvaluateResult(results, doc, files, time.perf_counter() - t0, run_id)


def _log_model_metrics(results: Sequence[GroupResult]) -> None:
    """Log each evaluated network's test errors and noise ratio against its MLflow logged model (model_id),
    so that the model's page lists them with this run; and tag the model versions with this run."""
    import mlflow

    client = mlflow.MlflowClient()
    run_id = mlflow.active_run().info.run_id
    for r in results:
        for network, mv in r.model_versions.items():
            values = {
                "test_rmse_labels": r.headline_rmse(LABELS, network),
                "test_rmse_truth": r.headline_rmse(TRUTH, network),
                "noise_ratio": r.noise.ratio.get(network),
            }
            # keys unique in this run (which logs every group); the model's page lists them with the run
            values = {
                f"{r.group}.{network}.{k}": v for k, v in values.items() if v is not None and math.isfinite(v)
            }
            if mv.get("model_id") and values:
                mlflow.log_metrics(values, model_id=mv["model_id"])
            client.set_model_version_tag(mv["name"], mv["version"], "evaluate_run", run_id)
            client.set_model_version_tag(
                mv["name"], mv["version"], "noise_flagged", str(network in r.noise.flagged).lower()
            )


def _fmt(v: float | None, digits: int = 3) -> str:
    return "n/a" if v is None or not math.isfinite(v) else f"{v:.{digits}g}"


def _cmd(args: argparse.Namespace) -> int:
    params = load_params(args.params)
    result = run(params, args.models, args.labelled, args.out, args.truth)
    for r in result.results:
        s = result.metrics["summary"][r.group]
        ratios = r.ratios()
        flags = f"; noisy: {', '.join(r.noise.flagged)}" if r.noise.flagged else ""
        print(
            f"{r.group}: RMSE {s['headline']} raw {_fmt(r.headline_rmse(LABELS, RAW))}, "
            f"nn7 {_fmt(r.headline_rmse(LABELS, NN7))} (raw/nn7 {_fmt(ratios['raw_over_nn7'][LABELS])}, "
            f"nn7/oracle {_fmt(ratios['nn7_over_oracle'][LABELS])} vs labels); deploy {r.recommended}{flags}"
        )
    print(f"report: {Path(args.out) / REPORT_FILE} ({result.seconds:.0f} s)")
    return 0


def add_cli(subparsers: Any) -> None:
    """Add `ftcal evaluate MODELS LABELLED OUT [--truth DIR]`."""
    parser = subparsers.add_parser(
        STAGE,
        help="error tables, plots and noise check of every group's models",
        description=(__doc__ or "").split("\n\n")[0],
    )
    parser.add_argument(
        "models", type=Path, help="directory of the groups' model directories (models/<group>)"
    )
    parser.add_argument("labelled", type=Path, help="directory of labelled <log>.parquet tables")
    parser.add_argument(
        "out", type=Path, help="output directory of the report (index.html, metrics.json, plots)"
    )
    parser.add_argument(
        "--truth",
        type=Path,
        default=None,
        help="directory of simulated <log>.truth.parquet tables (optional): adds the errors against the "
        "true wrench and the oracle calibration",
    )
    parser.add_argument("--params", type=Path, default=None, help="params file (default: repo params.yaml)")
    parser.set_defaults(func=_cmd)
