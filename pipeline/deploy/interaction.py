"""Test D, interaction fidelity: does the deployed calibration report what the robot meets?

On the interaction log of a simulated deployment day (`pipeline.sim.push`: the robot on the pole, every FT
sensor's site pushed in several directions with 10-40 N, then a load carried in each hand), the truth holds
``external.<sensor>``: the part of each sensor's true wrench due to those pushes and loads. A calibration
that reads a sensor faithfully reports that change; one that rebuilt forces from torque channels or the IMU
on its training relation does not.

Per sensor with pushes on its free side, per model (raw, the deployed calibration, the oracle), over the
samples of its push windows (contiguous runs where its external wrench is not zero):

- the *reported change* ``c = model - (true - external)``, minus its mean over `MARGIN_S` before and after
  the window (the model's own slowly varying error, the offsets for raw);
- per axis, the slope ``sum(c_a e_a) / sum(e_a^2)`` of the reported change against the true one, e the
  external wrench (None where an axis moved less than `MIN_SHARE` of the sensor's most moved axis);
- the force error during the pushes, ``model - true`` (RMSE and max over the force axes, not
  baseline-corrected: what the robot would read).

- the error of the reported change against the true one (``rmse_change_force``, force axes).

The same for the carried loads (their windows apart). A sensor passes as `judge` says: slopes as close to
the truth's as the oracle's within ``deploy.slope_tolerance``, the change's error at most
``deploy.push_rmse_target`` times the oracle's. Wrenches N and Nm in the sensor frame.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from pipeline.logs import schema as S

MARGIN_S = 0.25  # s before and after a window whose mean reported change is its baseline
MIN_SHARE = 0.05  # an axis whose external wrench (RMS, in units of its noise) is below this share of the
# sensor's largest gets no slope: too little change to measure one
NOISE_UNITS = np.array([0.6, 0.6, 0.6, 0.03, 0.03, 0.03])  # N, Nm: comparable axes when choosing them
ON_N = 1e-6  # |external| above this (N or Nm) marks a sample as pushed
MODELS = ("raw", "calibrated", "oracle")


def _windows(active: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) of the runs of True in `active`."""
    edges = np.flatnonzero(np.diff(np.r_[0, active.astype(np.int8), 0]))
    return list(zip(edges[::2], edges[1::2], strict=True))


def _reported_change(
    err: np.ndarray, windows: list[tuple[int, int]], time_s: np.ndarray, quiet: np.ndarray
) -> np.ndarray:
    """(N, 6) `err` minus, inside each window, its mean over the quiet samples within MARGIN_S of it;
    NaN outside the windows."""
    out = np.full_like(err, np.nan)
    for a, b in windows:
        near = quiet & (time_s >= time_s[a] - MARGIN_S) & (time_s <= time_s[b - 1] + MARGIN_S)
        near[a:b] = False
        base = np.nanmean(err[near], axis=0) if near.any() else np.zeros(err.shape[1])
        out[a:b] = err[a:b] - base
    return out


def fidelity(
    time_s: np.ndarray,
    true: np.ndarray,
    external: np.ndarray,
    outputs: Mapping[str, np.ndarray],
    load: np.ndarray,
) -> dict[str, Any] | None:
    """Test D of one sensor: `true`, `external` (N, 6) truth; `outputs` model -> (N, 6); `load` (N,) bool, the
    samples of carried loads. None when nothing pushed the sensor."""
    active = np.isfinite(external).all(axis=1) & (np.abs(np.nan_to_num(external)).max(axis=1) > ON_N)
    quiet = np.isfinite(external).all(axis=1) & ~active
    out: dict[str, Any] = {}
    for kind, mask in (("pushes", active & ~load), ("loads", active & load)):
        windows = _windows(mask)
        if not windows:
            continue
        inside = np.zeros(len(mask), dtype=bool)
        for a, b in windows:
            inside[a:b] = True
        e = external[inside]
        scale = np.sqrt(np.mean(e**2, axis=0)) / NOISE_UNITS
        keep = scale >= MIN_SHARE * scale.max()
        entry: dict[str, Any] = {
            "windows": len(windows),
            "samples": int(inside.sum()),
            "peak_force_n": float(np.max(np.linalg.norm(e[:, :3], axis=1))),
        }
        for model, pred in outputs.items():
            err = pred - (true - external)
            change = _reported_change(err, windows, time_s, quiet)[inside]
            ok = np.isfinite(change).all(axis=1)
            slopes = [
                float(np.sum(change[ok, a] * e[ok, a]) / np.sum(e[ok, a] ** 2)) if keep[a] else None
                for a in range(6)
            ]
            force_err = (pred - true)[inside][:, :3]
            force_err = force_err[np.isfinite(force_err).all(axis=1)]
            change_err = (change[ok] - e[ok])[:, :3]
            entry[model] = {
                "slopes": slopes,
                "rmse_force": float(np.sqrt(np.mean(force_err**2))) if len(force_err) else None,
                "max_force": float(np.max(np.abs(force_err))) if len(force_err) else None,
                "rmse_change_force": float(np.sqrt(np.mean(change_err**2))) if len(change_err) else None,
            }
        out[kind] = entry
    return out or None


