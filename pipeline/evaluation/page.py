"""The report page index.html: summary, noise check, one section per group (images by relative path)."""

from __future__ import annotations

import math
import subprocess
from collections.abc import Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.calib.params import LS_AFFINE
from pipeline.core.io import write_text
from pipeline.evaluation.answer import answer_table
from pipeline.evaluation.floors import MARK, below_oracle, prior_box
from pipeline.evaluation.html import cell as _cell
from pipeline.evaluation.html import document, fmt, warning
from pipeline.evaluation.html import esc as _e
from pipeline.evaluation.html import img as _img
from pipeline.evaluation.html import table as _table
from pipeline.evaluation.params import (
    DEPLOYMENT_PAGE,
    IDENTIFIED_FIGURE,
    LABELS,
    NN7,
    NN13,
    NO_TRUTH,
    ORACLE,
    PLOTS_DIR,
    REFERENCE_TITLES,
    REFERENCES,
    REPORT_FILE,
    TRUTH,
)
from pipeline.evaluation.residual import held_out_html, held_out_lines
from pipeline.evaluation.sections import (
    availability_section,
    cv_section,
    identification_section,
    phase_section,
    wbd_section,
)
from pipeline.evaluation.trust import excitation_html, fidelity_table, passed_over_html
from pipeline.logs import schema as S

if TYPE_CHECKING:
    from pipeline.evaluation.params import EvaluateParams
    from pipeline.evaluation.results import GroupReport


# --- the page ------------------------------------------------------------------------------------


_METRIC_ROWS = [("global", ""), ("force", "_force"), ("torque", "_torque")] + [
    (a, f"_{a}") for a in S.WRENCH_AXES
]


def thesis_table(tables: Mapping[str, Mapping[str, float]], models: Sequence[str], metric: str) -> str:
    """Thesis layout (tables 5.1-5.24): rows = MSE/MAE/RMSE global, force, torque, axes; columns = models.
    The lowest value of each row (oracle excluded) is bold."""

    rows = []
    for label, suffix in _METRIC_ROWS:
        values = [tables[m].get(f"{metric}{suffix}") for m in models]
        finite = [
            v
            for m, v in zip(models, values, strict=True)
            if m != ORACLE and v is not None and math.isfinite(v)
        ]
        best = min(finite) if finite else None
        cells = [f"{metric.upper()} {label}"]
        for v in values:
            text = _e(fmt(v))
            cells.append(f"<b>{text}</b>" if best is not None and v == best else text)
        rows.append(cells)
    rows.append(["samples"] + [_e(fmt(_count(tables[m].get("samples")))) for m in models])
    return _table([metric.upper(), *models], rows, "num", raw_html=True)


def _count(value: Any) -> int | None:
    return None if value is None or not math.isfinite(value) else int(value)


def _git_commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5, check=False
        )
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _headline_cells(r: GroupReport, name: str, refs: Sequence[str], cfg: EvaluateParams) -> str:
    """The RMSE and ratio cells of one headline of a summary row."""
    ratios, best, row = r.ratios(name), r.best_on_validation, ""
    for ref in refs:
        row += _cell(r.headline_rmse(ref, "raw", name=name))
        for model in (best, NN7):
            cell = _cell(r.headline_rmse(ref, model, name=name) if model else None)
            if ref == TRUTH and below_oracle(r, name, model) is not None:  # a footnote: prior_box says why
                cell = cell.replace("</td>", f"<sup>{MARK}</sup></td>", 1)
            row += cell
        row += _cell(r.headline_rmse(ref, ORACLE, name=name))
        if ref == TRUTH:  # the white noise alone: what a calibration with memory is judged against
            row += _cell(r.floor.get(name))
    for ref in refs:
        a, b = ratios["raw_over_nn7"][ref], ratios["nn7_over_oracle"][ref]
        row += _cell(a, None if a is None else a >= cfg.target_raw_over_nn7)
        row += _cell(b, None if b is None else b <= cfg.target_nn7_over_oracle)
    return row


