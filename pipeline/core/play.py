"""The play (backlash) operator: the path dependence of a sensor's reading, simulated and calibrated.

A play operator of width w follows its input x with backlash: its output y stays where it is while x moves
within ``[y - w, y + w]`` and is dragged along by x beyond, ``y_k = clip(y_{k-1}, x_k - w, x_k + w)``; its
normalised state ``z = (x - y) / w`` lies in [-1, 1] (``z_k = clip(z_{k-1} + (x_k - x_{k-1}) / w, -1, 1)``,
the same recursion). It is rate-independent (only the path of x matters, not its speed), so a log resampled
onto other stamps gives about the same z. The simulator's sensors read ``h * z`` on top of their static
distortion (`pipeline.sim.distortion`); a calibration with memory (the ``play`` family,
`pipeline.calib.linear`) reads z of its raw wrench at a few widths (a Prandtl-Ishlinskii model) and runs
`play_step` sample by sample as the exported graphs do.

Shapes: x (N, m) over N consecutive samples of m signals; widths scalar or (m,), in x's unit, > 0.

The widths a params section gives (the play model's, `train.defaults`; the identification's sensor model's,
`label.identify`) are checked by `checked_widths` (each list by `distinct_positive`) and laid out per
operator by `width_rows`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from pipeline.core.errors import ConfigError

_SCAN_BLOCK = 32  # block length of the play-operator scan (fastest of 8..64 for 1e5 x 6 samples)


def play_operator(x: np.ndarray, width: np.ndarray | float, initial: np.ndarray | float = 0.0) -> np.ndarray:
    """Play (backlash) operator per column: ``z_k = clip(z_{k-1} + (x_k - x_{k-1}) / width, -1, 1)``.

    x: (N, m) input signal; width: scalar or (m,), same unit as x, > 0; initial: z_0, scalar or (m,)
    in [-1, 1]. Returns z, (N, m), dimensionless in [-1, 1].

    Method: each step is the map ``z -> clamp(z + a, lo, hi)``, and such maps are closed under
    composition, so z is a prefix scan of maps. The scan runs in blocks (a Hillis-Steele scan inside
    blocks of `_SCAN_BLOCK` samples, the same scan recursively over the block totals): ~5 vectorised
    passes over the data instead of a Python loop over samples. Equal to the loop to ~1e-15.
    """
    x = np.asarray(x, dtype=float)
    if x.ndim != 2:
        raise ValueError(f"x must have shape (N, m), got {x.shape}")
    z0 = np.broadcast_to(np.asarray(initial, dtype=float), x.shape[1:])
    z = np.empty_like(x)
    if len(x) == 0:
        return z
    a = np.diff(x, axis=0) / width
    a, lo, hi = _scan_clamps(a, np.full_like(a, -1.0), np.full_like(a, 1.0))
    z[0] = z0
    z[1:] = np.minimum(np.maximum(z0 + a, lo), hi)
    return z


def _compose_scan_inplace(a: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
    """Inclusive Hillis-Steele scan along axis 1 of maps ``z -> clamp(z + a, lo, hi)``, in place.

    Arrays are (blocks, k, ...); element k of each block becomes map_k o ... o map_0 of that block.
    Composition rule: ``clamp(clamp(z + a1, l1, h1) + a2, l2, h2)
    = clamp(z + a1 + a2, clamp(l1 + a2, l2, h2), clamp(h1 + a2, l2, h2))``.
    """
    s = 1
    while s < a.shape[1]:
        a2, l2, h2 = a[:, s:], lo[:, s:], hi[:, s:]
        new_lo = lo[:, :-s] + a2
        np.minimum(np.maximum(new_lo, l2, out=new_lo), h2, out=new_lo)
        new_hi = hi[:, :-s] + a2
        np.minimum(np.maximum(new_hi, l2, out=new_hi), h2, out=new_hi)
        new_a = a[:, :-s] + a2
        a[:, s:], lo[:, s:], hi[:, s:] = new_a, new_lo, new_hi
        s *= 2


def _scan_clamps(a: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inclusive scan (along axis 0) of maps ``z -> clamp(z + a, lo, hi)``; returns new arrays."""
    k, rest = len(a), a.shape[1:]
    if k <= _SCAN_BLOCK:
        a, lo, hi = a[None].copy(), lo[None].copy(), hi[None].copy()
        _compose_scan_inplace(a, lo, hi)
        return a[0], lo[0], hi[0]
    nb = -(-k // _SCAN_BLOCK)
    pad = nb * _SCAN_BLOCK - k  # padded with identity maps (a = 0, no clamp)

    def blocks(y: np.ndarray, fill: float) -> np.ndarray:  # (k, ...) -> (nb, block length, ...), a copy
        return np.concatenate([y, np.full((pad, *rest), fill)]).reshape(nb, _SCAN_BLOCK, *rest)

    a, lo, hi = blocks(a, 0.0), blocks(lo, -np.inf), blocks(hi, np.inf)
    _compose_scan_inplace(a, lo, hi)
    ta, tl, th = _scan_clamps(a[:, -1], lo[:, -1], hi[:, -1])  # maps up to the end of each block
    # Exclusive prefix of each block (identity before the first), composed under the in-block maps.
    pa = np.concatenate([np.zeros((1, *rest)), ta[:-1]])[:, None]
    pl = np.concatenate([np.full((1, *rest), -np.inf), tl[:-1]])[:, None]
    ph = np.concatenate([np.full((1, *rest), np.inf), th[:-1]])[:, None]
    new_lo = np.minimum(np.maximum(pl + a, lo), hi)
    new_hi = np.minimum(np.maximum(ph + a, lo), hi)
    a += pa

    def unblock(y: np.ndarray) -> np.ndarray:
        return y.reshape(nb * _SCAN_BLOCK, *rest)[:k]

    return unblock(a), unblock(new_lo), unblock(new_hi)


def play_outputs(x: np.ndarray, width: np.ndarray | float) -> np.ndarray:
    """(N, m) the operator's output y after each sample, in x's unit, starting at the first sample's value
    (``y_0 = x_0``, z_0 = 0): ``y = x - width * play_operator(x, width)``."""
    x = np.asarray(x, dtype=float)
    return x - np.asarray(width, dtype=float) * play_operator(x, width)


def memory_step(previous: np.ndarray, x: np.ndarray, radius: Any, alpha: Any) -> np.ndarray:
    """The outputs after one more sample of play operators and first-order filters alike, elementwise:
    ``clip(s + alpha (x - s), x - radius, x + radius)`` with s the output before, or x itself at a fresh start
    (a NaN in `previous`). A play operator of width r is radius r, alpha 0; a filter (`pipeline.core.lowpass`)
    an infinite radius and its step gain."""
    start = np.where(np.isnan(previous), x, previous)
    return np.minimum(np.maximum(start + alpha * (x - start), x - radius), x + radius)


def play_step(previous: np.ndarray, x: np.ndarray, width: np.ndarray | float) -> np.ndarray:
    """The output after one more sample: ``clip(previous, x - width, x + width)``, elementwise; a NaN in
    `previous` is a fresh start (the output is then x itself)."""
    return memory_step(previous, x, width, 0.0)


def play_memory(x: np.ndarray, widths: np.ndarray) -> np.ndarray:
    """(N, S, 6 K) the play outputs before each sample (module docstring) of one log's samples x (N, S, >= 6)
    in time order, widths (K, 6) per axis (N, Nm); NaN at each sensor's first finite reading and where its
    reading is not finite."""
    x = np.asarray(x, dtype=np.float64)
    widths = np.asarray(widths, dtype=np.float64)
    n, n_sensors = x.shape[:2]
    out = np.full((n, n_sensors, widths.size), np.nan)
    for s in range(n_sensors):
        rows = np.flatnonzero(np.isfinite(x[:, s, :6]).all(axis=1))
        if len(rows) < 2:
            continue
        wrench = x[rows, s, :6]
        y = np.concatenate([play_outputs(wrench, w) for w in widths], axis=1)  # after each sample
        out[rows[1:], s] = y[:-1]
    return out


def play_features(wrench: np.ndarray, previous: np.ndarray, widths: np.ndarray) -> np.ndarray:
    """(N, 6 K) the play states z in [-1, 1] at each sample (column 6 k + a: width k, axis a) from its raw
    wrench (N, 6) and the play outputs before it, `previous` (N, 6 K) (NaN: a fresh start, z = 0)."""
    widths = np.asarray(widths, dtype=np.float64).reshape(-1)
    tiled = np.tile(np.asarray(wrench, dtype=np.float64), len(widths) // 6)
    return (tiled - play_step(previous, tiled, widths)) / widths


def distinct_positive(value: object, key: str) -> tuple[float, ...]:
    """A params list of distinct positive finite numbers (play widths; the arx model's time constants) as
    floats, else ConfigError naming `key`."""
    ok = isinstance(value, list | tuple) and all(
        isinstance(v, int | float) and not isinstance(v, bool) and 0 < v < math.inf for v in value
    )
    if not ok or len(set(value)) != len(value):
        raise ConfigError(f"{key} must be a list of distinct positive numbers, got {value!r}")
    return tuple(float(v) for v in value)


def checked_widths(key: str, force_n: Any, torque_nm: Any) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The play widths of a params section, ``<key>.play_widths_n`` (force axes, N) and
    ``<key>.play_widths_nm`` (torque axes, Nm), as tuples of floats. Raises ConfigError naming the key
    unless each is a list of distinct positive numbers and they are as many."""
    force = distinct_positive(force_n, f"{key}.play_widths_n")
    torque = distinct_positive(torque_nm, f"{key}.play_widths_nm")
    if len(force) != len(torque):
        raise ConfigError(
            f"{key}.play_widths_nm must have as many widths as play_widths_n ({len(force)}), "
            f"got {list(torque)!r}"
        )
    return force, torque


def width_rows(force_n: tuple[float, ...], torque_nm: tuple[float, ...]) -> tuple[tuple[float, ...], ...]:
    """One row of widths per play operator (K, 6: the force axes' width N, then the torque axes' Nm)."""
    return tuple((f, f, f, t, t, t) for f, t in zip(force_n, torque_nm, strict=True))
