"""The human side of stage `evaluate`: figures (``plots/*.png``), DVC plot data (``plots_data/``) and the
report page ``index.html`` with every table and figure (images by relative path).

Figures, per sensor or foot sum (thesis figs 5.3-5.8): prediction vs expected vs raw (and true) over the
whole test set, a zoom per experiment type, residuals, RMSE per axis of every model side by side; per
group: training and validation loss curves, and one quasi-static stretch showing the noise each model
adds; overall: headline RMSE of every model and the noise amplification ratios.
Nothing here computes a metric: everything comes from `pipeline.stages.evaluate`'s results.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.calib.params import LS_AFFINE
from pipeline.calib.registry import RAW, colour
from pipeline.core.io import write_atomic, write_csv
from pipeline.evaluation.noise import highpass
from pipeline.evaluation.params import (
    EXPERIMENT,
    GROUPS_DIR,
    LABELS,
    NN7,
    NN13,
    ORACLE,
    PLOTS_DATA_DIR,
    PLOTS_DIR,
    REFERENCE_TITLES,
    REFERENCES,
    TRUTH,
)
from pipeline.logs import schema as S
from pipeline.logs.schema import PRED

if TYPE_CHECKING:
    from pipeline.evaluation.params import EvaluateParams
    from pipeline.evaluation.results import GroupReport, GroupResult

AXIS_UNITS = {"fx": "N", "fy": "N", "fz": "N", "tx": "Nm", "ty": "Nm", "tz": "Nm"}
_GAP_S = 3.0  # s of blank between consecutive logs in the whole-test-set plots
_DPI = 90
# Fixed colours so that a model looks the same in every figure: a family's from the registry, and these.
COLORS = {
    "oracle": "#2ca02c",
    LS_AFFINE: "#17becf",  # recorded logs: the plain least-squares affine map, the lab's reference
    "expected": "#000000",
    "true": "#2ca02c",
}


def _color(model: str) -> str:
    return COLORS.get(model) or colour(model)


def pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: Path) -> None:
    """Save a figure atomically and close it."""
    try:
        # every figure is laid out with tight_layout (a second pass costs seconds)
        write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=_DPI))
    finally:
        pyplot().close(fig)


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
    shown = [m for m in (NN7,) if m in r.inputs.models]
    if r.recommended and r.recommended not in shown and r.recommended != "raw":
        shown.append(r.recommended)
    return shown


def plot_timeseries(r: GroupResult, name: str, path: Path) -> None:
    """Prediction vs expected vs raw (and true) of one sensor or sum over the whole test set, 6 axes."""
    PRED = S.PRED

    plt = pyplot()
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
    save_figure(fig, path)


def _zoom_window(f: Any, kind: str, zoom_s: float) -> np.ndarray:
    """Row indices of a `zoom_s` window in the middle of the first test log of experiment type `kind`."""

    rows = np.flatnonzero(f[EXPERIMENT].to_numpy() == kind)
    log = f[S.LOG].to_numpy()[rows[0]]
    rows = rows[f[S.LOG].to_numpy()[rows] == log]
    t = f[S.TIME].to_numpy()[rows]
    mid = 0.5 * (t[0] + t[-1])
    return rows[(t >= mid - zoom_s / 2) & (t <= mid + zoom_s / 2)]


def plot_zoom(r: GroupResult, name: str, zoom_s: float, path: Path) -> None:
    """A `zoom_s` window per experiment type (thesis figs 5.3b-c): 6 axes x experiment types."""
    PRED = S.PRED

    plt = pyplot()
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
    save_figure(fig, path)


def plot_residuals(r: GroupResult, name: str, path: Path) -> None:
    """Prediction minus label over the test set (thesis fig. 5.4): with raw (left), models only (right)."""

    plt = pyplot()
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
    save_figure(fig, path)


def plot_rmse_axes(r: GroupResult, name: str, path: Path) -> None:
    """RMSE per axis of every model side by side (thesis fig. 5.8), force and torque, labels and truth."""
    plt = pyplot()
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
    save_figure(fig, path)


def plot_losses(r: GroupResult, path: Path) -> None:
    """Training loss and validation RMSE per epoch of each network's best trial (thesis figs 5.2, 5.20)."""
    plt = pyplot()
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
    save_figure(fig, path)


def _noise_model(r: GroupResult) -> str | None:
    """The model whose noise the example shows: the worst flagged one, else the noisiest network."""

    ratios = {m: v for m, v in r.noise.ratio.items() if v is not None and m not in (ORACLE, "raw")}
    if not ratios:
        return None
    flagged = [m for m in r.noise.flagged if m in ratios]
    return max(flagged or ratios, key=lambda m: ratios[m])


def plot_noise_example(r: GroupResult, cfg: EvaluateParams, path: Path) -> None:
    """The output of raw, the noisiest model and the recommended one on a quasi-static stretch: signal
    (top) and its high-frequency part (bottom), on the noisiest model's worst axis."""

    plt = pyplot()
    fig, axes = plt.subplots(2, 1, figsize=(13, 6), sharex=True)
    model = _noise_model(r)
    mask = r.noise.mask
    if model is None or not mask.any():
        axes[0].text(
            0.5, 0.5, "no quasi-static stretch in the test logs", ha="center", transform=axes[0].transAxes
        )
        fig.tight_layout()
        save_figure(fig, path)
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
    shown = list(dict.fromkeys([RAW, NN7, NN13, model, r.recommended or RAW]))
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
    save_figure(fig, path)


