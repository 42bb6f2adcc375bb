"""The report page's parts on trust off the training relation: fidelity to a push, excitation, and the
models the recommendation passed over (what `pipeline.evaluation.fidelity` computes, and why)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.calib.excitation import OUTSIDE, WEAK
from pipeline.calib.fidelity import entry_slopes
from pipeline.evaluation.fidelity import AXES
from pipeline.evaluation.html import esc, fmt, table
from pipeline.evaluation.params import TRUTH

if TYPE_CHECKING:
    from pipeline.evaluation.results import GroupReport

RELATION_R2 = 0.9  # a sensor's labels "follow torque ~ c x force" when it explains this share of the torques


def passed_over(r: GroupReport, flags: Mapping[str, str]) -> list[dict[str, Any]]:
    """The models ranked before the recommended one and why each was passed over, with the cost: the
    recommended model's mean fold error and (simulated logs) headline RMSE against the truth beside theirs."""
    if r.recommended is None:
        return []
    means = (r.cv or {}).get("mean") or {}
    out = []
    for model in r.validation_ranking:
        if model == r.recommended:
            break
        out.append(
            {
                "model": model,
                "why": flags.get(model, "not evaluated"),
                "cv_mean": means.get(model),
                "cv_mean_deployed": means.get(r.recommended),
                "truth": r.headline_rmse(TRUTH, model),
                "truth_deployed": r.headline_rmse(TRUTH, r.recommended),
            }
        )
    return out


def flag_reasons(r: GroupReport, noise_limit: float) -> dict[str, str]:
    """model -> every reason it is flagged (noise, fidelity)."""
    out: dict[str, list[str]] = {}
    for m in r.noise.flagged:
        ratio = fmt(r.noise.ratio.get(m))
        out.setdefault(m, []).append(f"output noise {ratio}x raw's (limit {noise_limit:g})")
    for m, why in r.unfaithful.items():
        out.setdefault(m, []).append(f"unfaithful to a push: {why}")
    return {m: "; ".join(v) for m, v in out.items()}


def passed_over_html(r: GroupReport, noise_limit: float) -> str:
    """One plain sentence per model cross-validation preferred over the deployed one."""
    rows = passed_over(r, flag_reasons(r, noise_limit))
    if not rows:
        return ""
    items = []
    for p in rows:
        cost = f"mean fold error {fmt(p['cv_mean_deployed'])} instead of {fmt(p['cv_mean'])}"
        if p["truth"] is not None and p["truth_deployed"] is not None:
            cost += f"; against the truth {fmt(p['truth_deployed'])} instead of {fmt(p['truth'])}"
        items.append(
            f"<li><b>{esc(p['model'])}</b>, preferred by cross-validation, was passed over: {esc(p['why'])}. "
            f"Deployed instead: <b>{esc(r.recommended)}</b> ({esc(cost)}).</li>"
        )
    return f"<p><b>{esc(r.group)}:</b></p><ul>{''.join(items)}</ul>"


