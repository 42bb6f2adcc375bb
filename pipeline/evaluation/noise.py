"""Deployment noise (thesis chapter 6, Test A): quasi-static stretches and high-frequency output ratios.

The 13-input network of the thesis passed the FT board's IMU noise into its output and was unusable on
the robot, standing still. On quasi-static segments, the high-frequency part of each model's output
(zero-phase Butterworth high-pass at ``highpass_hz``) is compared with raw's: ``ratio = std(HF model) /
std(HF raw)`` per sensor (or sum) and axis; a model's ratio is its worst axis, and a model above
``noise_threshold`` is flagged. Quasi-static: samples where the group's FT boards turn slower than
``still_gyro_rad_s`` (gyroscope norm, low-passed), with a constant contact set and outside guard bands, in
runs of at least ``still_min_s`` within a contiguous stretch of samples.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from pipeline.evaluation.params import MAX_STEP

# --- deployment noise ----------------------------------------------------------------------------


def segment_ids(log: np.ndarray, stamp_ns: np.ndarray) -> tuple[np.ndarray, float]:
    """Contiguous stretches of samples and the sampling rate.

    Args:
        log: (N,) log of each sample; stamp_ns: (N,) int64 ns, increasing within a log.

    Returns:
        ((N,) int id of the stretch of each sample, sampling rate in Hz). A stretch ends where the log
        changes or the stamp steps by more than 1.5 nominal periods (the median step): a lost sample.
    """
    stamp = np.asarray(stamp_ns, dtype=np.int64)
    log = np.asarray(log)
    if len(stamp) < 2:
        return np.zeros(len(stamp), dtype=np.int64), math.nan
    step = np.diff(stamp).astype(np.float64)
    same = log[1:] == log[:-1]
    nominal = float(np.median(step[same & (step > 0)])) if (same & (step > 0)).any() else math.nan
    new = ~same | (step <= 0) | (step > MAX_STEP * nominal)
    return np.r_[0, np.cumsum(new)].astype(np.int64), 1e9 / nominal


def _runs(ids: np.ndarray) -> list[tuple[int, int]]:
    """[(start, stop)] of the runs of equal consecutive values of `ids` (N,)."""
    if len(ids) == 0:
        return []
    edges = np.flatnonzero(ids[1:] != ids[:-1]) + 1
    starts = np.r_[0, edges]
    stops = np.r_[edges, len(ids)]
    return list(zip(starts.tolist(), stops.tolist(), strict=True))


def highpass(x: np.ndarray, segments: np.ndarray, fs: float, cutoff_hz: float, order: int) -> np.ndarray:
    """Zero-phase Butterworth high-pass of x (N, C) along time, each stretch of `segments` (N,) alone.

    Stretches too short for the forward-backward filter's padding are NaN. Units are those of x.
    """
    from scipy.signal import butter, sosfiltfilt

    x = np.asarray(x, dtype=np.float64)
    out = np.full_like(x, np.nan)
    if not math.isfinite(fs) or cutoff_hz >= fs / 2:
        return out
    sos = butter(order, cutoff_hz, btype="highpass", fs=fs, output="sos")
    padlen = 3 * (2 * len(sos) + 1 - min(int((sos[:, 2] == 0).sum()), int((sos[:, 5] == 0).sum())))
    for start, stop in _runs(segments):
        chunk = x[start:stop]
        if stop - start > padlen and np.isfinite(chunk).all():
            out[start:stop] = sosfiltfilt(sos, chunk, axis=0)
    return out


def board_speed(
    gyro: Sequence[np.ndarray], segments: np.ndarray, fs: float, cutoff_hz: float, order: int
) -> np.ndarray:
    """(N,) rad/s: the largest angular speed among FT boards, from their gyroscopes (each (N, 3), rad/s).

    Each gyroscope is low-passed (the complement of `highpass`: noise and vibration removed) before its norm.
    """
    speeds = []
    for g in gyro:
        g = np.asarray(g, dtype=np.float64)
        speeds.append(np.linalg.norm(g - highpass(g, segments, fs, cutoff_hz, order), axis=1))
    return np.max(speeds, axis=0)


def quasi_static_mask(
    speed: np.ndarray,
    contacts: np.ndarray,
    guard: np.ndarray,
    segments: np.ndarray,
    fs: float,
    max_speed: float,
    min_s: float,
    edge_s: float,
) -> np.ndarray:
    """(N,) bool: samples in quasi-static runs.

    A run is a maximal stretch of consecutive samples of one segment with one contact set, outside guard
    bands, whose `speed` (N,) rad/s stays below `max_speed`, at least `min_s` long (at `fs` Hz). Samples
    within `edge_s` of a segment's ends are left out (where a zero-phase filter has transients).
    """
    n = len(speed)
    ok = np.isfinite(speed) & (speed < max_speed) & ~np.asarray(guard, dtype=bool)
    edge = int(round(edge_s * fs)) if math.isfinite(fs) else 0
    for start, stop in _runs(segments):
        ok[start : min(stop, start + edge)] = False
        ok[max(start, stop - edge) : stop] = False
    # Run ids change with the segment, the contact set and the ok flag.
    contacts = np.asarray(contacts, dtype=object)
    change = np.ones(n, dtype=bool)
    if n > 1:
        change[1:] = (segments[1:] != segments[:-1]) | (contacts[1:] != contacts[:-1]) | (ok[1:] != ok[:-1])
    ids = np.cumsum(change)
    min_len = max(1, int(math.ceil(min_s * fs))) if math.isfinite(fs) else n + 1
    mask = np.zeros(n, dtype=bool)
    for start, stop in _runs(ids):
        if ok[start] and stop - start >= min_len:
            mask[start:stop] = True
    return mask


def noise_ratio(model_hf: np.ndarray, raw_hf: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(C,) std of a model's high-frequency output over raw's, on the samples of `mask` (N,).

    model_hf, raw_hf: (N, C) high-passed outputs (same units per column). NaN for a column with fewer
    than 2 samples or no raw noise.
    """
    m = np.asarray(mask, dtype=bool) & np.isfinite(model_hf).all(axis=1) & np.isfinite(raw_hf).all(axis=1)
    if m.sum() < 2:
        return np.full(model_hf.shape[1], np.nan)
    num = np.std(model_hf[m], axis=0)
    den = np.std(raw_hf[m], axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 0, num / den, np.nan)
