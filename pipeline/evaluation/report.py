"""The human side of stage `evaluate`: figures (``plots/*.png``), DVC plot data (``plots_data/``) and the
report page ``index.html`` with every table and figure (images by relative path).

Figures, per sensor or foot sum (thesis figs 5.3-5.8): prediction vs expected vs raw (and true) over the
whole test set, a zoom per experiment type, residuals, RMSE per axis of every model side by side; per
group: training and validation loss curves, and one quasi-static stretch showing the noise each model
adds; overall: headline RMSE of every model and the noise amplification ratios.
Nothing here computes a metric: everything comes from `pipeline.stages.evaluate`'s results.
"""

from __future__ import annotations

import csv
import html
import math
import os
import subprocess
from collections.abc import Mapping, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.logs import schema as S

if TYPE_CHECKING:
    from pipeline.stages.evaluate import EvaluateParams, GroupResult

AXIS_UNITS = {"fx": "N", "fy": "N", "fz": "N", "tx": "Nm", "ty": "Nm", "tz": "Nm"}
_GAP_S = 3.0  # s of blank between consecutive logs in the whole-test-set plots
_DPI = 90
# Fixed colours so that a model looks the same in every figure.
COLORS = {
    "raw": "#8c8c8c",
    "affine": "#bcbd22",
    "poly1": "#d9b36c",
    "poly2": "#e0894a",
    "poly3": "#c8553d",
    "poly4": "#8c2d04",
    "nn7": "#1f77b4",
    "nn13": "#d62728",
    "oracle": "#2ca02c",
    "expected": "#000000",
    "true": "#2ca02c",
}


def _color(model: str) -> str:
    return COLORS.get(model, "#9467bd")


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> None:
    """Save a figure atomically and close it."""
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.png")
    try:
        fig.savefig(tmp, dpi=_DPI)  # every figure is laid out with tight_layout (a second pass costs seconds)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    finally:
        _plt().close(fig)


def _write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with tmp.open("w", newline="", encoding="utf-8") as fh:
            writer = csv.writer(fh)
            writer.writerow(header)
            for row in rows:
                writer.writerow(
                    ["" if (isinstance(v, float) and not math.isfinite(v)) or v is None else v for v in row]
                )
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


# --- the time axis of the whole test set ---------------------------------------------------------


def concatenated_time(
    log: np.ndarray, time_s: np.ndarray
) -> tuple[np.ndarray, list[tuple[str, float, float]]]:
    """(N,) s: the test logs laid end to end (each from 0, _GAP_S apart), and [(log, start, end)] spans."""
    x = np.empty(len(time_s))
    spans = []
    offset = 0.0
    for start, stop in _runs(log):
        t = time_s[start:stop] - time_s[start]
        x[start:stop] = t + offset
        spans.append((str(log[start]), offset, offset + float(t[-1])))
        offset += float(t[-1]) + _GAP_S
    return x, spans


def _runs(values: np.ndarray) -> list[tuple[int, int]]:
    if len(values) == 0:
        return []
    edges = np.flatnonzero(values[1:] != values[:-1]) + 1
    return list(zip(np.r_[0, edges].tolist(), np.r_[edges, len(values)].tolist(), strict=True))


