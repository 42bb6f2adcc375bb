"""Parts of the report page beyond the thesis tables: error per contact phase, cross-validation folds,
exact-label availability (each rendered only where its data exist)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from pipeline.calib.registry import POLY, in_family
from pipeline.evaluation.availability import CUT, PAIR, SENSOR
from pipeline.evaluation.html import esc, fmt, table
from pipeline.evaluation.params import LABELS, ORACLE, TRUTH
from pipeline.evaluation.phases import AIR, DOUBLE, PHASE_KEYS, PHASE_TITLES

if TYPE_CHECKING:
    from pipeline.evaluation.results import GroupReport

_PHASE_REFS = {
    LABELS: "against the labels (samples where the switch is 1)",
    TRUTH: "against the truth (all samples)",
}
_KEY_TITLES = {"rmse": "global", "rmse_force": "force", "rmse_torque": "torque"}


def _bold_min(values: Sequence[Any], models: Sequence[str]) -> list[str]:
    """Formatted values, the lowest (oracle excluded) in bold."""
    finite = [
        v for m, v in zip(models, values, strict=True) if m != ORACLE and v is not None and math.isfinite(v)
    ]
    best = min(finite) if finite else None
    return [f"<b>{esc(fmt(v))}</b>" if v is not None and v == best else esc(fmt(v)) for v in values]


def _model_title(model: str, recommended: str | None) -> str:
    if model == recommended:
        return f"{model} (deploy)"
    return f"{model} (best polynomial on val.)" if in_family(model, POLY) else model


def phase_section(r: GroupReport, name: str) -> str:
    """The RMSE per contact phase of headline `name` (empty if the report has none): one table per
    reference; rows phase x (global, force, torque), columns the group's `phase_models`."""
    refs = r.phases.get(name) or {}
    if not refs:
        return ""
    models = list(r.phase_models)
    head = ["phase", "samples", "RMSE", *(_model_title(m, r.recommended) for m in models)]
    tables, empty = [], set()
    for ref, title in _PHASE_REFS.items():
        if ref not in refs:
            continue
        rows = []
        for phase, entry in refs[ref].items():
            n = int(entry.get("samples") or 0)
            if n == 0:
                empty.add((ref, phase))
                rows.append([esc(PHASE_TITLES.get(phase, phase)), "0", "", *("" for _ in models)])
                continue
            for k, key in enumerate(PHASE_KEYS):
                values = [(entry["models"].get(m) or {}).get(key) for m in models]
                first = [esc(PHASE_TITLES.get(phase, phase)), esc(n)] if k == 0 else ["", ""]
                rows.append([*first, _KEY_TITLES[key], *_bold_min(values, models)])
        tables.append(f"<div><b>{esc(title)}</b>{table(head, rows, 'num', raw_html=True)}</div>")
    note = (
        "Phase from the sample's contact set (declared, or detected from the foot forces): single support = "
        "contacts on one foot only (balancing, half-foot, walking), double support = on both feet, pole = "
        "held by a link that is not a foot. Against the truth every sample of a phase counts, guard bands "
        "included; against the labels only samples where this headline's switch is 1. Lowest per row "
        "(oracle excluded) in bold; force in N, torque in Nm, global pools the 6 components."
    )
    if (TRUTH, AIR) in empty or (LABELS, AIR) in empty and TRUTH not in refs:
        note += " In the air: no test sample without any contact (the row is kept with 0 samples)."
    if (LABELS, DOUBLE) in empty and (TRUTH, DOUBLE) not in empty:
        note += (
            " Double support against the labels: 0 samples, this headline has no exact label there (both "
            "sides of its cut touch); its error there is measurable against the truth only."
        )
    return (
        f"<h4>RMSE per contact phase</h4><div class='tables'>{''.join(tables)}</div>"
        f"<p class='note'>{esc(note)}</p>"
    )


