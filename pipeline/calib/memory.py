"""The memory models' structure, chosen by the training data: play widths per raw axis, arx time constants.

A play operator (`pipeline.core.play`) of width w models hysteresis only where the motion reverses by more
than 2 w: there its state saturates and carries the path. An operator wider than the motion never
saturates; its state is then ``(f - f_0) / w``, the reading's departure from the log's first reading: a
static gain plus an offset set by wherever the log began. Fitted, such a column trades its gain against the
static map's and its start-dependent offset against the logs' offset drift; on a log that starts elsewhere
(a fresh segment, a robot booted in another pose) it moves the prediction by the difference, and its
least-squares weight, unbounded where the training logs began alike, took a real pole run's held-out
segment to 1e12 N. Likewise a low-pass filter whose time constant is not short beside a log is its first
reading plus a slow ramp.

So the widths are fractions (`train.defaults.play_width_fractions`) of each raw axis's span over the
training samples (the 0.5-99.5 % quantiles, the largest of the group's sensors; at least a few noise stds),
the fit keeps per output axis only the operators the training samples saturate (`saturated`, in
`pipeline.calib.linear`), and the arx model keeps the time constants (`train.defaults.arx_time_constants_s`)
at least two sample periods long and at most a quarter of the median training log. Wrenches N and Nm, times s.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from pipeline.calib.data import Group, LogInfo, load_group_data
from pipeline.calib.excitation import noise_std
from pipeline.logs.schema import WRENCH_AXES as AXES

WRENCH = 6
SPAN_QUANTILES = (0.005, 0.995)  # a raw axis's span: robust to a glitch, not to a motion
LONGEST_FRACTION = 0.25  # an arx time constant is at most this fraction of the median training log
SHORTEST_PERIODS = 2.0  # and at least this many sample periods (shorter: the filter is the reading)
MIN_SATURATED = 0.02  # an operator is kept where the training samples hold its state at |z| = 1 this often
NOISE_WIDTHS = 3.0  # a play width is at least this many noise stds of its axis
FLOOR = 1e-6  # a width on an axis that does not move (N, Nm): positive, and dropped as never saturated


def axis_spans(raw: np.ndarray) -> np.ndarray:
    """(6,) the span of each raw axis, N / Nm: from raw readings (N, S, >= 6), per sensor the 0.5-99.5 %
    quantile range over the finite samples, the largest over the S sensors (0 where none is finite)."""
    spans = np.zeros(WRENCH)
    for s in range(raw.shape[1]):
        for a in range(WRENCH):
            v = raw[:, s, a]
            v = v[np.isfinite(v)]
            if len(v):
                lo, hi = np.quantile(v, SPAN_QUANTILES)
                spans[a] = max(spans[a], float(hi - lo))
    return spans


def data_widths(
    raw: np.ndarray, fractions: Sequence[float], noise: np.ndarray | None = None
) -> tuple[tuple[float, ...], ...]:
    """The play model's widths (K, 6), N / Nm: each fraction of each raw axis's span (`axis_spans`), at
    least `NOISE_WIDTHS` times the axis's noise std (6,) where given (a narrower operator follows the
    noise, not the path)."""
    spans = np.maximum(axis_spans(raw), FLOOR / min(fractions))
    least = np.zeros(WRENCH) if noise is None else NOISE_WIDTHS * np.nan_to_num(noise)
    return tuple(tuple(float(max(f * s, m)) for s, m in zip(spans, least, strict=True)) for f in fractions)


def data_time_constants(
    candidates: Sequence[float], durations: Sequence[float], period: float
) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(kept, dropped) of the arx model's candidate time constants (s), given the training logs' durations
    (s) and their sample period (s): kept those within [SHORTEST_PERIODS periods, LONGEST_FRACTION x the
    median duration]."""
    longest = LONGEST_FRACTION * float(np.median(durations)) if len(durations) else 0.0
    kept = tuple(t for t in candidates if SHORTEST_PERIODS * period <= t <= longest)
    return kept, tuple(t for t in candidates if t not in kept)


def saturated(states: np.ndarray) -> np.ndarray:
    """(6 K,) bool: the play states (M, 6 K) in [-1, 1] that the samples hold at the bound (|z| > 0.999)
    at least `MIN_SATURATED` of the time."""
    if len(states) == 0:
        return np.zeros(states.shape[1], dtype=bool)
    return np.mean(np.abs(states) > 0.999, axis=0) >= MIN_SATURATED


def structure(
    group: Group, logs: Sequence[LogInfo], fractions: Sequence[float], taus: Sequence[float]
) -> tuple[Group, dict[str, Any]]:
    """`group` with the play widths and arx time constants its training logs `logs` choose (module
    docstring; none of either where `fractions` / `taus` is empty), and what the data set: ``play_widths``
    (K, 6) N / Nm, ``arx_time_constants_s`` kept and ``arx_left_out_s``, with the spans, durations and
    period they came from (metrics.json's ``memory``)."""
    if not fractions and not taus:
        return group, {}
    train = load_group_data(replace(group, widths=None, time_constants=None, windows=None), logs)
    info: dict[str, Any] = {}
    widths = None
    if fractions:
        noise = np.nanmax(
            [noise_std(train.x[:, s, :WRENCH], train.log, train.stamp) for s in range(len(group.sensors))],
            axis=0,
        )
        widths = data_widths(train.x[:, :, :WRENCH], fractions, noise)
        info.update(spans=axis_spans(train.x[:, :, :WRENCH]).tolist(), play_widths=[list(w) for w in widths])
    kept: tuple[float, ...] = ()
    if taus:
        durations = [float(np.ptp(train.time[train.log == k])) for k in np.unique(train.log)]
        steps = [np.diff(train.time[train.log == k]) for k in np.unique(train.log)]
        period = float(np.median(np.concatenate(steps))) if any(len(s) for s in steps) else 0.0
        kept, dropped = data_time_constants(taus, durations, period)
        info.update(
            arx_time_constants_s=list(kept),
            arx_left_out_s=list(dropped),
            median_log_s=float(np.median(durations)) if durations else 0.0,
            period_s=period,
        )
    return replace(group, widths=widths, time_constants=kept or None), info


def describe(name: str, info: Mapping[str, Any]) -> str:
    """One line of what the data set (`structure`'s info), for the stage's output."""
    parts = []
    if info.get("play_widths"):
        widths = info["play_widths"]
        shown = ", ".join(f"{a} {' / '.join(f'{w[i]:.3g}' for w in widths)}" for i, a in enumerate(AXES))
        parts.append(f"play widths from the training span: {shown} (N, Nm)")
    if "arx_time_constants_s" in info:
        kept = ", ".join(f"{t:g}" for t in info["arx_time_constants_s"]) or "none"
        parts.append(f"arx time constants {kept} s")
        if info["arx_left_out_s"]:
            parts[-1] += (
                f" ({', '.join(f'{t:g}' for t in info['arx_left_out_s'])} s left out: the training logs last "
                f"{info['median_log_s']:.3g} s at {info['period_s']:.3g} s, a filter is kept between "
                f"{SHORTEST_PERIODS:g} periods and {LONGEST_FRACTION:g} of a log)"
            )
    return f"{name}: " + "; ".join(parts)