def _broken(x: np.ndarray, y: np.ndarray, segments: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """x, y with a NaN inserted where a contiguous stretch ends, so that lines do not bridge gaps."""
    cuts = np.flatnonzero(segments[1:] != segments[:-1]) + 1
    return np.insert(x.astype(float), cuts, np.nan), np.insert(y.astype(float), cuts, np.nan)


# --- figures -------------------------------------------------------------------------------------


def _shown_models(r: GroupResult) -> list[str]:
    """The models drawn in the time-series figures: NN7 and the recommended model (thesis figs 5.3, 5.6)."""
    shown = [m for m in ("nn7",) if m in r.inputs.models]
    if r.recommended and r.recommended not in shown and r.recommended != "raw":
        shown.append(r.recommended)
    return shown


def plot_timeseries(r: GroupResult, name: str, path: Path) -> None:
    """Prediction vs expected vs raw (and true) of one sensor or sum over the whole test set, 6 axes."""
    PRED = S.PRED

    plt = _plt()
    f = r.inputs.frame
    x, spans = concatenated_time(f[S.LOG].to_numpy(), f[S.TIME].to_numpy())
    seg = r.inputs.segments
    fig, axes = plt.subplots(6, 1, figsize=(16, 14), sharex=True)
    series = [("raw", f"{PRED}.raw", 0.8, "-")]
    series += [(m, f"{PRED}.{m}", 0.8, "-") for m in _shown_models(r)]
    series += [("expected", S.EXPECTED, 1.0, "-")]
    if r.inputs.has_truth:
        series.append(("true", S.TRUE, 0.8, "--"))
    for a, axis in enumerate(S.WRENCH_AXES):
        ax = axes[a]
        for label, quantity, width, style in series:
            col = f"{quantity}.{name}.{axis}"
            xs, ys = _broken(x, f[col].to_numpy(), seg)
            ax.plot(xs, ys, style, lw=width, color=_color(label), label=label, rasterized=True)
        ax.set_ylabel(f"{axis} [{AXIS_UNITS[axis]}]")
        ax.grid(alpha=0.3)
        for log, start, _end in spans:
            ax.axvline(start, color="k", lw=0.5, alpha=0.4)
            if a == 0:
                ax.text(start, 1.02, log, transform=ax.get_xaxis_transform(), fontsize=8, va="bottom")
    axes[0].legend(loc="upper right", ncol=len(series), fontsize=8)
    axes[-1].set_xlabel("time, test logs end to end [s]")
    fig.suptitle(f"{name}: calibrated vs expected (label) vs raw wrench on the test logs")
    fig.tight_layout()
    _save(fig, path)


def _zoom_window(f: Any, kind: str, zoom_s: float) -> np.ndarray:
    """Row indices of a `zoom_s` window in the middle of the first test log of experiment type `kind`."""
    from pipeline.stages.evaluate import EXPERIMENT

    rows = np.flatnonzero(f[EXPERIMENT].to_numpy() == kind)
    log = f[S.LOG].to_numpy()[rows[0]]
    rows = rows[f[S.LOG].to_numpy()[rows] == log]
    t = f[S.TIME].to_numpy()[rows]
    mid = 0.5 * (t[0] + t[-1])
    return rows[(t >= mid - zoom_s / 2) & (t <= mid + zoom_s / 2)]


def plot_zoom(r: GroupResult, name: str, zoom_s: float, path: Path) -> None:
    """A `zoom_s` window per experiment type (thesis figs 5.3b-c): 6 axes x experiment types."""
    PRED = S.PRED

    plt = _plt()
    f = r.inputs.frame
    kinds = r.inputs.experiments
    fig, axes = plt.subplots(6, len(kinds), figsize=(4.2 * len(kinds) + 1, 14), squeeze=False)
    series = [("raw", f"{PRED}.raw", "-")] + [(m, f"{PRED}.{m}", "-") for m in _shown_models(r)]
    series += [("expected", S.EXPECTED, "-")]
    if r.inputs.has_truth:
        series.append(("true", S.TRUE, "--"))
    for k, kind in enumerate(kinds):
        rows = _zoom_window(f, kind, zoom_s)
        t = f[S.TIME].to_numpy()[rows]
        seg = r.inputs.segments[rows]
        for a, axis in enumerate(S.WRENCH_AXES):
            ax = axes[a, k]
            for label, quantity, style in series:
                xs, ys = _broken(t, f[f"{quantity}.{name}.{axis}"].to_numpy()[rows], seg)
                ax.plot(xs, ys, style, lw=1.0, color=_color(label), label=label)
            ax.grid(alpha=0.3)
            if k == 0:
                ax.set_ylabel(f"{axis} [{AXIS_UNITS[axis]}]")
            if a == 0:
                ax.set_title(f"{kind} ({f['log'].to_numpy()[rows[0]] if len(rows) else ''})", fontsize=9)
        axes[-1, k].set_xlabel("time in log [s]")
    axes[0, -1].legend(loc="upper right", fontsize=7)
    fig.suptitle(f"{name}: zoom of {zoom_s:g} s per experiment type")
    fig.tight_layout()
    _save(fig, path)


def plot_residuals(r: GroupResult, name: str, path: Path) -> None:
    """Prediction minus label over the test set (thesis fig. 5.4): with raw (left), models only (right)."""
    from pipeline.stages.evaluate import ORACLE, PRED

    plt = _plt()
    f = r.inputs.frame
    x, spans = concatenated_time(f[S.LOG].to_numpy(), f[S.TIME].to_numpy())
    seg = r.inputs.segments
    # the oracle first, so that it lies behind the models it is the floor of
    models = ([ORACLE] if ORACLE in r.inputs.models else []) + _shown_models(r)
    fig, axes = plt.subplots(6, 2, figsize=(16, 14), sharex=True)
    for a, axis in enumerate(S.WRENCH_AXES):
        label = f[f"{S.EXPECTED}.{name}.{axis}"].to_numpy()
        for col, with_raw in ((0, True), (1, False)):
            ax = axes[a, col]
            for m in (["raw"] if with_raw else []) + models:
                xs, ys = _broken(x, f[f"{PRED}.{m}.{name}.{axis}"].to_numpy() - label, seg)
                alpha = 0.6 if m == ORACLE else 1.0
                ax.plot(xs, ys, lw=0.6, color=_color(m), label=m, alpha=alpha, rasterized=True)
            ax.axhline(0, color="k", lw=0.5)
            ax.grid(alpha=0.3)
            for _log, start, _end in spans:
                ax.axvline(start, color="k", lw=0.5, alpha=0.4)
        axes[a, 0].set_ylabel(f"{axis} residual [{AXIS_UNITS[axis]}]")
    axes[0, 0].set_title("prediction - label, with raw")
    axes[0, 1].set_title("prediction - label, calibrated models only")
    axes[0, 0].legend(loc="upper right", fontsize=8)
    axes[0, 1].legend(loc="upper right", fontsize=8)
    for ax in axes[-1]:
        ax.set_xlabel("time, test logs end to end [s] (only where the label is exact)")
    fig.suptitle(f"{name}: residuals against the labels on the test logs")
    fig.tight_layout()
    _save(fig, path)


def plot_rmse_axes(r: GroupResult, name: str, path: Path) -> None:
    """RMSE per axis of every model side by side (thesis fig. 5.8), force and torque, labels and truth."""
    plt = _plt()
    refs = list(r.tables[name])
    models = r.inputs.models
    fig, axes = plt.subplots(len(refs), 2, figsize=(15, 4.2 * len(refs)), squeeze=False)
    width = 0.8 / len(models)
    for i, ref in enumerate(refs):
        for j, (part, keys) in enumerate(
            (("force", ("fx", "fy", "fz", "force")), ("torque", ("tx", "ty", "tz", "torque")))
        ):
            ax = axes[i, j]
            for k, m in enumerate(models):
                values = [r.tables[name][ref][m].get(f"rmse_{key}", math.nan) for key in keys]
                pos = np.arange(len(keys)) + (k - (len(models) - 1) / 2) * width
                ax.bar(pos, values, width, color=_color(m), label=m)
            ax.set_xticks(np.arange(len(keys)), [*keys[:3], f"{part} (pooled)"])
            ax.set_yscale("log")
            ax.set_ylabel(f"RMSE [{'N' if part == 'force' else 'Nm'}]")
            ax.set_title(f"{part} RMSE against {ref}")
            ax.grid(alpha=0.3, axis="y", which="both")
    axes[0, 1].legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9)
    fig.suptitle(f"{name}: test RMSE per axis of every model (log scale)")
    fig.tight_layout()
    _save(fig, path)