def summary_table(results: Sequence[GroupReport], cfg: EvaluateParams) -> str:
    """One row per headline of every group (a group with several headlines, e.g. both legs and feet
    trained together, spans several rows): headline RMSE of raw, the best-on-validation model, NN7 and the
    oracle against labels and truth; the acceptance ratios; then per group the networks' noise ratios
    and the model to deploy."""

    refs = [ref for ref in REFERENCES if any(ref in r.tables[h] for r in results for h in _headlines(r))]
    head1 = "<tr><th rowspan=2>group</th><th rowspan=2>sensor / sum</th>"
    head2 = "<tr>"
    for ref in refs:
        head1 += f"<th colspan={5 if ref == TRUTH else 4}>RMSE against {REFERENCE_TITLES[ref]}</th>"
        head2 += "<th>raw</th><th>best on val.</th><th>NN7</th><th>oracle</th>"
        head2 += "<th>noise floor</th>" if ref == TRUTH else ""
    for ref in refs:
        head1 += f"<th colspan=2>ratios, {REFERENCE_TITLES[ref]}</th>"
        head2 += "<th>raw / NN7</th><th>NN7 / oracle</th>"
    head1 += (
        "<th colspan=2>noise ratio</th><th rowspan=2>best on validation</th><th rowspan=2>deploy</th></tr>"
    )
    head2 += "<th>NN7</th><th>NN13</th></tr>"
    body = []
    for r in results:
        names = _headlines(r)
        span = f" rowspan={len(names)}" if len(names) > 1 else ""
        best, rec = r.best_on_validation, r.recommended or "none"
        group_cells = ""
        for m in (NN7, NN13):
            v = r.noise.ratio.get(m)
            cell = _cell(v, None if v is None else v <= cfg.noise_limit)
            group_cells += cell.replace("<td", f"<td{span}", 1)
        notes = ["best on validation is noisy"] if rec != best else []
        worse = [
            n
            for n in names
            if (a := r.headline_rmse(LABELS, rec, name=n)) is not None
            and (b := r.headline_rmse(LABELS, "raw", name=n)) is not None
            and a > b
        ]
        if worse:
            what = f" ({', '.join(worse)})" if len(names) > 1 else ""
            notes.append(f"worse than raw on the test logs{what}: validation does not cover them")
        note = f" <small>({'; '.join(notes)})</small>" if notes else ""
        cls = "deploy bad" if worse else "deploy"
        group_cells += f"<td{span}>{_e(best)}</td><td{span} class='{cls}'><b>{_e(rec)}</b>{note}</td>"
        for i, name in enumerate(names):
            row = f"<tr><td{span}>{_e(r.group)}</td>" if i == 0 else "<tr>"
            row += f"<td>{_e(name)}</td>" + _headline_cells(r, name, refs, cfg)
            body.append(row + (group_cells if i == 0 else "") + "</tr>")
    return f'<table class="num summary"><thead>{head1}{head2}</thead><tbody>{"".join(body)}</tbody></table>'


def _headlines(r: GroupReport) -> list[str]:
    return list(r.headlines or [r.headline])


def _flags_box(results: Sequence[GroupReport], cfg: EvaluateParams) -> str:
    """One line each: the noise flags, the fidelity flags (or one green line: none), the models
    cross-validation preferred but passed over, the networks not trained; their detail folded."""
    flagged = [(r.group, m, r.noise.ratio.get(m)) for r in results for m in r.noise.flagged]
    unfaithful = [(r.group, m, why) for r in results for m, why in r.unfaithful.items()]
    lines = []
    if not flagged and not unfaithful:
        lines.append(
            warning(
                "Noise and fidelity",
                f"no model flagged (output noise within {cfg.noise_threshold:g}x raw's on quasi-static "
                f"stretches; every virtual push read within {cfg.fidelity_tolerance:g} of its size)",
                ok=True,
            )
        )
    if flagged:
        names = ", ".join(f"{_e(g)}/{_e(m)}" for g, m, _ in flagged)
        detail = (
            ", ".join(f"<b>{_e(g)}/{_e(m)}</b> (x{_e(fmt(v))})" for g, m, v in flagged)
            + f": output noise above {cfg.noise_threshold:g}x raw's on quasi-static stretches (thesis "
            "chapter 6, Test A: the 13-input network passed the IMU noise through and was unusable on the "
            "robot)."
        )
        lines.append(warning("Noise flags", f"{names}: not deployed", detail))
    if unfaithful:
        names = ", ".join(f"{_e(g)}/{_e(m)}" for g, m, _ in unfaithful)
        detail = (
            ", ".join(f"<b>{_e(g)}/{_e(m)}</b> ({_e(why)})" for g, m, why in unfaithful)
            + f": a virtual push on that axis (at the push prior's size, or at 1, 5 or 20 N) comes out more "
            f"than {cfg.fidelity_tolerance:g} off its size: the model reads the axis off other channels (its "
            "training relation) or snaps small changes to it, and would misreport a push, a contact or a "
            "load there."
        )
        lines.append(warning("Fidelity flags", f"{names}: not deployed", detail))
    passed = [(r.group, html) for r in results if (html := passed_over_html(r, cfg.noise_limit))]
    if passed:
        groups = ", ".join(_e(g) for g, _ in passed)
        summary = f"{groups}: a model cross-validation preferred is not the one deployed"
        lines.append(warning("Passed over", summary, "".join(h for _, h in passed)))
    notes = [f"<li>{_e(n)}</li>" for r in results for n in r.notes]
    if notes:
        lines.append(warning("Not trained", f"{len(notes)} network(s)", f"<ul>{''.join(notes)}</ul>"))
    return "".join(lines)


