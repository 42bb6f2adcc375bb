"""reports/deployment.html and its figures: the verdict per day, then each day's tests, numbers first.

The page has the look of the report page (`pipeline.evaluation.html`) and links to it, as it links here.
"""

from __future__ import annotations

from collections.abc import Mapping
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.io import write_text
from pipeline.evaluation.figures import pyplot, save_figure
from pipeline.evaluation.html import cell, document, esc, img, table
from pipeline.evaluation.params import REPORT_FILE
from pipeline.logs import schema as S


def plot_walking(
    table: Any, truth: Any, calibrated: dict[str, np.ndarray], sensors: list[str], path: Path
) -> None:
    """Thesis figure 6.3: fz of the given sensors while walking: raw, calibrated, label, truth."""
    plt = pyplot()
    fig, axes = plt.subplots(len(sensors), 1, figsize=(11, 2.6 * len(sensors)), sharex=True, squeeze=False)
    t = table[S.TIME].to_numpy()
    for ax, s in zip(axes[:, 0], sensors, strict=True):
        col = S.wrench_cols(S.FT, s)[2]
        ax.plot(t, table[col], lw=0.7, label="raw", color="tab:red")
        ax.plot(t, calibrated[s][:, 2], lw=0.7, label="calibrated", color="tab:blue")
        ax.plot(t, table[S.wrench_cols(S.EXPECTED, s)[2]], lw=1.2, ls="--", label="label (exact)", color="k")
        if truth is not None:
            ax.plot(
                t, truth[S.wrench_cols(S.TRUE, s)[2]], lw=0.7, label="truth", color="tab:green", alpha=0.7
            )
        ax.set_ylabel(f"{s} fz (N)")
    axes[0, 0].legend(loc="upper right", ncol=4, fontsize=8)
    axes[-1, 0].set_xlabel("time (s)")
    fig.tight_layout()
    save_figure(fig, path)


def plot_torques(series: dict[str, Any], joint_suffix: str, path: Path) -> None:
    """Thesis figure of Test C: the hip pitch torque of each leg from raw and calibrated vs the truth."""
    plt = pyplot()
    legs = [k for k in series if isinstance(series[k], dict)]
    fig, axes = plt.subplots(len(legs), 1, figsize=(11, 3 * len(legs)), sharex=True, squeeze=False)
    t = series["time_s"]
    for ax, leg in zip(axes[:, 0], legs, strict=True):
        d = series[leg]
        c = next(i for i, j in enumerate(d["joints"]) if j.endswith(joint_suffix))
        ax.plot(t, d["raw"][:, c], lw=0.8, color="tab:red", label="from raw sensor")
        ax.plot(t, d["calibrated"][:, c], lw=0.8, color="tab:blue", label="from calibrated sensor")
        ax.plot(t, d["true"][:, c], lw=1.2, ls="--", color="k", label="true")
        ax.fill_between(
            t, 0, 1, where=series["pushed"], transform=ax.get_xaxis_transform(), alpha=0.1, color="grey"
        )
        ax.set_ylabel(f"{d['joints'][c]} (Nm)")
    axes[0, 0].legend(loc="upper right", ncol=3, fontsize=8)
    axes[-1, 0].set_xlabel("time (s); grey: pushes")
    fig.tight_layout()
    save_figure(fig, path)


def plot_scales(result: Mapping[str, Any], path: Any) -> bool:
    """Per sensor: the slope of the force pushes (worst force axis against 1) and the moments' against the
    magnitude (log x), deployed solid, oracle dashed, raw dotted. False if nothing to draw."""
    from pipeline.deploy.scales import worst_slope

    shown = [s for s, e in result.items() if e.get("force")]
    if not shown:
        return False
    plt = pyplot()
    fig, axes = plt.subplots(1, len(shown), figsize=(3.6 * len(shown), 3.2), squeeze=False)
    styles = {"deployed": ("-", "tab:blue"), "oracle": ("--", "tab:green"), "raw": (":", "tab:red")}
    for ax, sensor in zip(axes[0], shown, strict=True):
        for family, marker, axes_ in (("force", "o", range(3)), ("moment", "s", range(3, 6))):
            rows = result[sensor].get(family) or {}
            mags = [float(m) for m in rows]
            for model, (ls, color) in styles.items():
                worst = [worst_slope(rows[m][model]["slopes"], axes_) for m in rows]
                label = f"{model} ({'N' if family == 'force' else 'Nm'})"
                ax.plot(mags, worst, ls=ls, marker=marker, color=color, ms=3, lw=1, label=label)
        ax.axhline(1.0, color="k", lw=0.6)
        ax.set_xscale("log")
        ax.set_title(sensor, fontsize=9)
        ax.set_xlabel("push magnitude (N; moments Nm)", fontsize=8)
        ax.set_ylabel("slope, worst axis", fontsize=8)
    axes[0, 0].legend(fontsize=6, ncol=2)
    fig.tight_layout()
    save_figure(fig, path)
    return True