def plot_losses(r: GroupResult, path: Path) -> None:
    """Training loss and validation RMSE per epoch of each network's best trial (thesis figs 5.2, 5.20)."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.2))
    for network, rows in sorted(r.histories.items()):
        epochs = np.array([h["epoch"] for h in rows]) + 1
        loss = np.array([h["loss"] for h in rows])
        val = np.array([h["val_rmse"] for h in rows])
        axes[0].plot(epochs, loss, "-o", ms=3, color=_color(network), label=network)
        axes[1].plot(epochs, val, "-o", ms=3, color=_color(network), label=network)
        best = int(np.nanargmin(val))
        axes[1].plot(epochs[best], val[best], "*", ms=12, color=_color(network))
    if not r.histories:
        for ax in axes:
            ax.text(0.5, 0.5, "no loss history found", ha="center", va="center", transform=ax.transAxes)
    axes[0].set_title("training loss (switched MSE, N^2 and Nm^2 mixed)")
    axes[1].set_title("validation RMSE of every exact label (* = kept epoch)")
    for ax in axes:
        ax.set_xlabel("epoch")
        ax.set_yscale("log")
        ax.grid(alpha=0.3, which="both")
        if r.histories:
            ax.legend()
    fig.suptitle(f"{r.group}: loss curves of the best trial (source: {r.history_source})")
    fig.tight_layout()
    _save(fig, path)


def _noise_model(r: GroupResult) -> str | None:
    """The model whose noise the example shows: the worst flagged one, else the noisiest network."""
    from pipeline.stages.evaluate import ORACLE

    ratios = {m: v for m, v in r.noise.ratio.items() if v is not None and m not in (ORACLE, "raw")}
    if not ratios:
        return None
    flagged = [m for m in r.noise.flagged if m in ratios]
    return max(flagged or ratios, key=lambda m: ratios[m])


def plot_noise_example(r: GroupResult, cfg: EvaluateParams, path: Path) -> None:
    """The output of raw, the noisiest model and the recommended one on a quasi-static stretch: signal
    (top) and its high-frequency part (bottom), on the noisiest model's worst axis."""
    from pipeline.stages.evaluate import PRED, highpass

    plt = _plt()
    fig, axes = plt.subplots(2, 1, figsize=(13, 6), sharex=True)
    model = _noise_model(r)
    mask = r.noise.mask
    if model is None or not mask.any():
        axes[0].text(
            0.5, 0.5, "no quasi-static stretch in the test logs", ha="center", transform=axes[0].transAxes
        )
        fig.tight_layout()
        _save(fig, path)
        return
    channel = r.noise.worst_channel[model]
    name, axis = channel.rsplit(".", 1)
    # the longest quasi-static run, at most 3 s of it
    runs = [(a, b) for a, b in _runs(mask) if mask[a]]
    start, stop = max(runs, key=lambda ab: ab[1] - ab[0])
    stop = min(stop, start + int(3 * r.inputs.fs))
    f = r.inputs.frame
    rows = slice(start, stop)
    t = f[S.TIME].to_numpy()[rows]
    shown = list(dict.fromkeys(["raw", "nn7", "nn13", model, r.recommended or "raw"]))
    shown = [m for m in shown if m in r.inputs.models]
    seg = r.inputs.segments
    for m in shown:
        col = f"{PRED}.{m}.{name}.{axis}"
        y = f[col].to_numpy()
        hf = highpass(y[:, None], seg, r.inputs.fs, cfg.highpass_hz, cfg.highpass_order)[:, 0]
        ratio = r.noise.per_channel.get(m, {}).get(channel)
        label = f"{m} (noise x{ratio:.2f})" if ratio is not None else m
        axes[0].plot(t, y[rows], lw=1, color=_color(m), label=label)
        axes[1].plot(t, hf[rows], lw=1, color=_color(m), label=label)
    axes[0].set_ylabel(f"{axis} [{AXIS_UNITS[axis]}]")
    axes[1].set_ylabel(f"{axis} above {cfg.highpass_hz:g} Hz [{AXIS_UNITS[axis]}]")
    axes[1].set_xlabel(f"time in log {f['log'].to_numpy()[start]} [s]")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    fig.suptitle(f"{r.group}: output noise on a quasi-static stretch ({name}.{axis})")
    fig.tight_layout()
    _save(fig, path)