def fidelity_table(r: GroupReport, tolerance: float) -> str:
    """Per model: headline RMSE against labels and truth beside its worst virtual-push slope (sensor, axis)
    at the prior's size and at each small scale, and, for 13-input networks, how much force it reads off
    the accelerometer."""
    if not r.fidelity:
        return ""
    scales = list(
        dict.fromkeys(k for m in r.fidelity.values() for e in m.values() for k, _ in entry_slopes(e))
    )
    rows = []
    for model in r.models:
        sensors = r.fidelity.get(model)
        if not sensors:
            continue
        cells = []
        for scale in scales:
            worst = max(
                ((abs(v - 1), s, AXES[a], v) for s, e in sensors.items() for k, slopes in entry_slopes(e)
                 if k == scale for a, v in enumerate(slopes)),
                default=None,
            )  # fmt: skip
            bad = worst is not None and worst[0] > tolerance
            text = (
                ""
                if worst is None
                else f"{esc(fmt(worst[3]))} <small>({esc(worst[1])} {esc(worst[2])})</small>"
            )
            cells.append(f"<b>{text}</b>" if bad else text)
        imu = [e.get("imu_kg") for e in sensors.values() if e.get("imu_kg") is not None]
        status = "unfaithful" if model in r.unfaithful else ("deploy" if model == r.recommended else "")
        rows.append(
            [
                esc(model),
                esc(fmt(r.headline_rmse("labels", model))),
                esc(fmt(r.headline_rmse(TRUTH, model))),
                *cells,
                esc(fmt(max(imu))) if imu else "",
                esc(status),
            ]
        )
    worst_heads = [f"worst slope, {k}" if k else "worst slope, prior's size" for k in scales]
    head = ["model", "RMSE labels", "RMSE truth", *worst_heads, "force per acc (kg)", ""]
    note = (
        f"<p class='note'>Virtual pushes on the validation samples' raw readings (no truth): the slope of "
        f"the reported change along each axis of each sensor, at the push prior's size and at 1, 5 and 20 N "
        f"(either way; torques: that force at the prior's lever); the factory map's is 1, a faithful "
        f"calibration's within its few % of gain error at every scale. Farther than {tolerance:g} from 1 at "
        "any scale (bold): unfaithful, not deployed (a network that snaps small pushes to its training "
        "relation fails at 1 N while looking faithful at the prior's size). Per axis in the table below.</p>"
    )
    detail = []
    for model in r.models:
        for sensor, e in (r.fidelity.get(model) or {}).items():
            for scale, slopes in entry_slopes(e):
                detail.append(
                    [esc(model), esc(sensor), esc(scale or "prior"), *(esc(fmt(v)) for v in slopes)]
                )
    details = table(["model", "sensor", "scale", *AXES], detail, "num", raw_html=True)
    return (
        "<h4>Fidelity to a push</h4>"
        + note
        + table(head, rows, "num", raw_html=True)
        + f"<details><summary>per-axis slopes</summary>{details}</details>"
    )


def _direction_text(direction: Sequence[float], noise: Sequence[float]) -> str:
    """A whitened direction in physical terms: its two largest components, e.g. 'fx 0.71 + ty -0.70'."""
    d = np.asarray(direction) * np.asarray(noise)  # back to N and Nm
    d = d / np.linalg.norm(d)
    top = np.argsort(-np.abs(d))[:2]
    return " + ".join(f"{AXES[a]} {d[a]:+.2f}" for a in sorted(top))


def excitation_html(r: GroupReport) -> str:
    """Per sensor: the excited directions, the relation its labels follow, the test samples' outside
    distance, and a plain warning with the experiment that would widen a narrow excitation."""
    if not r.excitation:
        return ""
    rows, warnings = [], []
    for sensor, e in r.excitation.items():
        out = (r.outside or {}).get(sensor, {})
        std = e["std"]
        c, r2 = e["lever_m"], e["lever_r2"]
        rows.append(
            [
                esc(sensor),
                esc(str(e["samples"])),
                " ".join(esc(fmt(v)) for v in std),
                esc(str(e["weak"])),
                f"({', '.join(f'{v:.3f}' for v in c)}) m, {esc(fmt(100 * r2))} %",
                esc(fmt(out.get("p95"))),
                esc(fmt(100 * out["share_outside"])) if "share_outside" in out else "",
            ]
        )
        if e["weak"]:
            weak = [_direction_text(d, e["noise"]) for d in e["directions"][len(std) - e["weak"] :]]
            relation = (
                f" Its labels follow torque ~ c x force (c = ({', '.join(f'{v:.3f}' for v in c)}) m, "
                f"{fmt(100 * r2)} % of the torque variance): a free limb's relation."
                if r2 >= RELATION_R2
                else ""
            )
            warnings.append(
                f"<li><b>{esc(sensor)}</b>: {e['weak']} of 6 directions barely excited by the training "
                f"labels (std below {WEAK:g}x the noise): {esc('; '.join(weak))}. Along them its calibration "
                "keeps the factory map's gain and coupling (the virtual pushes): trustworthy there only as "
                f"far as the factory calibration is.{esc(relation)} To widen it: record a known-load "
                "experiment (a mass at a known point of the limb, simulate type known_load) or pushes with "
                "a known force.</li>"
            )
    head = ["sensor", "labels", "std per direction (noise units)", "weak", "torque ~ c x force (c, R²)",
            "test: outside p95", f"test: % beyond {OUTSIDE:g}"]  # fmt: skip
    parts = ["<h4>Excitation of the training labels</h4>", table(head, rows, "num", raw_html=True)]
    if warnings:
        parts.append(f"<div class='flags'><ul>{''.join(warnings)}</ul></div>")
    return "".join(parts)