_NOTES = {
    "test_a": "Output noise of every trained model standing still: high-pass std per axis over raw's on the "
    "quasi-static stretches, worst axis; a model above the limit is flagged (as evaluate flags it). The "
    "deployed model must not be.",
    "test_b": "RMSE (N and Nm pooled; per axis in deployment/details.json) of the calibrated sensors and "
    "foot sums while walking, against the labels (where exact) and the truth, beside raw; raw / "
    "calibrated against truth is judged. The last column: the group's affine map, the calibration "
    "wholeBodyDynamics runs from exported/wholebodydynamics.xml, on the same samples (not judged).",
    "test_c": "Leg joint torques estimated from each leg sensor, raw and calibrated, against the true "
    "torques during the pushes (Nm); the RMSE ratio of the judged joint is judged, the max error reported.",
    "test_d": "Pushes of 10-40 N at every sensor's site (hands, ankles, front and rear of the soles) in "
    "several directions, then a load carried in each hand, the robot on the pole: per sensor and axis the "
    "slope of the reported change against the true one (1 = follows the push), raw, deployed and oracle; "
    "the error of the reported change and of the reading itself during the pushes (N). Judged: the "
    "deployed slopes' error (against 1) at most the oracle's plus the tolerance (the oracle's own slopes "
    "carry the sensors' hysteresis), and the change's error at most the target x the oracle's. "
    "<i>outside</i>: how far the deployed output lies outside the training excitation (p95, noise units), "
    "during the pushes and on the rest of the log.",
}


def _test_a(a: Mapping[str, Any]) -> str:
    rows = []
    for group, entry in a.items():
        for model, r in entry["models"].items():
            deployed = model == entry["deployed"]
            good = None if not deployed else not r["flagged"]
            rows.append(
                f"<tr><td>{esc(group)}</td><td>{esc(model)}{' (deployed)' if deployed else ''}</td>"
                + cell(r["worst"], good, bold=deployed)
                + f"<td>{'FLAGGED' if r['flagged'] else 'ok'}</td></tr>"
            )
    head = "".join(f"<th>{h}</th>" for h in ("group", "model", "noise ratio (worst axis)", "verdict"))
    return f'<table class="num"><thead><tr>{head}</tr></thead><tbody>{"".join(rows)}</tbody></table>'


def _test_b(b: Mapping[str, Any], target: float) -> str:
    rows = []
    for name, e in b.items():
        lab, tru = e["labels"], e.get("truth", {})
        row = f"<tr><td>{esc(name)}</td>" + cell(lab["raw"]["rmse"]) + cell(lab["calibrated"]["rmse"])
        if tru:
            ratio = e["ratio_truth"]
            row += cell(tru["raw"]["rmse"]) + cell(tru["calibrated"]["rmse"]) + cell(ratio, ratio >= target)
        else:
            row += "<td>n/a</td>" * 3
        fallback = e.get("fallback") or {}
        row += cell((fallback.get("truth") or fallback.get("labels") or {}).get("rmse"))
        rows.append(row + "</tr>")
    header = ["sensor / sum", "raw vs labels", "calibrated vs labels", "raw vs truth", "cal. vs truth"]
    header += [f"raw / cal. (>= {target:g})", "wholeBodyDynamics affine (truth, else labels)"]
    head = "".join(f"<th>{h}</th>" for h in header)
    return f'<table class="num"><thead><tr>{head}</tr></thead><tbody>{"".join(rows)}</tbody></table>'