def plot_noise_summary(results: Sequence[GroupResult], cfg: EvaluateParams, path: Path) -> None:
    """Noise amplification ratio (worst axis) of every model of every group, threshold line."""
    plt = _plt()
    models = list(dict.fromkeys(m for r in results for m in r.inputs.models))
    fig, ax = plt.subplots(figsize=(max(8, 2.2 * len(results)), 4.8))
    width = 0.8 / max(len(models), 1)
    for k, m in enumerate(models):
        values = [r.noise.ratio.get(m) for r in results]
        values = [math.nan if v is None else v for v in values]
        pos = np.arange(len(results)) + (k - (len(models) - 1) / 2) * width
        ax.bar(pos, values, width, color=_color(m), label=m)
    ax.axhline(cfg.noise_threshold, color="r", ls="--", lw=1.2, label=f"threshold {cfg.noise_threshold:g}")
    ax.axhline(1.0, color="k", lw=0.6)
    ax.set_xticks(np.arange(len(results)), [r.group for r in results])
    largest = max((v for r in results for v in r.noise.ratio.values() if v is not None), default=1.0)
    if largest > 2.5 * cfg.noise_threshold:
        ax.set_yscale("log")  # a very noisy model would flatten the others
    else:
        ax.set_ylim(0, max(largest, cfg.noise_threshold) * 1.15)
    ax.set_ylabel("std(HF model) / std(HF raw), worst axis")
    ax.set_title(f"Noise amplification on quasi-static stretches (high-pass {cfg.highpass_hz:g} Hz)")
    ax.grid(alpha=0.3, axis="y", which="both")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9)
    fig.tight_layout()
    _save(fig, path)