def cv_section(cv: Mapping[str, Any] | None) -> str:
    """The cross-validation behind the recommendation (train's ``cv`` entry: folds, per-model validation
    RMSE per fold, mean, spread, rule, chosen); empty without one."""
    if not isinstance(cv, Mapping) or not isinstance(cv.get("scores"), Mapping) or not cv["scores"]:
        return ""
    scores, mean, spread = cv["scores"], cv.get("mean") or {}, cv.get("spread") or {}
    folds = list(cv.get("folds") or [])
    k = max([len(v) for v in scores.values() if isinstance(v, Sequence)] + [len(folds)])
    chosen = cv.get("chosen")
    head = ["model", *(f"fold {i + 1}" for i in range(k)), "mean", "spread"]
    rows = []
    for model, values in scores.items():
        values = list(values) if isinstance(values, Sequence) else []
        cells = [esc(fmt(values[i])) if i < len(values) else "n/a" for i in range(k)]
        label = f"<b>{esc(model)}</b> (chosen)" if model == chosen else esc(model)
        rows.append([label, *cells, esc(fmt(mean.get(model))), esc(fmt(spread.get(model)))])
    fold_rows = []
    for i, fold in enumerate(folds):
        val = ", ".join(str(v) for v in (fold.get("val") or [])) if isinstance(fold, Mapping) else ""
        train = len(fold.get("train") or []) if isinstance(fold, Mapping) else 0
        fold_rows.append(f"fold {i + 1}: validation {esc(val)} (trained on {train} logs)")
    rule = f"Rule: {esc(cv['rule'])}. " if cv.get("rule") else ""
    return (
        "<h3>Cross-validation behind the recommendation</h3>"
        f"<p class='note'>Validation RMSE against the labels (N and Nm pooled) per fold of whole training "
        f"logs. {rule}Chosen: <b>{esc(chosen)}</b>.</p>{table(head, rows, 'num cv', raw_html=True)}"
        + (f"<p class='note'>{'<br>'.join(fold_rows)}</p>" if fold_rows else "")
    )


_KIND_ORDER = {SENSOR: 0, PAIR: 1, CUT: 2}


def _pct(num: int, den: int) -> str:
    return "n/a" if den <= 0 else f"{100.0 * num / den:.1f}%"


def availability_section(avail: Mapping[str, Any] | None) -> str:
    """The exact-label availability table (`pipeline.evaluation.availability`); empty without data."""
    if not avail or not avail.get("types"):
        return ""
    types, double = avail["types"], avail.get("double") or {}
    labels = sorted(avail["labels"].items(), key=lambda kv: (_KIND_ORDER.get(kv[1], 3), kv[0]))
    cols = [(types[t], f"{t} ({types[t]['samples']} samples, {types[t]['logs']} logs)") for t in types]
    cols += [
        (double[t], f"{t}: double support outside guard bands ({double[t]['samples']} samples)")
        for t in double
    ]
    rows = []
    for name, kind in labels:
        cells = [_pct(c["exact"].get(name, 0), c["samples"]) for c, _ in cols]
        rows.append([name.replace("+", " + "), kind, *cells])
    guard_s = avail.get("guard_s")
    guard = f"{guard_s:g} s" if isinstance(guard_s, int | float) else "label.guard_s"
    ds = "; ".join(
        f"{esc(t)}: {c['samples'] + c['guard']} double-support samples, {c['guard']} of them in a guard band"
        for t, c in double.items()
    )
    note = (
        "<p class='note'>Share of samples whose label is exact (switch = 1), over every labelled log, "
        "training and test. A sensor's label is exact where one side of its cut touches nothing; a foot "
        "pair's sum and a cut set's sum (several sensors' wrenches mapped to one frame, isolating a part "
        "of the robot) where their part touches nothing or alone touches. Switches are also 0 where the "
        "kinematics of a joint the label needs are unusable or absent from the log (the joints on the path "
        "from the link fixed in the world to its cut, and those of its free side), and within "
        f"{esc(guard)} of a contact change (guard band). The "
        "double-support columns count only samples in double support (contacts on both feet) outside "
        "guard bands: the share of them with an exact label, e.g. for the leg pair and the four foot "
        f"sensors. {ds}.</p>"
    )
    head = ["label", "kind", *(h for _, h in cols)]
    return (
        "<h2 id='labels'>Exact-label availability</h2>"
        + note
        + table(head, [[esc(c) for c in row[:2]] + row[2:] for row in rows], "num", raw_html=True)
    )


def _num(values: Mapping[str, Any], key: str, missing: str) -> str:
    """`values[key]` as a short number, else the words `missing`."""
    return f"{values[key]:g}" if key in values else missing