def _held_out_box(results: Sequence[GroupReport]) -> str:
    """Recorded groups: one line saying how many held-out findings there are, each (`held_out_lines`) with
    its own detail folded below it."""
    items = []
    for r in results:
        for line in held_out_lines(r.group, r.held_out):
            head, _, detail = line.partition(": ")
            what, _, why = detail.partition(": ")
            items.append(f"<details><summary><b>{_e(head)}</b>: {_e(what)}</summary>{_e(why)}</details>")
    if not items:
        return ""
    return warning("Held out (recorded, against labels)", f"{len(items)} finding(s)", "".join(items))


def _no_truth_box(results: Sequence[GroupReport]) -> str:
    """A plain warning where the test logs are recordings: no truth, no oracle, errors against labels."""
    if not results or any(TRUTH in r.tables[h] for r in results for h in _headlines(r)):
        return ""
    detail = (
        "The test logs are recordings of a robot, not simulations. Every error on this page is against "
        "the <i>labels</i> (the expected wrench from the URDF and the motion, exact only where one side of "
        "a sensor's cut touches nothing, and only as good as the URDF's masses), on the labelled samples of "
        "the held-out test logs and segments; nothing here is measured against the true wrench, and there "
        f"is no oracle (noise floor). Beside the models, <i>{_e(LS_AFFINE)}</i> is the plain least-squares "
        "affine map fitted on the training segments (no virtual pushes), the in-situ reference any lab can "
        "compute: it is scored, never deployed."
    )
    return warning("No truth", _e(NO_TRUTH[len("no truth: ") :]), detail)


def _not_calibrated_box(results: Sequence[GroupReport]) -> str:
    """The groups nothing could be calibrated for, and the sensors left out of a group, with why."""
    names = [r.group for r in results if r.not_calibrated]
    names += [f"{r.group}/{s}" for r in results for s in r.left_out]
    if not names:
        return ""
    items = [f"<b>{_e(r.group)}</b>: {_e(r.not_calibrated)}" for r in results if r.not_calibrated]
    items += [f"<b>{_e(r.group)}/{_e(s)}</b>: {_e(why)}" for r in results for s, why in r.left_out.items()]
    detail = (
        f"{'; '.join(items)}. A label needs the joints on the path from the link fixed in the world to the "
        "sensor and those of its free side: without them no sample is exact, so nothing is trained, scored "
        "or exported for these."
    )
    return warning("Not calibrated", _e(", ".join(names)), detail)


_SUMMARY_NOTE = (
    "<p class='note'>Accuracy targets: raw/NN7 &ge; {a:g} and NN7/oracle &le; {b:g}, "
    "against the labels and against the truth (green: met, red: not). The oracle inverts each simulated "
    "sensor's static distortion exactly: its error is the white noise and the hysteresis, the floor of every "
    "memoryless model; the <i>noise floor</i> is the white noise alone (raw - distorted of the simulator's "
    "truth), the floor of a model with memory (play, arx), which can undo the hysteresis. <i>deploy</i>: the "
    "simplest model "
    "unless a more complex one is better on validation by more than train.selection_margin, if not "
    "noise-flagged, else the next of the validation ranking. Labels exist "
    "only where a sensor's switch is 1 (a foot sum: where the contacts are all on the foot or all off it). "
    "Against the truth (simulated logs) every model is scored twice: on the labelled samples (like for "
    "like with the labels) and on all test samples, double support included, where no label exists and "
    "a model interpolates without supervision.</p>"
)

