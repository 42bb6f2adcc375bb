"""Where a recorded run's held-out error comes from, and what its data can decide.

On a recording there is no truth: a model is scored against the labels of held-out segments, and its
residual (prediction - label, N and Nm, sensor frame) mixes the sensor's reading, the labels' own errors
(the URDF's masses and frames, the encoders' derivatives) and what the training segments did not show. Per
sensor with labels and per model shown (the deployed one, the affine map, the plain least squares), the
residual's mean square per axis is split, in this order, into what each of these explains (least squares on
the held-out samples themselves, so each share is an upper bound of what that cause can carry):

- ``offset``: a constant per held-out segment (the reading's offset drifting between segments);
- ``time``: a slope in time within each segment (drift while recording);
- ``pose``: linear in the positions of the joints that move (a frame, a mass or a centre of mass of the
  URDF: a label's error that follows the pose);
- ``speed``: linear in their velocities and |velocities| (inertial terms, hysteresis, the encoders'
  derivatives);
- ``rest``: what none of these explains (noise, and everything else).

Beside it, what the data excite: the training labels' directions (`pipeline.calib.excitation`, in noise
units) and the gain each map gives along them against the factory's 1, and per axis the plain least
squares' slope to a push on that axis: a map that reads a push on an axis at a fraction of its size is not
a faithful calibration, whatever its error on the training relation (`why_not_lower`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow.parquet as pq

from pipeline.calib.excitation import OUTSIDE, WEAK, Excitation
from pipeline.calib.linear import LinearBaseline
from pipeline.calib.params import LS_AFFINE
from pipeline.calib.registry import AFFINE, RAW, complexity, has_memory
from pipeline.logs import schema as S

AXES = S.WRENCH_AXES
CAUSES = ("offset", "time", "pose", "speed", "rest")
MOVING_RAD = np.radians(0.5)  # a joint moves in the held-out segments if its position spans more than this
START_S = 2.0  # a segment's first seconds: where a model with memory starts without its past
FAITHFUL = 0.15  # a map's slope to a push on an axis within this of 1 is faithful there
SAME = 0.02  # two held-out errors closer than this fraction are the same


def _explained(r: np.ndarray, features: np.ndarray, groups: np.ndarray | None = None) -> np.ndarray:
    """(M, 6) the part of residuals r (M, 6) that features (M, F) explain by least squares, fitted per
    group (one id per sample) where `groups` is given."""
    out = np.zeros_like(r)
    ids = np.zeros(len(r), dtype=np.int64) if groups is None else groups
    for g in np.unique(ids):
        m = ids == g
        f = features[m]
        if f.shape[1] == 0 or m.sum() <= f.shape[1]:
            continue
        coef = np.linalg.lstsq(f, r[m], rcond=None)[0]
        out[m] = f @ coef
    return out


def decompose(
    residual: np.ndarray, segment: np.ndarray, time: np.ndarray, q: np.ndarray, dq: np.ndarray
) -> dict[str, list[float]]:
    """cause -> (6,) share of each axis's mean square residual (module docstring), summing to 1.

    residual (M, 6) N / Nm; segment (M,) ids; time (M,) s; q, dq (M, J) the moving joints' positions (rad)
    and velocities (rad/s)."""
    total = np.mean(residual**2, axis=0)
    r = residual.copy()
    parts = {}
    ones = np.ones((len(r), 1))
    ids, at = np.unique(segment, return_inverse=True)
    means = np.array([time[segment == k].mean() for k in ids]) if len(r) else np.zeros(0)
    centred = time - means[at] if len(r) else time
    steps = [
        ("offset", ones, segment),
        ("time", centred[:, None], segment),
        ("pose", q - q.mean(axis=0) if q.size else q, None),
        ("speed", np.c_[dq, np.abs(dq)] - np.c_[dq, np.abs(dq)].mean(axis=0) if dq.size else dq, None),
    ]
    for name, features, groups in steps:
        part = _explained(r, features, groups)
        parts[name] = np.mean(part**2, axis=0)
        r = r - part
    parts["rest"] = np.mean(r**2, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return {k: np.where(total > 0, v / total, np.nan).tolist() for k, v in parts.items()}


def gains(model: LinearBaseline, s: int) -> np.ndarray:
    """(6, 6) the map's slope d(output)/d(raw wrench) of sensor s: identity plus its linear correction
    (the factory's map is the identity)."""
    weight, _ = model.affine_map(s)
    return np.eye(6) + weight[:, :6]


def excited_gains(excitation: Mapping[str, Any], maps: Mapping[str, np.ndarray]) -> list[dict[str, Any]]:
    """Per excited training direction (labels' std above `WEAK` noise stds): its std (noise units), its
    largest axes, and each map's gain along it (the factory's: 1)."""
    noise = np.asarray(excitation["noise"], dtype=np.float64)
    out = []
    for u, std in zip(excitation["directions"], excitation["std"], strict=True):
        if std < WEAK:
            continue
        u = np.asarray(u, dtype=np.float64)
        d = noise * u  # the direction in N and Nm
        top = np.argsort(-np.abs(u))[:2]
        entry = {"std_noise": float(std), "axes": [f"{u[a]:+.2f} {AXES[a]}" for a in top], "gain": {}}
        for name, g in maps.items():
            entry["gain"][name] = float(d @ (g @ d) / (d @ d))
        out.append(entry)
    return out


def why_not_lower(
    ls_gain: np.ndarray,
    excitation: Mapping[str, Any],
    deployed: float,
    plain: float,
    excited: Sequence[Mapping[str, Any]] = (),
    passed_over: Mapping[str, str] | None = None,
) -> str | None:
    """Why a faithful map may not reach the plain least squares' held-out error `plain` where the deployed
    model's is `deployed`, from what was measured: the excited directions along which the affine map's gain
    (`excited_gains`) departs from the factory's 1 by more than `FAITHFUL` (the labels contradict the
    factory's gain there), the axes on which least squares answers a push off its size (with how much the
    training labels move there, noise stds), and the models passed over as unfaithful; None where the
    deployed model is not worse."""
    if not deployed > plain * (1 + SAME):
        return None
    directions = np.asarray(excitation.get("directions") or np.eye(6), dtype=np.float64)
    std = np.asarray(excitation.get("std") or np.zeros(6), dtype=np.float64)
    labels_std = np.sqrt(((directions * std[:, None]) ** 2).sum(axis=0))  # per axis, noise units
    reasons = []
    contradicted = [d for d in excited if abs(d["gain"].get(AFFINE, 1.0) - 1) > FAITHFUL]
    if contradicted:
        text = "; ".join(
            f"along {', '.join(d['axes'])} (the labels move {d['std_noise']:.3g} noise stds) "
            + ", ".join(f"{m} {g:.2f}" for m, g in d["gain"].items())
            for d in contradicted
        )
        reasons.append(
            f"the labels contradict the factory's gain of 1: {text} (a frame or the masses of the URDF, or "
            "the sensor itself)"
        )
    off = [a for a in range(6) if abs(ls_gain[a, a] - 1) > FAITHFUL]
    if off:
        axes = ", ".join(
            f"{AXES[a]} at {ls_gain[a, a]:.2f} (its labels move {labels_std[a]:.3g} noise stds)" for a in off
        )
        reasons.append(
            f"{LS_AFFINE} reads a push on {axes}: it rebuilds those axes from the others along the training "
            "motion's relation, which lowers its error there and misreports anything off it"
        )
    if passed_over:
        reasons.append(
            "passed over as unfaithful to a push: "
            + "; ".join(f"{m} ({why})" for m, why in passed_over.items())
        )
    if not reasons:
        return (
            f"no measured reason: {LS_AFFINE} answers a push on every axis within {FAITHFUL:g} of its size, "
            f"so a faithful map could reach its {plain:.3g} where the deployed model leaves {deployed:.3g}"
        )
    return f"{LS_AFFINE} {plain:.3g}, deployed {deployed:.3g}: " + "; ".join(reasons)


def worse_than_affine(
    errors: Mapping[str, float],
    per_axis: Mapping[str, np.ndarray],
    cv: Mapping[str, Any] | None,
    starts: Mapping[str, tuple[float, float]],
    outside_share: float | None,
) -> dict[str, str]:
    """model -> the measured cause, for each model whose pooled held-out error exceeds the affine map's by
    more than `SAME` (closer is the same error).

    errors: model -> pooled RMSE; per_axis: model -> (6,) RMSE; cv: train's cross-validation (mean,
    spread); starts: model -> (RMSE in the segments' first `START_S` s, after); outside_share: the share of
    held-out samples off the training span (`pipeline.calib.excitation.OUTSIDE`)."""
    base = errors.get(AFFINE)
    if base is None or not np.isfinite(base):
        return {}
    means, spread = dict((cv or {}).get("mean") or {}), dict((cv or {}).get("spread") or {})
    out = {}
    for model, err in errors.items():
        if model in (RAW, AFFINE, LS_AFFINE) or not err > base * (1 + SAME):
            continue
        worst = int(np.argmax(per_axis[model] - per_axis[AFFINE]))
        axis = f"{AXES[worst]} {per_axis[model][worst]:.3g} against {per_axis[AFFINE][worst]:.3g}"
        why = []
        if complexity(model) < complexity(AFFINE):  # the offset: the factory's gains kept
            why.append("it keeps the factory's gains, which the affine map corrects on these data")
        margin = spread.get(model, 0.0)
        if err - base <= margin:
            why.append(f"within the spread of its validation folds ({margin:.2g})")
        if has_memory(model) and model in starts and starts[model][0] > 1.5 * starts[model][1]:
            first, after = starts[model]
            why.append(
                f"its memory starts without the sensor's past: {first:.3g} in each segment's first "
                f"{START_S:g} s against {after:.3g} after"
            )
        if outside_share is not None and outside_share > 0.05 and complexity(model) > complexity(AFFINE):
            why.append(
                f"{outside_share:.0%} of the held-out samples lie off the training span (farther than "
                f"{OUTSIDE:g} noise stds along its weak directions), where its terms beyond the affine "
                "extrapolate"
            )
        if model in means and AFFINE in means and means[model] < means[AFFINE] * (1 - SAME):
            why.append(
                f"validation ranked it {means[model]:.3g} against the affine's {means[AFFINE]:.3g}: the "
                "held-out segments move unlike the training ones"
            )
        out[model] = f"{err:.3g} against the affine's {base:.3g} (worst {axis}): " + "; ".join(
            why or ["it fits the training segments' motion, not the sensor"]
        )
    return out


def _model_errors(
    sub: pd.DataFrame,
    name: str,
    label: np.ndarray,
    seg: np.ndarray,
    t: np.ndarray,
    q: np.ndarray,
    dq: np.ndarray,
    models: Sequence[str],
    shown: Sequence[str],
) -> tuple[dict[str, float], dict[str, np.ndarray], dict[str, tuple[float, float]], dict[str, Any]]:
    """Per model on the labelled held-out samples `sub` of `name`: pooled RMSE, RMSE per axis (6,), RMSE
    in the segments' first `START_S` s and after, and for the models `shown` their `decompose`."""
    errors, per_axis, starts, scored = {}, {}, {}, {}
    early = np.zeros(len(t), dtype=bool)
    for k in np.unique(seg):
        m = seg == k
        early[m] = t[m] < t[m].min() + START_S
    for model in models:
        r = sub[S.prediction_cols(model, name)].to_numpy(np.float64) - label
        per_axis[model] = np.sqrt(np.mean(r**2, axis=0))
        errors[model] = float(np.sqrt(np.mean(r**2)))
        if early.any() and (~early).any():
            starts[model] = (float(np.sqrt(np.mean(r[early] ** 2))), float(np.sqrt(np.mean(r[~early] ** 2))))
        if model in shown:
            scored[model] = {
                "rmse": per_axis[model].tolist(),
                "pooled": errors[model],
                "shares": decompose(r, seg, t, q, dq),
            }
    return errors, per_axis, starts, scored


def held_out(
    frame: pd.DataFrame,
    joints: pd.DataFrame,
    names: Sequence[str],
    models: Sequence[str],
    recommended: str | None,
    train: Mapping[str, Any],
    baselines: Mapping[str, LinearBaseline],
    sensors: Sequence[str],
    unfaithful: Mapping[str, str] | None = None,
    inertial: Mapping[str, Mapping[str, Sequence[float]]] | None = None,
) -> dict[str, Any]:
    """name -> the held-out analysis of a recorded group (module docstring) for each sensor name with
    labels: per model shown the RMSE per axis and the shares of `decompose`; the excited directions and the
    maps' gains; `why_not_lower` and `worse_than_affine`.

    frame: the group's test samples (`pipeline.evaluation.inputs.GroupInputs.frame`); joints: per sample
    (same rows) ``qs.<joint>``, ``dqs.<joint>``; baselines: train's linear maps by name; unfaithful: the
    models passed over as unfaithful to a push, and why (`pipeline.evaluation.fidelity.unfaithful`);
    inertial: log -> sensor -> (6,) the RMS of its labels' inertial part (`read_inertial`)."""
    out: dict[str, Any] = {}
    excitation = dict(train.get("excitation") or {})
    shown = [m for m in dict.fromkeys([recommended, AFFINE, LS_AFFINE]) if m in models]
    for name in names:
        if name not in sensors:
            continue
        s = list(sensors).index(name)
        on = frame[S.switch_col(name)].to_numpy() == 1
        if on.sum() < 20:
            continue
        sub, jt = frame[on], joints[on]
        label = sub[S.wrench_cols(S.EXPECTED, name)].to_numpy(np.float64)
        seg = pd.factorize(sub["log"])[0]
        t = sub[S.TIME].to_numpy(np.float64)
        qcols = [c for c in jt.columns if c.startswith(f"{S.QS}.")]
        moving = [c for c in qcols if np.ptp(jt[c].to_numpy()) > MOVING_RAD]
        q = jt[moving].to_numpy(np.float64)
        dq = jt[[c.replace(f"{S.QS}.", f"{S.DQS}.", 1) for c in moving]].to_numpy(np.float64)
        errors, per_axis, starts, scored = _model_errors(sub, name, label, seg, t, q, dq, models, shown)
        entry: dict[str, Any] = {"models": scored, "moving_joints": [c[3:] for c in moving]}
        entry["label_noise"] = {log: v[name] for log, v in (inertial or {}).items() if name in v}
        maps = {m: gains(baselines[m], s) for m in (AFFINE, LS_AFFINE) if m in baselines}
        exc = excitation.get(name)
        if exc:
            entry["excited"] = excited_gains(exc, maps)
            entry["raw_noise"] = list(exc["noise"])
        if LS_AFFINE in maps and recommended in errors and LS_AFFINE in errors:
            entry["ls_push_slopes"] = np.diag(maps[LS_AFFINE]).tolist()
            ranked = [m for m in models if m not in (RAW, LS_AFFINE) and m in errors]
            lower = {
                m: why
                for m, why in (unfaithful or {}).items()
                if m in ranked and errors[m] < errors[recommended] * (1 - SAME)
            }
            entry["why_not_lower"] = why_not_lower(
                maps[LS_AFFINE],
                exc or {},
                errors[recommended],
                errors[LS_AFFINE],
                entry.get("excited", []),
                lower,
            )
        share = None
        if exc and AFFINE in models:
            calibrated = sub[S.prediction_cols(AFFINE, name)].to_numpy(np.float64)
            share = float(np.mean(Excitation.from_dict(dict(exc)).outside(calibrated) > OUTSIDE))
            entry["outside_share"] = share
        entry["worse_than_affine"] = worse_than_affine(errors, per_axis, train.get("cv"), starts, share)
        out[name] = entry
    return out


def read_joints(frame: pd.DataFrame, smoothed: Path | None) -> pd.DataFrame:
    """Per row of `frame` (columns ``log``, ``stamp_ns``) the smoothed joint positions and velocities of
    its smoothed table (``qs.<joint>``, ``dqs.<joint>``), in frame's order; no column where a table is
    absent (or `smoothed` is None)."""
    parts = []
    for log, rows in frame.groupby("log", sort=False):
        path = None if smoothed is None else smoothed / f"{log}{S.PARQUET_SUFFIX}"
        if path is None or not path.is_file():
            parts.append(pd.DataFrame(index=rows.index))
            continue
        names = pq.read_schema(path).names
        cols = [c for c in names if c.startswith((f"{S.QS}.", f"{S.DQS}."))]
        table = pq.read_table(path, columns=[S.STAMP, *cols]).to_pandas()
        joined = rows[[S.STAMP]].merge(table, on=S.STAMP, how="left", validate="many_to_one")
        joined.index = rows.index
        parts.append(joined.drop(columns=[S.STAMP]))
    return pd.concat(parts).reindex(frame.index)


# --- the page ------------------------------------------------------------------------------------


def held_out_lines(group: str, held: Mapping[str, Any]) -> list[str]:
    """One plain line per finding of a recorded group (`held_out`): why the deployed model is above the
    plain least squares, and each model worse than the affine map with its cause."""
    lines = []
    for name, entry in held.items():
        if entry.get("why_not_lower"):
            lines.append(f"{group}/{name}: deployed model above {LS_AFFINE}: {entry['why_not_lower']}")
        for model, why in (entry.get("worse_than_affine") or {}).items():
            lines.append(f"{group}/{name}: {model} worse than the affine held out: {why}")
    return lines


def held_out_html(held: Mapping[str, Any], figures: Mapping[str, str]) -> str:
    """Per sensor of a recorded group: the held-out RMSE per axis of the models shown and what explains
    it (shares of its mean square, `decompose`), the excited directions with the maps' gains, the findings,
    and the residual's figure (`figures`: name -> path)."""
    from pipeline.evaluation.html import esc, fmt, table

    parts = []
    for name, entry in held.items():
        parts.append(f"<h4>{esc(name)}: where the held-out residual comes from (against labels)</h4>")
        moving = ", ".join(entry.get("moving_joints") or []) or "none"
        parts.append(
            f"<p class='note'>Share of each axis's mean square residual on the held-out segments that a "
            f"constant per segment (offset drift), a slope in time (drift), the moving joints' positions "
            f"(a frame, the URDF's masses) and their speeds (inertia, hysteresis, encoder derivatives) "
            f"explain, in that order; moving joints: {esc(moving)}.</p>"
        )
        rows = []
        for model, e in entry["models"].items():
            for a, axis in enumerate(AXES):
                shares = [f"{100 * e['shares'][c][a]:.0f} %" for c in CAUSES]
                rows.append([model if a == 0 else "", axis, fmt(e["rmse"][a]), *shares])
        parts.append(table(["model", "axis", "RMSE", *CAUSES], rows, "num"))
        excited = entry.get("excited") or []
        if excited:
            maps = list(excited[0]["gain"])
            rows = [
                [", ".join(d["axes"]), fmt(d["std_noise"]), *(f"{d['gain'][m]:.3f}" for m in maps)]
                for d in excited
            ]
            head = ["excited direction (largest axes)", "labels' std (noise units)"]
            parts.append(table([*head, *(f"gain: {m}" for m in maps)], rows, "num"))
            parts.append("<p class='note'>The factory's gain along every direction is 1.</p>")
        noise = entry.get("label_noise") or {}
        if noise:
            rows = [[log, *(fmt(v) for v in values)] for log, values in noise.items()]
            if entry.get("raw_noise"):
                rows.append(["the raw reading (training)", *(fmt(v) for v in entry["raw_noise"])])
            parts.append(
                "<p class='note'>The labels' inertial part per log or segment (RMS, N and Nm: the label "
                "less the same pose's label at rest), all that the smoothed encoders' velocities and "
                "accelerations put in it; on a slow motion mostly their noise. Beside it the raw reading's "
                "noise.</p>"
            )
            parts.append(table(["log", *AXES], rows, "num"))
        if entry.get("ls_push_slopes"):
            slopes = ", ".join(f"{a} {v:.2f}" for a, v in zip(AXES, entry["ls_push_slopes"], strict=True))
            parts.append(
                f"<p class='note'>{esc(LS_AFFINE)}'s slope to a push on each axis: {esc(slopes)}.</p>"
            )
        found = held_out_lines("", {name: entry})
        if found:
            parts.append("<ul>" + "".join(f"<li>{esc(x.split(': ', 1)[1])}</li>" for x in found) + "</ul>")
        if figures.get(name):
            parts.append(
                f"<figure><img src='{esc(figures[name])}' alt='{esc(name)} held-out residual'>"
                f"<figcaption>{esc(name)}: held-out residual per axis against time, the most moving "
                "joint and its speed</figcaption></figure>"
            )
    return "".join(parts)


def plot_held_out(
    frame: pd.DataFrame, joints: pd.DataFrame, name: str, models: Sequence[str], path: Path
) -> None:
    """The held-out residual (prediction - label) of `models` on each axis of `name` against time, the
    most moving joint's position and its speed: 6 rows, 3 columns, written to `path` (PNG)."""
    from pipeline.evaluation.figures import _color, pyplot, save_figure

    plt = pyplot()
    on = frame[S.switch_col(name)].to_numpy() == 1
    sub, jt = frame[on], joints[on]
    qcols = [c for c in jt.columns if c.startswith(f"{S.QS}.")]
    spans = {c: float(np.ptp(jt[c].to_numpy())) for c in qcols}
    joint = max(spans, key=spans.get) if spans else None
    label = sub[S.wrench_cols(S.EXPECTED, name)].to_numpy(np.float64)
    t = sub[S.TIME].to_numpy(np.float64)
    fig, axes = plt.subplots(6, 3, figsize=(13, 13), sharex="col", squeeze=False)
    xs = [("time, s", t)]
    if joint is not None:
        dq = jt[joint.replace(f"{S.QS}.", f"{S.DQS}.", 1)].to_numpy(np.float64)
        xs += [
            (f"{joint[3:]}, deg", np.degrees(jt[joint].to_numpy(np.float64))),
            ("its speed, deg/s", np.degrees(dq)),
        ]
    for model in models:
        r = sub[S.prediction_cols(model, name)].to_numpy(np.float64) - label
        for a in range(6):
            for c, (_, x) in enumerate(xs):
                axes[a, c].plot(
                    x,
                    r[:, a],
                    ".",
                    ms=1.5,
                    alpha=0.5,
                    color=_color(model),
                    label=model if a == c == 0 else None,
                )
    for a, axis in enumerate(AXES):
        axes[a, 0].set_ylabel(f"{axis} residual, {'N' if a < 3 else 'Nm'}")
    for c, (title, _) in enumerate(xs):
        axes[-1, c].set_xlabel(title)
    axes[0, 0].legend(loc="upper right", markerscale=6, fontsize=8)
    fig.suptitle(f"{name}: held-out residual against the labels (recorded)")
    save_figure(fig, path)


def read_inertial(labelled: Path) -> dict[str, dict[str, list[float]]]:
    """log -> sensor -> (6,) the RMS of its labels' inertial part, from each labelled table's metadata
    (`pipeline.labels.table.inertial_part`; recordings only)."""
    out = {}
    for path in sorted(labelled.glob(f"*{S.PARQUET_SUFFIX}")):
        meta = S.read_metadata(pq.read_schema(path), S.META_LABEL) or {}
        if meta.get("inertial_rms"):
            out[path.name[: -len(S.PARQUET_SUFFIX)]] = meta["inertial_rms"]
    return out