def identification_section(ident: Mapping[str, Any] | None, figure: str | None) -> str:
    """The robot model identified by the label stage (`pipeline.stages.identify`: its identification.json)
    and its figure (a path relative to the page); empty without one."""
    if not ident:
        return ""
    from pipeline.labels.identify import part_state

    used = "the identified parameters" if ident.get("labels") == "identified" else "robot.urdf's parameters"
    why = f": {esc(ident['reason'])}" if ident.get("reason") else ""
    truth = any(p.get("mass_true") is not None for p in ident["parts"])
    crit = ident.get("criteria", {})
    head = ["part (heaviest link)", "URDF kg", "identified kg", "sd kg", "jackknife sd kg", "state"]
    rows = [
        [esc(p["name"]), fmt(p["mass_urdf"]), fmt(p["mass"]), fmt(p["sd"]), fmt(p["jackknife"])]
        + [esc(part_state(p))]
        + ([fmt(p["mass_true"])] if truth else [])
        for p in ident["parts"]
    ]
    errors = ("error_urdf", "error_identified", "error_true_inertials") if truth else ()
    sensor_head = ["sensor", "labels' change"] + (
        ["vs truth: URDF", "identified", "true inertials"] if truth else []
    )
    sensor_rows = [
        [esc(s), fmt(d["label_change"]), *(fmt(d[k]) for k in errors)] for s, d in ident["sensors"].items()
    ]
    shrink = _num(crit, "shrink", "a fraction of")
    reject_p = _num(crit, "reject_p", "label.identify.reject_p")
    note = (
        f"<p class='note'>Every massive link's mass and first moment identified with a model of each sensor "
        f"from {len(ident['logs'])} training logs ({ident['exact_samples']} exact samples; known loads in "
        f"{len(ident['known_load_logs'])}): <b>{esc(ident['status'])}</b>{why}. The labels use {used} "
        f"(label.inertials). A part is identified where the data shrink its mass's sd to {shrink} x the "
        "prior's (10 % of the mass), re-estimated where its masses' and first moments' change rejects the "
        "URDF's values (a chi-square statistic in the posterior covariance, beyond its quantile at "
        f"p = {reject_p}): its estimate, however uncertain, is nearer the robot than the URDF's. The others "
        "keep the URDF's values. The labels' change and their error against the true wrench (simulated logs) "
        "are RMS over the training logs' exact samples, 6 axes pooled, N and Nm. The identified model: "
        "models/identified/model.urdf.</p>"
    )
    img = f"<img src='{esc(figure)}' alt='identified part masses'>" if figure else ""
    return (
        "<h2 id='identified'>Identified robot model</h2>"
        + note
        + table(head + (["true kg"] if truth else []), rows, "num", raw_html=True)
        + table(sensor_head, sensor_rows, "num", raw_html=True)
        + img
    )


def wbd_section(results: Sequence[GroupReport]) -> str:
    """What wholeBodyDynamics' own linear calibration (the export's ``wholebodydynamics.xml``: each group's
    affine map) costs beside the deployed model, per headline: both test RMSEs (N/Nm pooled), against the
    truth where the logs have it, else the held-out labels."""
    from pipeline.export.wbd import fallback_cost

    rows = []
    for r in results:
        for name, c in fallback_cost(r.tables, r.recommended or "", r.headlines or [r.headline]).items():
            ratio = c["affine_rmse"] / c["deployed_rmse"] if c["deployed_rmse"] else math.nan
            rows.append(
                [
                    name,
                    c["deployed"],
                    fmt(c["deployed_rmse"]),
                    fmt(c["affine_rmse"]),
                    fmt(ratio),
                    c["against"],
                ]
            )
    if not rows:
        return ""
    head = ["headline", "deployed", "deployed RMSE", "affine RMSE", "affine / deployed", "against"]
    return (
        "<h2 id='wbd'>wholeBodyDynamics configuration</h2><p>The export writes "
        "<code>exported/wholebodydynamics.xml</code>: each group's affine map as wholeBodyDynamics' own "
        "secondary calibration, which a robot runs without ftcal's runtime (docs/deployment.md). What it "
        "costs beside the deployed model, on the test logs:</p>" + table(head, rows)
    )