_NOISE_NOTE = (
    "<p class='note'>On quasi-static stretches (the group's FT boards turning slower than {speed:g} "
    "rad/s, a constant contact set, outside guard bands, at least {min_s:g} s), the ratio "
    "std(model output above {hz:g} Hz) / std(raw above {hz:g} Hz) per axis; a model's ratio is its worst "
    "axis (of every part and the sum). 1 = raw's noise passed unchanged, &gt; 1 = noise added, &lt; 1 = "
    "smoothed. <i>signal share</i>: the largest ratio of the true wrench's content above {hz:g} Hz to "
    "raw's (simulated logs); near 0 means the ratio measures noise only.</p>"
)


def _group_section(r: GroupReport, tolerance: float) -> list[str]:

    g = r
    links = [f"training run {_e(r.train_run)}"] if r.train_run else ["no MLflow training run found"]
    for network, mv in sorted(r.model_versions.items()):
        links.append(f"{_e(network)} = registered model {_e(mv['name'])} v{_e(mv['version'])}")
    pair = f" · foot sum: {_e(g.pair)} (sole frame)" if g.pair else ""
    ranking = _e(" < ".join(r.validation_ranking))
    parts = [
        f"<h2 id='{_e(g.group)}'>{_e(g.group)}</h2>",
        f"<p class='note'>sensors: {_e(', '.join(g.sensors))}{pair} · test samples: {g.samples_test} · "
        f"best on validation: <b>{_e(r.best_on_validation)}</b> (ranking: {ranking}) · "
        f"deploy: <b>{_e(r.recommended)}</b> · {' · '.join(links)}</p>",
        _img(r.figures["loss"], f"{g.group}: training loss and validation RMSE per epoch"),
        _img(r.figures["noise"], f"{g.group}: output noise on a quasi-static stretch"),
        cv_section(r.cv),
        fidelity_table(r, tolerance),
        excitation_html(r),
        held_out_html(r.held_out, (r.figures or {}).get("held_out") or {}) if r.held_out else "",
    ]
    for name in g.names:
        if name == g.pair:
            what = "sum of front and rear in the sole frame"
        else:
            what = "part of the foot" if g.pair else "sensor"
        # ids: the group's heading may already be called like its sensor or pair
        parts.append(f"<h3 id='sensor-{_e(name)}'>{_e(name)} <small>({what})</small></h3>")
        for ref in REFERENCES:
            if ref in r.tables[name]:
                tables = [thesis_table(r.tables[name][ref], g.models, m) for m in ("rmse", "mae", "mse")]
                title = REFERENCE_TITLES[ref]
                parts.append(f"<h4>against {title}</h4><div class='tables'>{''.join(tables)}</div>")
        parts.append("<h4>RMSE (global) per experiment type</h4><div class='tables'>")
        for ref, by_kind in r.by_experiment[name].items():
            rows = [[f"{kind} ({ref})"] + [fmt(by_kind[kind].get(m)) for m in g.models] for kind in by_kind]
            parts.append(_table(["experiment", *g.models], rows, "num"))
        parts.append("</div>")
        parts.append(phase_section(r, name))
        fig = r.figures["names"][name]
        parts += [
            _img(fig["rmse"], f"{name}: RMSE per axis of every model (thesis fig. 5.8)"),
            _img(
                fig["timeseries"], f"{name}: calibrated vs expected vs raw on the test logs (figs 5.3, 5.6)"
            ),
            _img(fig["zoom"], f"{name}: zoom per experiment type"),
            _img(fig["residuals"], f"{name}: residuals against the labels (thesis fig. 5.4)"),
        ]
    return parts