def judge(entry: Mapping[str, Any], tolerance: float, rmse_target: float) -> dict[str, Any]:
    """The verdict of one sensor's pushes, beside the oracle.

    Slopes: on every measured axis the deployed model's error ``|s - 1|`` (the truth's slope is 1) is at
    most the oracle's plus `tolerance`. The oracle inverts the static distortion only: its slopes carry the
    sensor's hysteresis (1.0-1.2 under pushes of 10-40 N), which a calibration fitted on moving data
    partly absorbs; ``slope_gap`` (``|s - s_oracle| / s_oracle``, worst axis) is reported beside it.
    Error: the RMSE of the reported change against the true one during the pushes (force axes) is at most
    `rmse_target` times the oracle's; the RMSE of the reading itself (``rmse_ratio``, which also holds the
    day's offset drift, known to the oracle only) is reported beside it.
    """
    pushes = entry.get("pushes")
    if not pushes:
        return {"pass": True, "worst_slope_excess": None, "slope_gap": None, "change_ratio": None}
    pairs = [
        (c, o)
        for c, o in zip(pushes["calibrated"]["slopes"], pushes["oracle"]["slopes"], strict=True)
        if c is not None and o is not None and o != 0
    ]
    excess = max((abs(c - 1) - abs(o - 1) for c, o in pairs), default=None)
    gap = max((abs(c - o) / abs(o) for c, o in pairs), default=None)

    def ratio(key: str) -> float | None:
        model, oracle = pushes["calibrated"][key], pushes["oracle"][key]
        return model / oracle if model is not None and oracle is not None and oracle > 1e-9 else None

    change, reading = ratio("rmse_change_force"), ratio("rmse_force")
    ok = (excess is None or excess <= tolerance) and (change is None or change <= rmse_target)
    return {
        "pass": bool(ok),
        "worst_slope_excess": excess,
        "slope_gap": gap,
        "change_ratio": change,
        "rmse_ratio": reading,
    }


def load_mask(time_s: np.ndarray, robot: Any, params: Any, dp: Any) -> np.ndarray:
    """(N,) the samples of the interaction log's carried loads (their schedule, as the simulator's)."""
    from pipeline.physics.feet import robot_feet
    from pipeline.sim.push import LOAD, interaction_events
    from pipeline.sim.sites import interaction_sites

    soles = {s: foot.sole for foot in robot_feet(robot, params.robot.foot_pairs) for s in foot.sensors}
    events = interaction_events(interaction_sites(robot, soles, dp.interaction.sites), dp.interaction)
    out = np.zeros(len(time_s), dtype=bool)
    for e in events:
        if e.kind == LOAD:
            out |= (time_s >= e.start_s) & (time_s <= e.end_s)
    return out


def interaction_test(
    table: Any, truth: Any, calibrated: Mapping[str, np.ndarray], load_mask: np.ndarray, dp: Any
) -> dict[str, Any]:
    """Test D on one interaction log: per calibrated sensor pushed in it, `fidelity` and `judge`.

    table: the labelled table (raw wrenches, time); truth: its truth table (same rows: true, oracle,
    external); calibrated: sensor -> (N, 6) deployed outputs; load_mask: (N,) samples of carried loads.
    """
    time_s = table[S.TIME].to_numpy(np.float64)
    out: dict[str, Any] = {}
    for sensor, cal in calibrated.items():
        cols = S.wrench_cols(S.EXTERNAL, sensor)
        if cols[0] not in truth:
            continue
        outputs = {
            "raw": table[S.wrench_cols(S.FT, sensor)].to_numpy(np.float64),
            "calibrated": np.asarray(cal, dtype=np.float64),
            "oracle": truth[S.wrench_cols(S.ORACLE, sensor)].to_numpy(np.float64),
        }
        true = truth[S.wrench_cols(S.TRUE, sensor)].to_numpy(np.float64)
        entry = fidelity(time_s, true, truth[cols].to_numpy(np.float64), outputs, load_mask)
        if entry is None:
            continue
        entry["verdict"] = judge(entry, dp.slope_tolerance, dp.push_rmse_target)
        out[sensor] = entry
    return out


