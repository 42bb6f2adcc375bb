"""The three deployment tests of the thesis (chapter 6) on one deployment day's logs.

- Test A, standing still: output noise of every trained model against raw, high-pass std per axis on the
  quasi-static samples (`pipeline.evaluation.noise`); a model above ``EvaluateParams.noise_limit`` (worst
  axis: ``evaluate.noise_threshold`` widened by ``noise_margin``, as `evaluate` flags) is flagged.
- Test B, walking: thesis tables (MSE / MAE / RMSE, global and per axis) of the calibrated sensors and
  foot sums against the labels and, where simulated, the truth, beside raw.
- Test C, pushed on the pole: leg joint torques estimated from each leg sensor (`pipeline.physics.torques`)
  with raw and calibrated wrenches against the true joint torques; RMSE and max error per joint during
  the pushes.
Wrenches N / Nm in the sensor frame (foot sums in the sole frame), torques Nm.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.deploy.models import group_models
from pipeline.deploy.params import DeployParams
from pipeline.deploy.prepare import DeployLog
from pipeline.evaluation.noise import board_speed, highpass, noise_ratio, quasi_static_mask, segment_ids
from pipeline.evaluation.params import EvaluateParams
from pipeline.evaluation.results import score
from pipeline.logs import schema as S
from pipeline.physics.robot import RobotModel

RAW = "raw"  # the model name of the primary calibration (no secondary calibration)


def _wrench(df: pd.DataFrame, quantity: str, name: str) -> np.ndarray:
    return df[S.wrench_cols(quantity, name)].to_numpy(np.float64)


def _finite_segments(table: pd.DataFrame, sensors: list[str], stamps: np.ndarray) -> tuple[np.ndarray, float]:
    """(N,) stretch ids and the rate (Hz) for the high-pass filters: stretches of contiguous stamps that
    also end at every sample where an input of `sensors` (wrench, temperature, IMU) is not finite (the
    first samples before a stream's first message, lost messages), each such sample alone, so that one
    missing sample leaves out only itself and the filter edges beside it, not its whole stretch."""
    from pipeline.calib.data import input_cols

    cols = [c for s in sensors for c in input_cols(s, 13)]
    bad = ~np.isfinite(table[cols].to_numpy(np.float64)).all(axis=1)
    return segment_ids(2 * np.cumsum(bad) + bad, stamps)


def standing_noise(log: DeployLog, model_dir: Path, cfg: EvaluateParams, deployed: str) -> dict[str, Any]:
    """Test A on a standing-still log for the group trained into `model_dir`: noise ratio per axis and the
    verdict of each of its trained models (`deployed`: the exported one)."""
    table = pd.read_parquet(log.labelled)
    stamps = table[S.STAMP].to_numpy()
    sensors, predictors = group_models(model_dir)
    if deployed == RAW and RAW not in predictors:  # the factory calibration deployed: raw's own noise
        predictors[RAW] = lambda t: {s: _wrench(t, S.FT, s) for s in sensors}
    seg, fs = _finite_segments(table, sensors, stamps)
    gyro = [table[S.vector_cols(S.GYR, s)].to_numpy(np.float64) for s in sensors]
    speed = board_speed(gyro, seg, fs, cfg.highpass_hz, cfg.highpass_order)
    mask = quasi_static_mask(
        speed, table[S.CONTACTS].to_numpy(), table[S.GUARD].to_numpy(), seg, fs,
        cfg.still_gyro_rad_s, cfg.still_min_s, 1.0,
    )  # fmt: skip
    raw_hf = np.concatenate(
        [highpass(_wrench(table, S.FT, s), seg, fs, cfg.highpass_hz, cfg.highpass_order) for s in sensors], 1
    )
    rows = {}
    for name, predict in predictors.items():
        pred = predict(table)
        hf = np.concatenate(
            [highpass(pred[s], seg, fs, cfg.highpass_hz, cfg.highpass_order) for s in sensors], 1
        )
        ratio = noise_ratio(hf, raw_hf, mask)
        worst = float(np.nanmax(ratio)) if np.isfinite(ratio).any() else float("nan")
        rows[name] = {"ratio_axes": ratio.tolist(), "worst": worst, "flagged": bool(worst > cfg.noise_limit)}
    return {
        "sensors": sensors,
        "deployed": deployed,
        "quasi_static_s": float(mask.sum() / fs),
        "noise_limit": cfg.noise_limit,
        "models": rows,
    }


def _pair_sums(robot: RobotModel, params: Any, data: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    from pipeline.physics.feet import robot_pairs

    out = {}
    for pair in robot_pairs(robot, params.robot.foot_pairs):
        if pair.front in data and pair.rear in data:
            out[pair.name] = data[pair.front] @ pair.sole_X_front.T + data[pair.rear] @ pair.sole_X_rear.T
    return out


def walking_errors(
    log: DeployLog,
    robot: RobotModel,
    params: Any,
    calibrated: dict[str, np.ndarray],
    fallback: dict[str, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Test B on a walking log: per calibrated sensor and foot sum, scores of raw and calibrated against the
    labels (where exact) and the truth; with `fallback` (sensor -> (N, 6): the affine map wholeBodyDynamics
    would run, `pipeline.export.wbd`), its scores too, under ``fallback``."""
    table = pd.read_parquet(log.labelled)
    truth = pd.read_parquet(log.truth) if log.truth is not None else None
    raw = {s: _wrench(table, S.FT, s) for s in calibrated}
    true = {s: _wrench(truth, S.TRUE, s) for s in calibrated} if truth is not None else {}
    linear = {s: w for s, w in (fallback or {}).items() if s in calibrated}
    names = {s: (raw[s], calibrated[s], linear.get(s)) for s in calibrated}
    raw_sums, cal_sums = _pair_sums(robot, params, raw), _pair_sums(robot, params, calibrated)
    linear_sums = _pair_sums(robot, params, linear) if len(linear) == len(calibrated) else {}
    true_sums = _pair_sums(robot, params, true) if true else {}
    names.update({p: (raw_sums[p], cal_sums[p], linear_sums.get(p)) for p in cal_sums})
    true.update(true_sums)
    out: dict[str, Any] = {}
    for name, (r, c, f) in names.items():
        label = _wrench(table, S.EXPECTED, name)
        switch = table[S.switch_col(name)].to_numpy(bool)
        entry: dict[str, Any] = {
            "labels": {"raw": score(r, label, switch), "calibrated": score(c, label, switch)}
        }
        if name in true:
            entry["truth"] = {"raw": score(r, true[name]), "calibrated": score(c, true[name])}
            entry["ratio_truth"] = entry["truth"]["raw"]["rmse"] / entry["truth"]["calibrated"]["rmse"]
        if f is not None:
            entry["fallback"] = {"labels": score(f, label, switch)}
            if name in true:
                entry["fallback"]["truth"] = score(f, true[name])
        out[name] = entry
    return out


def read_true_torques(log: DeployLog, topic: str, stamps: np.ndarray, joints: list[str]) -> np.ndarray | None:
    """(N, len(joints)) true joint torques of a simulated pushed log at `stamps` (NaN where missing)."""
    from pipeline.logs.rosmsg import LogReader, concat_batches

    with LogReader(log.source) as reader:
        batches = reader.read([topic]).get(topic, [])
    if not batches:
        return None
    data = concat_batches(batches)
    names = list(batches[0].names or ())
    out = np.full((len(stamps), len(joints)), np.nan)
    pos = np.searchsorted(data["stamp_ns"], stamps)
    pos = np.clip(pos, 0, len(data["stamp_ns"]) - 1)
    hit = data["stamp_ns"][pos] == stamps
    for c, j in enumerate(joints):
        out[hit, c] = data["effort"][pos[hit], names.index(j)]
    return out


def push_torques(
    log: DeployLog, robot: RobotModel, params: Any, dp: DeployParams, calibrated: dict[str, np.ndarray]
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Test C on a pushed pole log: per leg joint, RMSE and max error of the torque from the raw and from
    the calibrated leg sensor against the truth during the pushes. Returns (results, series for figures)."""
    from pipeline.labels.table import experiment_gravity
    from pipeline.physics.torques import limb_joints, sensor_joint_torques
    from pipeline.sim.push import push_profile

    table = pd.read_parquet(log.labelled)
    smooth = pd.read_parquet(log.smoothed, columns=[S.STAMP, *(
        c for k in (S.QS, S.DQS, S.DDQS) for c in S.joint_cols(k, robot.joint_names))])  # fmt: skip
    q, dq, ddq = (smooth[S.joint_cols(k, robot.joint_names)].to_numpy() for k in (S.QS, S.DQS, S.DDQS))
    time_s = table[S.TIME].to_numpy()
    gravity = experiment_gravity(log.labelled, log.experiment, params.robot.gravity)
    fixed = str(table[S.FIXED_LINK].iloc[0])
    _, who = push_profile(time_s, dp.push, len(dp.torque_limbs))
    pushed = who >= 0
    results, series = {}, {"time_s": time_s, "pushed": pushed}
    for sensor, end in dp.torque_limbs.items():
        if sensor not in calibrated:
            continue
        joints = limb_joints(robot, end)
        true = read_true_torques(log, params.topics.sim_joint_torques, table[S.STAMP].to_numpy(), joints)
        if true is None:
            continue
        readings = np.stack([_wrench(table, S.FT, sensor), calibrated[sensor]])
        both = sensor_joint_torques(robot, sensor, joints, q, dq, ddq, readings, fixed, gravity)
        est = {"raw": both[0], "calibrated": both[1]}
        ok = (
            pushed
            & np.isfinite(true).all(1)
            & np.isfinite(est["raw"]).all(1)
            & np.isfinite(est["calibrated"]).all(1)
        )
        per_joint = {}
        for c, j in enumerate(joints):
            per_joint[j] = {
                kind: {
                    "rmse": float(np.sqrt(np.mean((e[ok, c] - true[ok, c]) ** 2))),
                    "max": float(np.max(np.abs(e[ok, c] - true[ok, c]))),
                }
                for kind, e in est.items()
            }
            for stat in ("rmse", "max"):
                per_joint[j][f"ratio_{stat}"] = per_joint[j]["raw"][stat] / max(
                    per_joint[j]["calibrated"][stat], 1e-12
                )
        results[sensor] = {"joints": per_joint, "samples_pushed": int(ok.sum())}
        series[sensor] = {"joints": joints, "true": true, **est}
    return results, series