def _test_c(c: Mapping[str, Any], joint: str, target: float) -> str:
    rows = []
    for leg, r in c.items():
        for j, v in r["joints"].items():
            judged = j.endswith(joint)
            rows.append(
                f"<tr><td>{esc(leg)}</td><td>{esc(j)}</td>"
                + cell(v["raw"]["rmse"]) + cell(v["calibrated"]["rmse"])
                + cell(v["ratio_rmse"], v["ratio_rmse"] >= target if judged else None, bold=judged)
                + cell(v["raw"]["max"]) + cell(v["calibrated"]["max"]) + cell(v["ratio_max"]) + "</tr>"
            )  # fmt: skip
    header = ["sensor", "joint", "RMSE raw", "RMSE cal.", f"RMSE raw / cal. (>= {target:g})"]
    head = "".join(f"<th>{h}</th>" for h in [*header, "max raw", "max cal.", "max raw / cal."])
    return f'<table class="num"><thead><tr>{head}</tr></thead><tbody>{"".join(rows)}</tbody></table>'


def _slopes(values: list[Any]) -> str:
    return " ".join("-" if v is None else f"{v:.2f}" for v in values)


def _test_d(d: Mapping[str, Any], tolerance: float, target: float) -> str:
    rows = []
    for sensor, e in d.items():
        verdict = e["verdict"]
        for kind in ("pushes", "loads"):
            if kind not in e:
                continue
            entry = e[kind]
            for model in ("raw", "calibrated", "oracle"):
                r = entry[model]
                judged = model == "calibrated" and kind == "pushes"
                excess = verdict.get("worst_slope_excess") if judged else None
                ratio = verdict.get("change_ratio") if judged else None
                outside = ((e.get("outside") or {}).get("pushed") or {}).get("p95") if judged else None
                rows.append(
                    f"<tr><td>{esc(sensor)}</td><td>{kind} ({entry['windows']})</td><td>{esc(model)}</td>"
                    f"<td>{esc(_slopes(r['slopes']))}</td>"
                    + cell(excess, None if excess is None else excess <= tolerance, bold=judged)
                    + cell(r["rmse_change_force"])
                    + cell(ratio, None if ratio is None else ratio <= target, bold=judged)
                    + cell(r["rmse_force"]) + cell(r["max_force"]) + cell(outside) + "</tr>"
                )  # fmt: skip
    header = ["sensor", "what", "model", "slopes fx fy fz tx ty tz", f"slope excess (<= {tolerance:g})",
              "change RMSE", f"/ oracle's (<= {target:g})", "RMSE", "max", "outside p95"]  # fmt: skip
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    return f'<table class="num"><thead><tr>{head}</tr></thead><tbody>{"".join(rows)}</tbody></table>'


_SCALES_NOTE = (
    "Virtual pushes on every simulated log of the day (standing, walking, pole, interaction), added through "
    "each sensor's own hidden distortion (hysteresis included; the log's noise, temperature and IMU as "
    "logged) and run through the deployed export beside the oracle and raw: forces of 1-40 N along the "
    "sensor's axes at levers 0-1.5 x its site (hand, ankle, sole), pure moments, random 6-D directions, "
    "loads held at the site. Per magnitude the slope of the reported change against the push per axis "
    "(fx fy fz, or tx ty tz for moments; 1 = follows it) and the change error RMS(reported - push) / "
    "RMS(push), deployed / oracle. Judged at every force magnitude: each axis's slope error (against 1) at "
    "most the oracle's plus the tolerance, the change error at most the target x the oracle's."
)


_STEPS_NOTE = (
    "The loads above held at each sensor's site (raised-cosine ramps, then a plateau) while the robot "
    "goes on moving: the reported change of the force along the load, over the load, averaged over the "
    "holds of the day's logs (1 = the load as it is). On the plateau: the means of its first and last "
    "thirds and their difference (a decay), its extremes (an overshoot). The sensor's hysteresis reads a "
    "fresh load larger than a held one (the oracle, the static inverse, shows it); a calibration with "
    "memory must stay flat, neither lagging nor decaying (figure: step responses)."
)


