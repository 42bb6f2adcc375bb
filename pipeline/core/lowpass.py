"""First-order low-pass filters of a sensor's raw wrench (the memory of the ``arx`` family), and the one state
step that filters and play operators share.

A filter of time constant tau follows its input x: ``y_k = y_{k-1} + alpha (x_k - y_{k-1})``, with
``alpha = 1 - exp(-dt / tau)`` (the exact discretisation of ``dy/dt = (x - y) / tau`` for an input held over
each sample period dt); it starts at the first sample (``y_0 = x_0``). The arx model reads ``x - y`` per raw
axis and time constant: the reading's departure from its recent past over a few horizons. That is a lagged
linear map of the raw wrench's history whose poles are fixed (an ARX model whose autoregressive part is a
bank of first-order filters): its state is 6 values per time constant, not a window of samples. Unlike a
play operator, a filter depends on the rate: a model trained on samples `period` apart runs on samples as far
apart (the export's manifest says so).

`pipeline.core.play.memory_step` is one step of either operator on each column, ``y = clip(s + alpha (x - s),
x - r, x + r)`` with s the output before (x itself at a fresh start, a NaN): a play operator of width r has
alpha = 0, a filter an infinite r.

Shapes: x (N, m) or (N, S, >= 6) over N consecutive samples; time constants (J,) s; period s.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.signal import lfilter

from pipeline.core.play import memory_step, play_memory

WRENCH = 6


def alphas(time_constants: np.ndarray, period: float) -> np.ndarray:
    """(J,) each filter's step gain ``1 - exp(-period / tau)`` for time constants (J,) s and a period, s."""
    return -np.expm1(-float(period) / np.asarray(time_constants, dtype=np.float64))


def nominal_period(time: np.ndarray) -> float:
    """The sample period of one log, s: the median step between its consecutive times (N,) s (NaN with fewer
    than two samples)."""
    steps = np.diff(np.asarray(time, dtype=np.float64))
    steps = steps[steps > 0]
    return float(np.median(steps)) if len(steps) else float("nan")


def lowpass_outputs(x: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """(N, m) each column's filter output after each sample, starting at the first sample's value, for
    x (N, m) and the step gains `alpha` (m,)."""
    x = np.asarray(x, dtype=np.float64)
    out = np.empty_like(x)
    for j in range(x.shape[1]):
        a = float(alpha[j])
        out[:, j] = lfilter([a], [1.0, a - 1.0], x[:, j], zi=[(1.0 - a) * x[0, j]])[0] if len(x) else x[:, j]
    return out


def lowpass_memory(x: np.ndarray, time_constants: np.ndarray, period: float) -> np.ndarray:
    """(N, S, 6 J) the filter outputs before each sample (column 6 j + a: time constant j, axis a) of one
    log's samples x (N, S, >= 6) in time order, `period` s apart; NaN at each sensor's first finite reading
    and where its reading is not finite (a missing reading neither moves nor resets the filters)."""
    x = np.asarray(x, dtype=np.float64)
    gains = np.repeat(alphas(time_constants, period), WRENCH)
    n, n_sensors = x.shape[:2]
    out = np.full((n, n_sensors, len(gains)), np.nan)
    for s in range(n_sensors):
        rows = np.flatnonzero(np.isfinite(x[:, s, :WRENCH]).all(axis=1))
        if len(rows) < 2:
            continue
        tiled = np.tile(x[rows, s, :WRENCH], len(gains) // WRENCH)
        out[rows[1:], s] = lowpass_outputs(tiled, gains)[:-1]
    return out


def lowpass_features(wrench: np.ndarray, previous: np.ndarray, gains: np.ndarray) -> np.ndarray:
    """(N, 6 J) the departures ``x - y`` (N, Nm) at each sample (column 6 j + a) from its raw wrench (N, 6)
    and the filter outputs before it, `previous` (N, 6 J) (NaN: a fresh start, 0), for step gains (J,)."""
    gains = np.repeat(np.asarray(gains, dtype=np.float64), WRENCH)
    tiled = np.tile(np.asarray(wrench, dtype=np.float64), len(gains) // WRENCH)
    return tiled - memory_step(previous, tiled, np.inf, gains)


def memory_of(x: np.ndarray, widths: Any, time_constants: Any, period: float | None) -> np.ndarray | None:
    """(N, S, 6 K + 6 J) the memory of one log's samples x (N, S, >= 6) in time order: the play outputs of
    `widths` (K, 6) (`pipeline.core.play.play_memory`), then the filter outputs of `time_constants` (J,) s at
    `period` s (arrays or nested sequences); None without either."""
    parts = []
    if widths is not None:
        parts.append(play_memory(x, widths))
    if time_constants is not None:
        parts.append(lowpass_memory(x, time_constants, float(period)))
    return np.concatenate(parts, axis=2) if parts else None


def operator_columns(
    widths: np.ndarray | None, time_constants: np.ndarray | None, period: float | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(radius, alpha, scale), each (6 K + 6 J,), of the memory columns of `memory_of`: a play operator's
    radius is its width, its alpha 0 and its state ``(x - y) / width``; a filter's radius is infinite, its
    alpha `alphas`' and its feature ``x - y`` (scale 1 N or Nm)."""
    radius, alpha, scale = [], [], []
    if widths is not None:
        r = np.asarray(widths, dtype=np.float64).reshape(-1)
        radius.append(r)
        alpha.append(np.zeros_like(r))
        scale.append(r)
    if time_constants is not None:
        a = np.repeat(alphas(time_constants, float(period)), WRENCH)
        radius.append(np.full_like(a, np.inf))
        alpha.append(a)
        scale.append(np.ones_like(a))
    if not radius:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    return np.concatenate(radius), np.concatenate(alpha), np.concatenate(scale)
