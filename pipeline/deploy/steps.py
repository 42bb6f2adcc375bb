"""Step responses: how a held load's reported change evolves while the load holds (Test D from the noise up).

A load held at a sensor's site (`pipeline.deploy.scales`, family ``load``: raised-cosine ramps, then a
plateau) is a step of the true wrench. A faithful calibration reports it as it is: its change rises with the
load and stays while the load holds, without lagging, overshooting or decaying. The sensor's hysteresis makes
the reading's change of a fresh load larger than of one held while the robot moves on (the play operators'
minor-loop gain, forgotten as the motion drags them along): the oracle, the static inverse, inherits that; a
calibration with memory must not add to it, nor answer the load late.

Per model the response of one hold is ``r(t) = c_F(t) . u / |F|``, c_F the reported change of the force, F
the load's peak force and u its direction (the true change gives the load's profile), on `POINTS` points
evenly spaced over the hold (resampled), averaged over the holds of the day's logs. On the plateau (the true
profile at its peak) its first and last thirds' means (``first``, ``last``: a decay is first - last) and its
extremes.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

POINTS = 40  # points of a step response over a hold
PLATEAU = 0.999  # the true profile at least this share of its peak: the load fully held
MODELS = ("deployed", "oracle", "raw")
STYLES = {"deployed": ("-", "tab:blue"), "oracle": ("--", "tab:green"), "raw": (":", "tab:red")}


class Steps:
    """Sums of the step responses per model over holds (and of the true profile)."""

    def __init__(self) -> None:
        self.sums: dict[str, np.ndarray] = {}
        self.counts: dict[str, int] = {}

    def add(self, model: str, change: np.ndarray, push: np.ndarray, peak: np.ndarray) -> None:
        """One hold: the model's reported change (L, >= 3) and the true push (L, >= 3) over its samples, the
        push's peak wrench (>= 3) (N, force first)."""
        force = np.asarray(peak[:3], dtype=np.float64)
        size = float(np.linalg.norm(force))
        if size <= 0 or len(change) < 2:
            return
        grid = (np.arange(POINTS) + 0.5) / POINTS
        s = (np.arange(len(change)) + 0.5) / len(change)
        for name, values in ((model, change), ("truth", push)):
            r = np.asarray(values[:, :3], dtype=np.float64) @ force / size**2
            if not np.isfinite(r).all():
                return
            if name == "truth" and model != MODELS[0]:
                continue  # the truth once per hold
            self.sums[name] = self.sums.get(name, 0.0) + np.interp(grid, s, r)
            self.counts[name] = self.counts.get(name, 0) + 1

    def merge(self, other: Steps) -> None:
        for k, v in other.sums.items():
            self.sums[k] = self.sums.get(k, 0.0) + v
            self.counts[k] = self.counts.get(k, 0) + other.counts[k]

    def entry(self) -> dict[str, Any]:
        """{"holds", "truth": curve, "models": {model: curve}, "plateau": {model: {first, last, min, max}}}
        (empty without a hold)."""
        if "truth" not in self.sums:
            return {}
        truth = self.sums["truth"] / self.counts["truth"]
        curves = {m: self.sums[m] / self.counts[m] for m in MODELS if m in self.sums}
        on = np.flatnonzero(truth >= PLATEAU * truth.max())
        third = max(len(on) // 3, 1)
        plateau = {
            m: {
                "first": _round(c[on[:third]].mean()),
                "last": _round(c[on[-third:]].mean()),
                "min": _round(c[on].min()),
                "max": _round(c[on].max()),
            }
            for m, c in curves.items()
        }
        return {
            "holds": int(self.counts["truth"]),
            "truth": [_round(v) for v in truth],
            "models": {m: [_round(v) for v in c] for m, c in curves.items()},
            "plateau": plateau,
        }


def _round(v: float) -> float:
    return float(round(float(v), 4))


def plot_steps(result: Mapping[str, Any], path: Any) -> bool:
    """Per sensor its step response (`Steps.entry` under ``step``): the true profile and each model's,
    over the hold's time (share of the hold). False if no sensor has one."""
    from pipeline.evaluation.figures import pyplot, save_figure

    shown = [s for s, e in result.items() if e.get("step")]
    if not shown:
        return False
    plt = pyplot()
    fig, axes = plt.subplots(1, len(shown), figsize=(3.6 * len(shown), 3.0), squeeze=False)
    grid = (np.arange(POINTS) + 0.5) / POINTS
    for ax, sensor in zip(axes[0], shown, strict=True):
        step = result[sensor]["step"]
        ax.plot(grid, step["truth"], color="k", lw=1.2, label="true")
        for model, curve in step["models"].items():
            ls, color = STYLES.get(model, ("-", "tab:grey"))
            ax.plot(grid, curve, ls=ls, color=color, lw=1, label=model)
        ax.set_title(f"{sensor} ({step['holds']} holds)", fontsize=9)
        ax.set_xlabel("time over the hold (share)", fontsize=8)
        ax.set_ylabel("reported change / load", fontsize=8)
    axes[0, 0].legend(fontsize=6)
    fig.tight_layout()
    save_figure(fig, path)
    return True


def steps_table(result: Mapping[str, Any]) -> str:
    """One row per sensor and model: the plateau's first and last thirds, their difference, its extremes."""
    from pipeline.evaluation.html import cell, esc

    rows = []
    for sensor, e in result.items():
        plateau = (e.get("step") or {}).get("plateau") or {}
        for model, p in plateau.items():
            rows.append(
                f"<tr><td>{esc(sensor)}</td><td>{esc(model)}</td>"
                + cell(p["first"]) + cell(p["last"]) + cell(round(p["first"] - p["last"], 4))
                + cell(p["min"]) + cell(p["max"]) + "</tr>"
            )  # fmt: skip
    if not rows:
        return ""
    header = ["sensor", "model", "plateau, first third", "last third", "decay (first - last)", "min", "max"]
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    return f'<table class="num"><thead><tr>{head}</tr></thead><tbody>{"".join(rows)}</tbody></table>'