def _scales_rows(e: Mapping[str, Any], tolerance: float, target: float) -> list[str]:
    from pipeline.deploy.scales import JUDGED, row_judgement

    rows = []
    units = {"force": "N", "moment": "Nm", "random": "N", "load": "kg"}
    for family, unit in units.items():
        axes = range(3, 6) if family == "moment" else range(6) if family == "random" else range(3)
        key = "error_torque" if family == "moment" else "error"
        for mag, row in (e.get(family) or {}).items():
            judged = family in JUDGED
            excess, _, ratio = row_judgement(row, family) if judged else (None, "", None)
            slopes = [_slopes([row[m]["slopes"][a] for a in axes]) for m in ("deployed", "oracle", "raw")]
            rows.append(
                f"<tr><td>{family}</td><td>{esc(mag)} {unit}</td>"
                + "".join(f"<td>{esc(v)}</td>" for v in slopes)
                + cell(excess, None if excess is None else excess <= tolerance, bold=judged)
                + "".join(cell(row[m][key]) for m in ("deployed", "oracle", "raw"))
                + cell(ratio, None if ratio is None else ratio <= target, bold=judged)
                + "</tr>"
            )
    return rows


def _scales_table(sensor: str, e: Mapping[str, Any], tolerance: float, target: float) -> str:
    """One sensor's table: a row per family and magnitude, deployed / oracle / raw slopes and errors."""
    header = ["what", "magnitude", "slopes deployed", "slopes oracle", "slopes raw",
              f"slope excess (<= {tolerance:g})", "change error deployed", "oracle", "raw",
              f"deployed / oracle (<= {target:g})"]  # fmt: skip
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    body = "".join(_scales_rows(e, tolerance, target))
    v = e["verdict"]
    where = (
        f"worst slope excess {v.get('worst_slope_excess')} at {v.get('at_slope', '')} N, "
        f"worst change ratio {v.get('worst_change_ratio')} at {v.get('at_change', '')} N"
    )
    lever = ", ".join(f"{x:.3f}" for x in e["lever_m"])
    levers = "; ".join(
        f"x{k}: "
        + " ".join("-" if a is None else f"{a:.2f}/{b:.2f}" for a, b in zip(*r.values(), strict=True))
        for k, r in e.get("levers", {}).items()
    )
    return (
        f"<h4>{esc(sensor)}: {'pass' if v['pass'] else 'FAIL'} <small>({esc(where)}; site lever "
        f"({lever}) m)</small></h4>"
        f'<table class="num"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'
        "<p class='meta'>force pushes' change error per lever scale, deployed/oracle at each force "
        f"magnitude: {esc(levers)}</p>"
    )


def scales_section(ds: Mapping[str, Any], tolerance: float, target: float) -> str:
    """Test D from the noise level up (`pipeline.deploy.scales`): its note and one table per sensor."""
    from pipeline.deploy.steps import steps_table

    parts = ["<h3>Test D from the noise level up: virtual pushes of every scale</h3>",
             f"<p class='note'>{_SCALES_NOTE}</p>"]  # fmt: skip
    parts += [_scales_table(sensor, e, tolerance, target) for sensor, e in ds.items()]
    steps = steps_table(ds)
    if steps:
        parts += ["<h4>Step responses: a held load's reported change over its hold</h4>",
                  f"<p class='note'>{_STEPS_NOTE}</p>", steps]  # fmt: skip
    return "\n".join(parts)


def verdict_table(
    summary: Mapping[str, Mapping[str, Any]], rezeroed: Mapping[str, Mapping[str, Any]] | None = None
) -> str:
    """One row per day, each test's pass and the day's verdict; beneath it the same after re-zeroing."""
    rows = []
    for day, s in summary.items():
        variants = [(day, "", s)]
        if (rezeroed or {}).get(day):
            variants.append((f"{day}, re-zeroed", "-rezeroed", rezeroed[day]["summary"]))
        for name, anchor, v in variants:
            passed = [bool(v.get(f"{t}.passed", True)) for t in ("a", "b", "c", "d", "ds")]
            cells = "".join(
                f'<td class="{"ok" if p else "bad"}">{"pass" if p else "fail"}</td>' for p in passed
            )
            verdict = "fit to deploy" if v["fit_to_deploy"] else "recalibrate"
            link = f"<a href='#{esc(day + anchor)}'>{esc(name)}</a>"
            rows.append(f"<tr><td>{link}</td>{cells}<td><b>{verdict}</b></td></tr>")
    head = ["day", "Test A", "Test B", "Test C", "Test D", "Test D, every scale", "verdict"]
    return table(head, [], cls="num").replace("<tbody></tbody>", f"<tbody>{''.join(rows)}</tbody>")