def plot_overview(results: Sequence[GroupResult], path: Path) -> None:
    """Headline RMSE (global) of every model per group, against labels and truth (log scale)."""
    from pipeline.stages.evaluate import REFERENCE_TITLES, REFERENCES

    plt = _plt()
    refs = [ref for ref in REFERENCES if any(ref in r.tables[r.inputs.headline] for r in results)]
    models = list(dict.fromkeys(m for r in results for m in r.inputs.models))
    fig, axes = plt.subplots(1, len(refs), figsize=(7.5 * len(refs) + 1.5, 4.8), squeeze=False)
    width = 0.8 / max(len(models), 1)
    for i, ref in enumerate(refs):
        ax = axes[0, i]
        for k, m in enumerate(models):
            values = [r.headline_rmse(ref, m) for r in results]
            values = [math.nan if v is None else v for v in values]
            ax.bar(
                np.arange(len(results)) + (k - (len(models) - 1) / 2) * width,
                values,
                width,
                color=_color(m),
                label=m,
            )
        ax.set_xticks(np.arange(len(results)), [r.inputs.headline for r in results], rotation=20)
        ax.set_yscale("log")
        ax.set_ylabel("RMSE, 6 axes pooled [N, Nm]")
        ax.set_title(f"test RMSE against {REFERENCE_TITLES[ref]}")
        ax.grid(alpha=0.3, axis="y", which="both")
    axes[0, -1].legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9)
    fig.tight_layout()
    _save(fig, path)


# --- DVC plot data -------------------------------------------------------------------------------