def plot_noise_summary(results: Sequence[GroupReport], cfg: EvaluateParams, path: Path) -> None:
    """Noise amplification ratio (worst axis) of every model of every group, threshold line."""
    plt = pyplot()
    models = list(dict.fromkeys(m for r in results for m in r.models))
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
    save_figure(fig, path)


def plot_overview(results: Sequence[GroupReport], path: Path) -> None:
    """Global RMSE of every model per headline of every group, against labels and truth (log scale)."""

    plt = pyplot()
    bars = [(r, name) for r in results for name in (r.headlines or [r.headline])]
    refs = [ref for ref in REFERENCES if any(ref in r.tables[name] for r, name in bars)]
    models = list(dict.fromkeys(m for r in results for m in r.models))
    width = 0.8 / max(len(models), 1)
    fig, axes = plt.subplots(
        1, len(refs), figsize=(max(7.5, 1.3 * len(bars)) * len(refs) + 1.5, 4.8), squeeze=False
    )
    for i, ref in enumerate(refs):
        ax = axes[0, i]
        for k, m in enumerate(models):
            values = [r.headline_rmse(ref, m, name=name) for r, name in bars]
            values = [math.nan if v is None else v for v in values]
            ax.bar(
                np.arange(len(bars)) + (k - (len(models) - 1) / 2) * width,
                values,
                width,
                color=_color(m),
                label=m,
            )
        ax.set_xticks(np.arange(len(bars)), [name for _, name in bars], rotation=20)
        ax.set_yscale("log")
        ax.set_ylabel("RMSE, 6 axes pooled [N, Nm]")
        ax.set_title(f"test RMSE against {REFERENCE_TITLES[ref]}")
        ax.grid(alpha=0.3, axis="y", which="both")
    axes[0, -1].legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)


# --- DVC plot data -------------------------------------------------------------------------------


def write_plot_data(out: Path, r: GroupResult) -> list[str]:
    """CSV series of one group for `dvc plots` (see dvc.yaml): plots_data/rmse_labels/<group>.csv and
    rmse_truth/<group>.csv (model, rmse: the headline's global RMSE; no row without truth), noise/<group>.csv
    (model, ratio, ratio_rms), loss/<group>/<network>.csv (epoch from 1, train_loss, val_rmse). Returns
    paths relative to `out`."""
    base = out / PLOTS_DATA_DIR
    files = []

    def write(sub: str, stem: str, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
        write_csv(base / sub / f"{stem}.csv", header, rows)
        files.append(f"{PLOTS_DATA_DIR}/{sub}/{stem}.csv")

    for sub, ref in (("rmse_labels", LABELS), ("rmse_truth", TRUTH)):
        rows = [[m, r.headline_rmse(ref, m)] for m in r.models if r.headline_rmse(ref, m) is not None]
        write(sub, r.group, ["model", "rmse"], rows)
    rows = [[m, r.noise.ratio.get(m), r.noise.ratio_rms.get(m)] for m in r.models]
    write("noise", r.group, ["model", "ratio", "ratio_rms"], rows)
    (base / "loss" / r.group).mkdir(parents=True, exist_ok=True)  # a dvc plots output, even without networks
    for old in (base / "loss" / r.group).glob("*.csv"):
        old.unlink()
    for network, history in r.histories.items():
        rows = [[int(h["epoch"]) + 1, h["loss"], h["val_rmse"]] for h in history]
        write(f"loss/{r.group}", network, ["epoch", "train_loss", "val_rmse"], rows)
    return files


def write_group_figures(
    out: Path, r: GroupResult, cfg: EvaluateParams, progress: Any = None
) -> dict[str, Any]:
    """Every figure of one group into ``out/<GROUPS_DIR>/<group>/plots/``; returns their paths relative to
    `out`: {"loss", "noise", "names": {sensor or pair: {rmse, timeseries, zoom, residuals}}}."""
    rel = f"{GROUPS_DIR}/{r.group}/{PLOTS_DIR}"
    (out / rel).mkdir(parents=True, exist_ok=True)
    for old in (out / rel).glob("*.png"):
        old.unlink()
    figures: dict[str, Any] = {"loss": f"{rel}/loss.png", "noise": f"{rel}/noise.png", "names": {}}
    draw = {
        "rmse": lambda p, n: plot_rmse_axes(r, n, p),
        "timeseries": lambda p, n: plot_timeseries(r, n, p),
        "zoom": lambda p, n: plot_zoom(r, n, cfg.zoom_s, p),
        "residuals": lambda p, n: plot_residuals(r, n, p),
    }
    for name in r.names:
        figures["names"][name] = {kind: f"{rel}/{name}_{kind}.png" for kind in draw}
    # the costliest kinds first (zoom: an axes per axis and experiment type), so that the workers end together
    jobs: list[tuple[str, Any]] = [
        (figures["names"][name][kind], lambda p, n=name, kind=kind: draw[kind](p, n))
        for kind in ("zoom", "residuals", "rmse", "timeseries")
        for name in r.names
    ]
    jobs.append((figures["loss"], lambda p: plot_losses(r, p)))
    jobs.append((figures["noise"], lambda p: plot_noise_example(r, cfg, p)))
    task = progress.add_task(f"evaluate {r.group}: plots", total=len(jobs)) if progress is not None else None
    from pipeline.core.parallel import forked_map

    pyplot()  # matplotlib imported once, before the workers fork
    drawn = [lambda p=out / path, job=job: job(p) for path, job in jobs]
    for _ in forked_map(drawn, labels=[str(out / path) for path, _ in jobs]):
        if task is not None:
            progress.advance(task)
    return figures