_REZERO_NOTE = (
    "Each sensor's raw reading's offset change since training, solved so that the calibration of raw - "
    "offset matches the exact labels of the day's first still seconds (ftcal rezero): <i>all</i>, every "
    "axis fixed by the sensor's own label or its sums with others; <i>sums</i>, only through cut-set sums "
    "(standing on both feet: how the legs' and feet's offsets split within their sums is not observable, "
    "and stays nearest to the calibration as delivered); <i>none</i>, no exact label. Offsets N and Nm; "
    "std: their uncertainty from the stretch's noise (worst force and torque axis); spread: the std of the "
    "offsets re-zeroed from each still pose of the log alone (worst axes), and its ratio to the reading's "
    "noise (worst axis): above the limit the calibration depends on the pose (the sensor's hysteresis, the "
    "URDF's errors in the labels), which the noise does not show. Applied: the axes whose estimated change "
    "is applied in full, shrunk, or not at all (within deploy.rezero.significance x its noise and floor: "
    "the labels' model error for the pose and the spread over the poses); the offsets shown are those "
    "applied."
)


def _applied(reasons: list[str] | None) -> str:
    """``full/shrunk/none``: how many axes of a sensor's estimate were applied so (`deploy.shrink`)."""
    if not reasons:
        return "-"
    kinds = [r.split(" ")[0] for r in reasons]
    return f"{kinds.count('applied')}/{kinds.count('shrunk')}/{kinds.count('not')}"


def _worst(values: list[Any]) -> float | None:
    return None if any(v is None for v in values) else max(values)


def rezero_table(records: Mapping[str, Mapping[str, Any]], limit: float) -> str:
    """The re-zeroing of each group on a day: the stretch and per sensor status, offset, std, pose spread."""
    parts, rows = [], []
    for group, r in records.items():
        if "error" in r:
            parts.append(f"<p class='meta'>{esc(group)}: {esc(r['error'])}</p>")
            continue
        for st in r["stretches"]:
            gyro = "n/a" if st["gyro_rad_s"] is None else f"{st['gyro_rad_s']:.3f}"
            parts.append(
                f"<p class='meta'>{esc(group)}: re-zeroed from {esc(st['name'])}; still: fastest joint "
                f"{esc(st['joint'])} {st['joint_rad_s']:.4f} rad/s, FT boards {gyro} rad/s</p>"
            )
        poses = (r.get("pose_dependence") or {}).get("sensors", {})
        for sensor, e in r["sensors"].items():
            offset = (r["offsets"].get(sensor) or [None] * 6)[:6]
            pose = poses.get(sensor, {})
            depends = pose.get("depends")
            spread = pose.get("spread") or [None] * 6
            rows.append(
                f"<tr><td>{esc(group)}</td><td>{esc(sensor)}</td><td>{esc(e['status'])}</td>"
                + "".join(cell(v) for v in offset) + cell(max(e["std"][:3])) + cell(max(e["std"][3:]))
                + cell(_worst(spread[:3])) + cell(_worst(spread[3:]))
                + cell(pose.get("ratio"), None if depends is None else not depends)
                + f"<td>{'POSE-DEPENDENT' if depends else ('ok' if depends is not None else '-')}</td>"
                + f"<td>{_applied(e.get('applied'))}</td></tr>"
            )  # fmt: skip
    header = ["group", "sensor", "re-zeroed", "fx", "fy", "fz", "tx", "ty", "tz", "std force", "std torque",
              "spread force", "spread torque", f"spread / noise (<= {limit:g})", "pose",
              "applied (full/shrunk/none)"]  # fmt: skip
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    rows_html = f'<table class="num"><thead><tr>{head}</tr></thead><tbody>{"".join(rows)}</tbody></table>'
    return "\n".join([f"<p class='note'>{_REZERO_NOTE}</p>", *parts, rows_html if rows else ""])