def outside_during(
    result: dict[str, Any],
    excitation: Mapping[str, Any] | None,
    truth: Any,
    calibrated: Mapping[str, np.ndarray],
) -> None:
    """Add to each sensor's entry of `result` how far the deployed output lies outside its training
    `excitation` (`pipeline.calib.excitation`, as in models/<group>/metrics.json), during the pushes and
    loads and on the rest of the log; nothing where train recorded no excitation."""
    from pipeline.evaluation.fidelity import outside_stats

    for sensor, entry in result.items():
        if not excitation or sensor not in excitation or sensor not in calibrated:
            continue
        external = truth[S.wrench_cols(S.EXTERNAL, sensor)].to_numpy(np.float64)
        pushed = np.abs(np.nan_to_num(external)).max(axis=1) > ON_N
        w = np.asarray(calibrated[sensor], dtype=np.float64)
        entry["outside"] = {
            part: outside_stats({sensor: excitation[sensor]}, {sensor: w[mask]}).get(sensor)
            for part, mask in (("pushed", pushed), ("rest", ~pushed))
        }


def plot_interaction(table: Any, truth: Any, calibrated: Mapping[str, np.ndarray], path: Any) -> bool:
    """Per sensor pushed: the reported change of each force axis against the true one during the pushes,
    raw, deployed and oracle (one dot per sample, a tenth of them), the identity dashed. False if none."""
    from pipeline.evaluation.figures import pyplot, save_figure

    time_s = table[S.TIME].to_numpy(np.float64)
    shown = [s for s in calibrated if S.wrench_cols(S.EXTERNAL, s)[0] in truth]
    panels = []
    for sensor in shown:
        external = truth[S.wrench_cols(S.EXTERNAL, sensor)].to_numpy(np.float64)
        true = truth[S.wrench_cols(S.TRUE, sensor)].to_numpy(np.float64)
        active = np.isfinite(external).all(axis=1) & (np.abs(np.nan_to_num(external)).max(axis=1) > ON_N)
        if active.any():
            panels.append((sensor, external, true, active))
    if not panels:
        return False
    plt = pyplot()
    cols = min(4, len(panels))
    rows = -(-len(panels) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 3.2 * rows), squeeze=False)
    quiet_all = {}
    for ax, (sensor, external, true, active) in zip(axes.flat, panels, strict=False):
        quiet_all[sensor] = np.isfinite(external).all(axis=1) & ~active
        windows = _windows(active)
        outputs = {
            "raw": (table[S.wrench_cols(S.FT, sensor)].to_numpy(np.float64), "tab:red"),
            "deployed": (np.asarray(calibrated[sensor], dtype=np.float64), "tab:blue"),
            "oracle": (truth[S.wrench_cols(S.ORACLE, sensor)].to_numpy(np.float64), "tab:green"),
        }
        lim = float(np.abs(external[active, :3]).max())
        for name, (pred, color) in outputs.items():
            change = _reported_change(pred - (true - external), windows, time_s, quiet_all[sensor])
            pick = np.flatnonzero(active)[::10]
            ax.scatter(external[pick, :3].ravel(), change[pick, :3].ravel(), s=2, color=color, label=name)
        ax.plot([-lim, lim], [-lim, lim], ls="--", color="k", lw=0.8)
        ax.set_title(sensor, fontsize=9)
        ax.set_xlabel("true change (N)", fontsize=8)
        ax.set_ylabel("reported change (N)", fontsize=8)
    for ax in list(axes.flat)[len(panels) :]:
        ax.axis("off")
    axes[0, 0].legend(fontsize=7, markerscale=4)
    fig.tight_layout()
    save_figure(fig, path)
    return True