def render_html(
    results: Sequence[GroupReport],
    cfg: EvaluateParams,
    figures: Mapping[str, Any],
    availability: Mapping[str, Any] | None = None,
    identification: Mapping[str, Any] | None = None,
) -> str:
    """The report page: summary, flags and overview figures, the noise check, the exact-label
    availability (`pipeline.evaluation.availability`, if given), the identified robot model (the label
    stage's identification.json, if given; its figure ``figures["identified"]``), then one section per
    calibrated group (the others are named, with why, in the summary)."""
    now = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    groups = ", ".join(r.group for r in results)
    uncalibrated = _not_calibrated_box(results)
    answer = answer_table(results)
    results = [r for r in results if r.not_calibrated is None]
    nav = "".join(f"<a href='#{_e(r.group)}'>{_e(r.group)}</a>" for r in results)
    models = list(dict.fromkeys(m for r in results for m in r.models))
    noise_rows = []
    for r in results:
        row = f"<tr><td>{_e(r.group)}</td>" + _cell(r.noise.quasi_static_s) + _cell(r.noise.windows)
        row += _cell(r.noise.signal_fraction)
        for m in models:
            v = r.noise.ratio.get(m)
            row += _cell(v, False, bold=True) if m in r.noise.flagged else _cell(v)
        noise_rows.append(row + "</tr>")
    head = "".join(
        f"<th>{_e(h)}</th>" for h in ["group", "quasi-static s", "stretches", "signal share", *models]
    )
    labels = availability_section(availability)
    labels_link = "<a href='#labels'>Exact-label availability</a>" if labels else ""
    identified = identification_section(identification, figures.get("identified"))
    labels_link += "<a href='#identified'>Identified robot model</a>" if identified else ""
    labels += identified
    parts = [
        "<h1>FT sensor calibration: evaluation on the test logs</h1>",
        f"<p class='meta'>generated {now} · git {_e(_git_commit())} · groups: {_e(groups)} · "
        "errors in N and Nm; global = the 6 components pooled, as in the thesis</p>",
        "<nav><a href='#summary'>Summary and recommendation</a>"
        + ("<a href='#noise'>Deployment noise check</a>" if results else "")
        + f"{labels_link}{nav}<a href='{DEPLOYMENT_PAGE}'>Deployment tests (its own page)</a></nav>",
        "<h2 id='summary'>Summary and recommendation</h2>",
        answer,
        uncalibrated,
    ]
    if not results:  # nothing calibrated: why, and where the labels are exact (nowhere, or too rarely)
        return document("ftcal evaluation report", [*parts, labels])
    parts += [
        _no_truth_box(results),
        _held_out_box(results),
        _flags_box(results, cfg),
        prior_box(results, [m for r in results for m in (r.best_on_validation, NN7) if m]),
        _img(
            figures["overview"],
            "Headline test RMSE (6 axes pooled) of every model per group and headline, log scale",
        ),
        "<h3 id='every-model'>Every model, per headline</h3>",
        summary_table(results, cfg),
        _SUMMARY_NOTE.format(a=cfg.target_raw_over_nn7, b=cfg.target_nn7_over_oracle),
        wbd_section(results),
        "<h2 id='noise'>Deployment noise check</h2>",
        _NOISE_NOTE.format(speed=cfg.still_gyro_rad_s, min_s=cfg.still_min_s, hz=cfg.highpass_hz),
        f'<table class="num"><thead><tr>{head}</tr></thead><tbody>{"".join(noise_rows)}</tbody></table>',
        _img(
            figures["noise"], "Noise amplification ratio per model and group (worst axis); threshold dashed"
        ),
        labels,
    ]
    for r in results:
        parts += _group_section(r, cfg.fidelity_tolerance)
    return document("ftcal evaluation report", parts)


def write_page(
    out: Path,
    reports: Sequence[GroupReport],
    cfg: EvaluateParams,
    availability: Mapping[str, Any] | None = None,
    identification: Mapping[str, Any] | None = None,
) -> list[str]:
    """The two overview figures and index.html into `out` (group figures are already under groups/);
    `availability`: the exact-label counts of `pipeline.evaluation.availability`, if any; `identification`:
    the label stage's identified robot model (its figure already at ``plots/identified_parts.png``)."""
    from pipeline.evaluation.figures import plot_noise_summary, plot_overview

    overview, noise = f"{PLOTS_DIR}/rmse_overview.png", f"{PLOTS_DIR}/noise_amplification.png"
    (out / PLOTS_DIR).mkdir(parents=True, exist_ok=True)
    calibrated = [r for r in reports if r.not_calibrated is None]
    shown = identification and (out / IDENTIFIED_FIGURE).is_file()
    ident = {"identified": IDENTIFIED_FIGURE} if shown else {}
    if not calibrated:  # nothing scored: no figure (the page says why)
        write_text(out / REPORT_FILE, render_html(reports, cfg, ident, availability, identification))
        return [REPORT_FILE]
    plot_overview(calibrated, out / overview)
    plot_noise_summary(calibrated, cfg, out / noise)
    figures = {"overview": overview, "noise": noise} | ident
    write_text(out / REPORT_FILE, render_html(reports, cfg, figures, availability, identification))
    return [overview, noise, REPORT_FILE]