def day_section(
    day: str, result: Mapping[str, Any], figures: Mapping[str, str], targets: Mapping[str, Any]
) -> str:
    """A day's tables and figures (`figures`: caption -> path relative to the page)."""
    parts = [
        f"<h2 id='{esc(day)}'>{esc(day)}</h2>",
        f"<p class='meta'>logs: {esc(', '.join(result['logs']))}</p>",
    ]
    if "test_a" in result:
        parts += ["<h3>Test A: output noise standing still</h3>", f"<p class='note'>{_NOTES['test_a']}</p>"]
        parts.append(_test_a(result["test_a"]))
    if "test_b" in result:
        parts += ["<h3>Test B: walking</h3>", f"<p class='note'>{_NOTES['test_b']}</p>"]
        parts.append(_test_b(result["test_b"], targets["b"]))
    if "test_c" in result:
        parts += [
            "<h3>Test C: joint torques during the pushes</h3>",
            f"<p class='note'>{_NOTES['test_c']}</p>",
        ]
        parts.append(_test_c(result["test_c"], targets["joint"], targets["c"]))
    if "test_d" in result:
        parts += ["<h3>Test D: interaction fidelity</h3>", f"<p class='note'>{_NOTES['test_d']}</p>"]
        parts.append(_test_d(result["test_d"], targets["d_slope"], targets["d_change"]))
    if "test_d_scales" in result:
        parts.append(scales_section(result["test_d_scales"], targets["d_slope"], targets["d_change"]))
    parts += [img(src, caption) for caption, src in figures.items()]
    return "\n".join(parts)


def _rezeroed_section(day: str, entry: Mapping[str, Any], targets: Mapping[str, Any]) -> str:
    """A day's tests after re-zeroing: the re-zeroing, then tests B, C, D and their figures."""
    tests = {k: v for k, v in entry["details"].items() if k != "test_a"}
    section = day_section(day, tests, entry.get("figures", {}), targets)
    head = f"<h2 id='{esc(day)}'>{esc(day)}</h2>"
    return section.replace(
        head,
        f"<h2 id='{esc(day)}-rezeroed'>{esc(day)}, re-zeroed</h2>"
        + rezero_table(entry.get("rezero", {}), targets.get("pose_limit", float("nan"))),
        1,
    )


def render_page(
    days: Mapping[str, Mapping[str, Any]],
    summary: Mapping[str, Mapping[str, Any]],
    figures: Mapping[str, Mapping[str, str]],
    targets: Mapping[str, Any],
    rezeroed: Mapping[str, Mapping[str, Any]] | None = None,
) -> str:
    """The deployment page: the verdict per day, then each day's tests (`targets`: b, c, joint, d_slope,
    d_change, pose_limit), each followed by its tests after re-zeroing (`rezeroed`: day -> summary, details,
    figures and the groups' re-zeroing records)."""
    now = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    nav = "".join(f"<a href='#{esc(d)}'>{esc(d)}</a>" for d in days)
    parts = [
        "<h1>FT sensor calibration: deployment tests</h1>",
        f"<p class='meta'>generated {now} · the thesis's tests A, B, C (chapter 6) and D (interaction "
        "fidelity) on logs no model has seen, calibrated by the export as on the robot, as delivered and "
        "re-zeroed from each day's first still seconds · N, Nm</p>",
        f"<nav><a href='{REPORT_FILE}'>Evaluation report (its own page)</a><a href='#verdict'>Verdict</a>"
        f"{nav}</nav>",
        "<h2 id='verdict'>Verdict</h2>",
        verdict_table(summary, rezeroed)
        if days
        else f"<div class='flags'>{esc(targets.get('nothing', ''))}</div>",
    ]
    for d, r in days.items():
        parts.append(day_section(d, r, figures.get(d, {}), targets))
        if (rezeroed or {}).get(d):
            parts.append(_rezeroed_section(d, rezeroed[d], targets))
    return document("ftcal deployment tests", parts)


def write_page(path: Path, *args: Any) -> None:
    """Write `render_page(*args)` to `path`, atomically."""
    write_text(path, render_page(*args))