def write_plot_data(out: Path, results: Sequence[GroupResult]) -> list[str]:
    """CSV series for `dvc plots` (see dvc.yaml), one file per group: plots_data/rmse_labels/<group>.csv
    and rmse_truth/<group>.csv (model, rmse: the headline's global RMSE), noise/<group>.csv (model, ratio,
    ratio_rms), loss/<group>_<network>.csv (epoch from 1, train_loss, val_rmse)."""
    from pipeline.stages.evaluate import LABELS, PLOTS_DATA_DIR, TRUTH

    base = out / PLOTS_DATA_DIR
    subdirs = ("rmse_labels", "rmse_truth", "noise", "loss")
    for sub in subdirs:
        (base / sub).mkdir(parents=True, exist_ok=True)
        for old in (base / sub).glob("*.csv"):
            old.unlink()
    files = []

    def write(sub: str, stem: str, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
        _write_csv(base / sub / f"{stem}.csv", header, rows)
        files.append(f"{PLOTS_DATA_DIR}/{sub}/{stem}.csv")

    for r in results:
        for sub, ref in (("rmse_labels", LABELS), ("rmse_truth", TRUTH)):
            rows = [
                [m, r.headline_rmse(ref, m)] for m in r.inputs.models if r.headline_rmse(ref, m) is not None
            ]
            if rows:
                write(sub, r.group, ["model", "rmse"], rows)
        rows = [[m, r.noise.ratio.get(m), r.noise.ratio_rms.get(m)] for m in r.inputs.models]
        write("noise", r.group, ["model", "ratio", "ratio_rms"], rows)
        for network, history in r.histories.items():
            rows = [[int(h["epoch"]) + 1, h["loss"], h["val_rmse"]] for h in history]
            write("loss", f"{r.group}_{network}", ["epoch", "train_loss", "val_rmse"], rows)
    return files


# --- the page ------------------------------------------------------------------------------------


def fmt(value: Any) -> str:
    """A table number: 2 decimals from 1 up (as the thesis), 3 significant digits below; n/a if missing."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    v = float(value)
    if abs(v) >= 1e5:
        return f"{v:.3e}"
    if abs(v) >= 1:
        return f"{v:.2f}"
    return f"{v:.3g}"


def _e(text: Any) -> str:
    return html.escape(str(text))


def _table(
    header: Sequence[str], rows: Sequence[Sequence[str]], cls: str = "", raw_html: bool = False
) -> str:
    """An HTML table; cells are escaped unless `raw_html` (then the caller escaped them)."""
    cell = (lambda c: c) if raw_html else _e
    head = "".join(f"<th>{_e(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{cell(c)}</td>" for c in row) + "</tr>" for row in rows)
    return f'<table class="{cls}"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


_METRIC_ROWS = [("global", ""), ("force", "_force"), ("torque", "_torque")] + [
    (a, f"_{a}") for a in S.WRENCH_AXES
]


def thesis_table(tables: Mapping[str, Mapping[str, float]], models: Sequence[str], metric: str) -> str:
    """Thesis layout (tables 5.1-5.24): rows = MSE/MAE/RMSE global, force, torque, axes; columns = models.
    The lowest value of each row (oracle excluded) is bold."""
    from pipeline.stages.evaluate import ORACLE

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


def _img(src: str, alt: str) -> str:
    src, alt = _e(src), _e(alt)
    return (
        f'<figure><a href="{src}"><img src="{src}" alt="{alt}" loading="lazy"></a>'
        f"<figcaption>{alt}</figcaption></figure>"
    )


def _git_commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5, check=False
        )
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:0 auto;max-width:1500px;
 padding:0 24px 60px;color:#222}
h1{margin-bottom:4px} h2{border-bottom:2px solid #ddd;padding-bottom:4px;margin-top:48px}
h3{margin-top:28px} h4{margin:18px 0 6px}
.meta{color:#666;font-size:13px}
table{border-collapse:collapse;margin:6px 0 14px;font-size:13px}
th,td{border:1px solid #ccc;padding:3px 8px;text-align:right;white-space:nowrap}
th{background:#f2f2f2;white-space:normal;text-align:center}
td:first-child,th:first-child{text-align:left} td.deploy{text-align:left}
table.num td{font-variant-numeric:tabular-nums}
.ok{background:#e3f4e3} .bad{background:#fbe0e0}
.flags{border:2px solid #c62828;background:#fdecea;padding:10px 16px;border-radius:6px;margin:14px 0}
.flags.none{border-color:#2e7d32;background:#edf7ed}
.tables{display:flex;flex-wrap:wrap;gap:22px;align-items:flex-start}
figure{margin:10px 0 18px} figure img{max-width:100%;border:1px solid #ddd}
figcaption{font-size:12px;color:#555}
nav{font-size:13px;columns:3;background:#fafafa;border:1px solid #eee;padding:8px 16px}
nav a{display:block} .note{font-size:13px;color:#444;max-width:1100px}
"""


def _cell(value: Any, good: bool | None = None, bold: bool = False) -> str:
    """A <td> with a number, green/red when `good` says whether it meets its target."""
    text = _e(fmt(value))
    text = f"<b>{text}</b>" if bold else text
    cls = "" if good is None else (' class="ok"' if good else ' class="bad"')
    return f"<td{cls}>{text}</td>"


def summary_table(results: Sequence[GroupResult], cfg: EvaluateParams) -> str:
    """One row per group: headline RMSE of raw, the best-on-validation model, NN7 and the oracle against
    labels and truth; the acceptance ratios; the networks' noise ratios; the model to deploy."""
    from pipeline.stages.evaluate import LABELS, NN7, NN13, ORACLE, REFERENCE_TITLES, REFERENCES

    refs = [ref for ref in REFERENCES if any(ref in r.tables[r.inputs.headline] for r in results)]
    head1 = "<tr><th rowspan=2>group</th><th rowspan=2>sensor / sum</th>"
    head2 = "<tr>"
    for ref in refs:
        head1 += f"<th colspan=4>RMSE against {REFERENCE_TITLES[ref]}</th>"
        head2 += "<th>raw</th><th>best on val.</th><th>NN7</th><th>oracle</th>"
    for ref in refs:
        head1 += f"<th colspan=2>ratios, {REFERENCE_TITLES[ref]}</th>"
        head2 += "<th>raw / NN7</th><th>NN7 / oracle</th>"
    head1 += (
        "<th colspan=2>noise ratio</th><th rowspan=2>best on validation</th><th rowspan=2>deploy</th></tr>"
    )
    head2 += "<th>NN7</th><th>NN13</th></tr>"
    body = []
    for r in results:
        ratios = r.ratios()
        best = r.best_on_validation
        row = f"<tr><td>{_e(r.group)}</td><td>{_e(r.inputs.headline)}</td>"
        for ref in refs:
            row += _cell(r.headline_rmse(ref, "raw")) + _cell(r.headline_rmse(ref, best) if best else None)
            row += _cell(r.headline_rmse(ref, NN7)) + _cell(r.headline_rmse(ref, ORACLE))
        for ref in refs:
            a, b = ratios["raw_over_nn7"][ref], ratios["nn7_over_oracle"][ref]
            row += _cell(a, None if a is None else a >= cfg.target_raw_over_nn7)
            row += _cell(b, None if b is None else b <= cfg.target_nn7_over_oracle)
        for m in (NN7, NN13):
            v = r.noise.ratio.get(m)
            row += _cell(v, None if v is None else v <= cfg.noise_threshold)
        rec = r.recommended or "none"
        notes = ["best on validation is noisy"] if rec != best else []
        rec_rmse, raw_rmse = r.headline_rmse(LABELS, rec), r.headline_rmse(LABELS, "raw")
        worse = rec_rmse is not None and raw_rmse is not None and rec_rmse > raw_rmse
        if worse:
            notes.append("worse than raw on the test logs: validation does not cover them")
        note = f" <small>({'; '.join(notes)})</small>" if notes else ""
        cls = "deploy bad" if worse else "deploy"
        row += f"<td>{_e(best)}</td><td class='{cls}'><b>{_e(rec)}</b>{note}</td></tr>"
        body.append(row)
    return f'<table class="num summary"><thead>{head1}{head2}</thead><tbody>{"".join(body)}</tbody></table>'


def _flags_box(results: Sequence[GroupResult], cfg: EvaluateParams) -> str:
    flagged = [(r.group, m, r.noise.ratio.get(m)) for r in results for m in r.noise.flagged]
    if not flagged:
        return (
            "<div class='flags none'><b>Noise flags:</b> none (no model's output noise above "
            f"{cfg.noise_threshold:g}x raw's on quasi-static stretches).</div>"
        )
    items = ", ".join(f"<b>{_e(g)}/{_e(m)}</b> (x{_e(fmt(v))})" for g, m, v in flagged)
    return (
        f"<div class='flags'><b>Noise flags:</b> {items}: output noise above "
        f"{cfg.noise_threshold:g}x raw's on quasi-static stretches (thesis chapter 6, Test A: the "
        "13-input network passed the IMU noise through and was unusable on the robot). "
        "Not recommended for deployment.</div>"
    )


_SUMMARY_NOTE = (
    "<p class='note'>Accuracy targets: raw/NN7 &ge; {a:g} and NN7/oracle &le; {b:g}, "
    "against the labels and against the truth (green: met, red: not). The oracle inverts each simulated "
    "sensor's static distortion exactly: its error is the noise floor. <i>deploy</i>: the model with the "
    "lowest validation error unless noise-flagged, else the next of the validation ranking. Labels exist "
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


def _group_section(r: GroupResult, figures: Mapping[str, Any]) -> list[str]:
    from pipeline.stages.evaluate import REFERENCE_TITLES, REFERENCES

    g = r.inputs
    links = [f"training run {_e(r.train_run)}"] if r.train_run else ["no MLflow training run found"]
    for network, mv in sorted(r.model_versions.items()):
        links.append(f"{_e(network)} = registered model {_e(mv['name'])} v{_e(mv['version'])}")
    pair = f" · foot sum: {_e(g.pair)} (sole frame)" if g.pair else ""
    ranking = _e(" < ".join(r.validation_ranking))
    parts = [
        f"<h2 id='{_e(g.group)}'>{_e(g.group)}</h2>",
        f"<p class='note'>sensors: {_e(', '.join(g.sensors))}{pair} · test samples: {len(g.frame)} · "
        f"best on validation: <b>{_e(r.best_on_validation)}</b> (ranking: {ranking}) · "
        f"deploy: <b>{_e(r.recommended)}</b> · {' · '.join(links)}</p>",
        _img(figures["groups"][g.group]["loss"], f"{g.group}: training loss and validation RMSE per epoch"),
        _img(figures["groups"][g.group]["noise"], f"{g.group}: output noise on a quasi-static stretch"),
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
        fig = figures["names"][name]
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
    results: Sequence[GroupResult], doc: Mapping[str, Any], cfg: EvaluateParams, figures: Mapping[str, Any]
) -> str:
    """The report page: summary, flags and overview figures, the noise check, then one section per group."""
    now = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    groups = ", ".join(r.group for r in results)
    nav = "".join(f"<a href='#{_e(r.group)}'>{_e(r.group)}</a>" for r in results)
    models = list(dict.fromkeys(m for r in results for m in r.inputs.models))
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
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        f"<title>ftcal evaluation report</title><style>{_CSS}</style></head><body>",
        "<h1>FT sensor calibration: evaluation on the test logs</h1>",
        f"<p class='meta'>generated {now} · git {_e(_git_commit())} · groups: {_e(groups)} · "
        "errors in N and Nm; global = the 6 components pooled, as in the thesis</p>",
        "<nav><a href='#summary'>Summary and recommendation</a><a href='#noise'>Deployment noise check</a>"
        f"{nav}</nav>",
        "<h2 id='summary'>Summary and recommendation</h2>",
        _flags_box(results, cfg),
        summary_table(results, cfg),
        _SUMMARY_NOTE.format(a=cfg.target_raw_over_nn7, b=cfg.target_nn7_over_oracle),
        _img(figures["overview"], "Headline test RMSE (6 axes pooled) of every model per group, log scale"),
        "<h2 id='noise'>Deployment noise check</h2>",
        _NOISE_NOTE.format(speed=cfg.still_gyro_rad_s, min_s=cfg.still_min_s, hz=cfg.highpass_hz),
        f'<table class="num"><thead><tr>{head}</tr></thead><tbody>{"".join(noise_rows)}</tbody></table>',
        _img(
            figures["noise"], "Noise amplification ratio per model and group (worst axis); threshold dashed"
        ),
    ]
    for r in results:
        parts += _group_section(r, figures)
    parts.append("</body></html>")
    return "\n".join(parts)


def write_all(
    out: Path,
    results: Sequence[GroupResult],
    doc: Mapping[str, Any],
    cfg: EvaluateParams,
    progress: Any = None,
) -> list[str]:
    """Write plots/*.png, plots_data/*.csv and index.html into `out`; return the files written (relative)."""
    from pipeline.stages.evaluate import PLOTS_DIR, REPORT_FILE

    plots = out / PLOTS_DIR
    plots.mkdir(parents=True, exist_ok=True)
    for old in plots.glob("*.png"):
        old.unlink()
    jobs: list[tuple[str, Any]] = []
    figures: dict[str, Any] = {
        "overview": f"{PLOTS_DIR}/rmse_overview.png",
        "noise": f"{PLOTS_DIR}/noise_amplification.png",
        "groups": {},  # group -> {loss, noise}
        "names": {},  # sensor or pair -> {rmse, timeseries, zoom, residuals}
    }
    jobs.append((figures["overview"], lambda p: plot_overview(results, p)))
    jobs.append((figures["noise"], lambda p: plot_noise_summary(results, cfg, p)))
    for r in results:
        group_figs = {"loss": f"{PLOTS_DIR}/{r.group}_loss.png", "noise": f"{PLOTS_DIR}/{r.group}_noise.png"}
        figures["groups"][r.group] = group_figs
        jobs.append((group_figs["loss"], lambda p, r=r: plot_losses(r, p)))
        jobs.append((group_figs["noise"], lambda p, r=r: plot_noise_example(r, cfg, p)))
        for name in r.inputs.names:
            figs = {
                kind: f"{PLOTS_DIR}/{name}_{kind}.png" for kind in ("rmse", "timeseries", "zoom", "residuals")
            }
            figures["names"][name] = figs
            jobs.append((figs["rmse"], lambda p, r=r, n=name: plot_rmse_axes(r, n, p)))
            jobs.append((figs["timeseries"], lambda p, r=r, n=name: plot_timeseries(r, n, p)))
            jobs.append((figs["zoom"], lambda p, r=r, n=name: plot_zoom(r, n, cfg.zoom_s, p)))
            jobs.append((figs["residuals"], lambda p, r=r, n=name: plot_residuals(r, n, p)))
    task = progress.add_task("evaluate: plots", total=len(jobs)) if progress is not None else None
    files = []
    for rel, job in jobs:
        job(out / rel)
        files.append(rel)
        if task is not None:
            progress.advance(task)
    files += write_plot_data(out, results)
    page = render_html(results, doc, cfg, figures)
    tmp = out / f".{REPORT_FILE}.{os.getpid()}.tmp"
    try:
        tmp.write_text(page, encoding="utf-8")
        os.replace(tmp, out / REPORT_FILE)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    files.append(REPORT_FILE)
    return files
