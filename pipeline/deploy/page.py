"""reports/deployment.html and its figures: the three tests per deployment day, numbers first."""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.io import write_text
from pipeline.evaluation.figures import pyplot, save_figure
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


def _f(v: Any) -> str:
    return f"{v:.3g}" if isinstance(v, float) and np.isfinite(v) else html.escape(str(v))


def _table(header: list[str], rows: list[list[Any]]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_f(c)}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def day_section(day: str, result: dict[str, Any], figures: dict[str, str]) -> str:
    parts = [f"<h2>{html.escape(day)}</h2>"]
    a = result.get("test_a", {})
    rows = [
        [g, m, r["worst"], "FLAGGED" if r["flagged"] else "ok", "deployed" if m == a[g]["deployed"] else ""]
        for g in a
        for m, r in a[g]["models"].items()
    ]
    parts += ["<h3>Test A: output noise standing still (HF std / raw's, worst axis)</h3>"]
    parts += [_table(["group", "model", "noise ratio", "verdict", ""], rows)]
    parts += ["<h3>Test B: walking (RMSE, N and Nm pooled; per axis in deployment/details.json)</h3>"]
    rows = []
    for name, e in result.get("test_b", {}).items():
        lab, tru = e["labels"], e.get("truth", {})
        row = [name, lab["raw"]["rmse"], lab["calibrated"]["rmse"]]
        row += [tru["raw"]["rmse"], tru["calibrated"]["rmse"], e["ratio_truth"]] if tru else ["", "", ""]
        rows.append(row)
    parts += [
        _table(
            [
                "sensor / sum",
                "raw vs labels",
                "calibrated vs labels",
                "raw vs truth",
                "cal. vs truth",
                "raw/cal",
            ],
            rows,
        )
    ]
    parts += ["<h3>Test C: joint torques during the pushes (Nm)</h3>"]
    rows = [
        [
            leg,
            j,
            v["raw"]["rmse"],
            v["calibrated"]["rmse"],
            v["ratio_rmse"],
            v["raw"]["max"],
            v["calibrated"]["max"],
            v["ratio_max"],
        ]
        for leg, r in result.get("test_c", {}).items()
        for j, v in r["joints"].items()
    ]
    parts += [
        _table(
            [
                "sensor",
                "joint",
                "RMSE raw",
                "RMSE cal.",
                "RMSE raw/cal",
                "max raw",
                "max cal.",
                "max raw/cal",
            ],
            rows,
        )
    ]
    parts += [
        f'<p><img src="{html.escape(src)}" alt="{html.escape(k)}" style="max-width:100%"></p>'
        for k, src in figures.items()
    ]
    return "\n".join(parts)


def write_page(
    path: Path, days: dict[str, dict[str, Any]], figures: dict[str, dict[str, str]], verdict: str
) -> None:
    style = "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}"
    body = [f"<h1>Deployment tests</h1><p>{html.escape(verdict)}</p>"]
    body += [day_section(day, r, figures.get(day, {})) for day, r in days.items()]
    write_text(path, f"<!doctype html><html><head><meta charset='utf-8'><style>{style}</style></head><body>"
               + "\n".join(body) + "</body></html>\n")  # fmt: skip
