"""Savitzky-Golay on joint positions -> smoothed positions, velocities, accelerations.

Encoder velocities are too noisy to differentiate, so joint velocities and accelerations come from a
Savitzky-Golay (SG) filter on the encoder positions: a least-squares polynomial of order ``polyorder``
over ``window`` samples, evaluated with its derivatives at each sample. Given ``smooth.choices``, each
segment gets the (window, polyorder) of that list with the least estimated acceleration error
(`choose_setting`): a gait's fast steps a narrow window, a slow posture change a wide one.

SG assumes uniform sampling, and joint-state stamps jitter and lose messages. The time base is cut into
segments at every stamp step above ``smooth.max_gap_s`` (nothing is ever smoothed across such a gap);
each segment is resampled linearly on a uniform grid with its median step, filtered there (derivatives
scaled by that step, so in rad/s and rad/s^2), and interpolated back to the original stamps. On
uniformly sampled data this is exactly `scipy.signal.savgol_filter`. Segments shorter than the (narrowest)
window get NaN and ``ok.kinematics`` False; so do, with their values kept, the first and last
``window // 2`` samples of every segment (its setting's window), where the fitted polynomial is
one-sided and its derivatives extrapolate.

Encoders count in steps (iCub's 0.088 deg), and a joint held still flickers by a step or two: SG of high
order turns that flicker into accelerations of rad/s^2 and the labels into newtons of inertial force that
is not there (measured on a real pole run: 0.07-0.65 N RMS in r_leg_ft's labels). So a joint whose
positions lie on a lattice (`quantisation_step`, on its board's own readings where ingest recorded it, as
interpolation takes them off it) is still wherever its readings within a window of `STILL_WINDOW_S` (or
the widest SG window, if wider) span at most two steps (`still_mask`; the joint then moves by less than
0.1 deg/s, whose inertial effect is far below a sensor's noise): there its position is its running mean
over that window and its velocity and acceleration are zero; and its moving samples' noise is at least
the lattice's (``step^2 / 12``) in the choice of setting. A joint off any lattice (no quantisation, an
encoder with its own noise above a step) is smoothed as it is.

Each joint is smoothed on the samples where its own position is finite: a joint whose stream is absent
(a recording without that board) or invalid for a stretch gets NaN and ``ok.kinematics.<joint>`` False
there only, its samples on either side being segments of their own when the stretch is longer than
``max_gap_s``; every other joint is smoothed as if it were not there. Joints sharing one validity mask
(all of them on a complete log) are filtered together, in one call. ``ok.kinematics`` is every joint's ok.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.core.errors import ConfigError, DataError
from pipeline.logs import schema as S

STAGE = "smooth"
DIFFERENCES = 6  # order of the differences that bound the encoder noise's variance (white noise: exact)
DIFFERENCES_BOUND = 4.0  # the noise variance is at most this multiple of the differences' estimate
TIE_RAD2_S4 = 1e-12  # (rad/s^2)^2: estimated acceleration errors this close are one (a still joint's are 0)
LATTICE_TOL = 0.02  # steps: readings within this of a multiple of the step lie on the lattice
LATTICE_SHARE = 0.99  # share of a joint's position changes that must lie on the lattice
LATTICE_MIN_CHANGES = 20  # fewer changes than this: no lattice is decided (not quantised)
STILL_STEPS = 2.0 + LATTICE_TOL  # still: the readings of a window span at most this many steps ...
STILL_WINDOW_S = 2.0  # ... of at least this long a window, s. A joint at rest flickers by a step or two for
# good; a balancing robot's stance ankle sways by a count or two each half second, and that sway carries the
# whole robot's mass (1-2 N of inertial force in the foot's labels): over 2 s it spans more (the real one-foot
# run: a 0.6 s window held it still, and the labels' least squares lost 25 % against an independent one)


@dataclass(frozen=True)
class SmoothParams:
    """Section `smooth` of params.yaml (see the comments there)."""

    window: int  # samples, odd, > polyorder
    polyorder: int  # >= 2 (accelerations), < window
    max_gap_s: float  # s: stamp steps above this split the series into separately smoothed segments
    choices: tuple[tuple[int, int], ...] = ()  # (window, polyorder) settings chosen among per segment

    def __post_init__(self) -> None:
        w, p, g = self.window, self.polyorder, self.max_gap_s
        _check_setting("smooth.window", "smooth.polyorder", w, p)
        if isinstance(g, bool) or not isinstance(g, int | float) or not math.isfinite(g) or g <= 0:
            raise ConfigError(f"smooth.max_gap_s must be a positive number of seconds, got {g!r}")
        object.__setattr__(self, "max_gap_s", float(g))
        if not isinstance(self.choices, list | tuple):
            raise ConfigError(
                f"smooth.choices must be a list of [window, polyorder] pairs, got {self.choices}"
            )
        settings = []
        for k, pair in enumerate(self.choices):
            if not isinstance(pair, list | tuple) or len(pair) != 2:
                raise ConfigError(f"smooth.choices[{k}] must be a [window, polyorder] pair, got {pair!r}")
            _check_setting(f"smooth.choices[{k}] window", f"smooth.choices[{k}] polyorder", *pair)
            settings.append((int(pair[0]), int(pair[1])))
        if len(set(settings)) != len(settings):
            raise ConfigError(f"smooth.choices lists a setting twice: {self.choices!r}")
        object.__setattr__(self, "choices", tuple(settings))

    @property
    def settings(self) -> tuple[tuple[int, int], ...]:
        """The (window, polyorder) settings a segment is smoothed with: the choices, or the one."""
        return self.choices or ((self.window, self.polyorder),)

    @property
    def widest(self) -> int:
        """The widest window of the settings, samples."""
        return max(w for w, _ in self.settings)

    @property
    def narrowest(self) -> int:
        """The narrowest window of the settings, samples: a shorter segment is not smoothed."""
        return min(w for w, _ in self.settings)


def _check_setting(window_key: str, order_key: str, w: object, p: object) -> None:
    if isinstance(w, bool) or not isinstance(w, int) or w < 3 or w % 2 == 0:
        raise ConfigError(f"{window_key} must be an odd integer >= 3, got {w!r}")
    if isinstance(p, bool) or not isinstance(p, int) or not 2 <= p < w:
        raise ConfigError(f"{order_key} must be an integer in [2, window), got {p!r}")


# --- pure functions ------------------------------------------------------------------------------


def segments(stamps_ns: np.ndarray, max_gap_ns: int) -> list[tuple[int, int]]:
    """[start, stop) index ranges of the runs of `stamps_ns` (N,) int64 whose steps are all <= max_gap_ns."""
    if len(stamps_ns) == 0:
        return []
    cuts = np.flatnonzero(np.diff(stamps_ns) > max_gap_ns) + 1
    bounds = [0, *cuts.tolist(), len(stamps_ns)]
    return list(zip(bounds[:-1], bounds[1:], strict=True))


def _interp_rows(x_new: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Linear interpolation (extrapolation past the ends) of the rows of y (M, J) at x_new; x increasing."""
    if len(x) == 1:
        return np.repeat(y, len(x_new), axis=0)
    idx = np.clip(np.searchsorted(x, x_new, side="right") - 1, 0, len(x) - 2)
    w = (x_new - x[idx]) / (x[idx + 1] - x[idx])
    return y[idx] + w[:, None] * (y[idx + 1] - y[idx])


def quantisation_step(q: np.ndarray) -> float:
    """The encoder step of joint positions q (N,) rad: the smallest change, where every change (at least
    `LATTICE_SHARE` of them, `LATTICE_MIN_CHANGES` or more) is a whole number of it within `LATTICE_TOL`;
    0.0 where the readings lie on no lattice (noise above a step, no quantisation, too few changes)."""
    q = np.asarray(q, dtype=np.float64)
    q = q[np.isfinite(q)]
    d = np.abs(np.diff(q))
    scale = max(float(np.max(np.abs(q), initial=0.0)), 1.0)
    d = d[d > 1e-12 * scale]
    if len(d) < LATTICE_MIN_CHANGES:
        return 0.0
    step = float(np.quantile(d, 0.01))
    ratio = d / step
    on = np.abs(ratio - np.round(ratio)) <= LATTICE_TOL
    return step if on.mean() >= LATTICE_SHARE else 0.0


def still_mask(q: np.ndarray, step: float, window: int) -> np.ndarray:
    """(M,) bool: the samples of q (M,) rad whose centred `window` (samples, odd; shorter at the ends)
    spans at most `STILL_STEPS` encoder steps: a joint at rest whose reading flickers by a step or two.
    All False where step is 0 (no lattice)."""
    from scipy.ndimage import maximum_filter1d, minimum_filter1d

    if step <= 0 or len(q) == 0:
        return np.zeros(len(q), dtype=bool)
    span = maximum_filter1d(q, window, mode="nearest") - minimum_filter1d(q, window, mode="nearest")
    return span <= STILL_STEPS * step


def hold_still(q: np.ndarray, steps: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Joint positions q (M, J) rad with each still stretch (`still_mask`, steps (J,) rad) replaced by its
    centred running mean over `window` samples (`_running_mean`): (held (M, J), still (M, J) bool).

    A running mean, not the stretch's one mean: a joint can creep by a step every half second for seconds
    (a balancing robot's stance ankle) with every window still; one mean would put the stretch's ends
    several steps (tenths of a degree, a torque of 0.5 Nm in the foot's labels) away from where it was."""
    held, still = q.copy(), np.zeros(q.shape, dtype=bool)
    for j in np.flatnonzero(steps > 0):
        mask = still_mask(q[:, j], float(steps[j]), window)
        still[:, j] = mask
        if not mask.any():
            continue
        edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
        for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True):
            held[a:b, j] = _running_mean(q[a:b, j], window // 2)
    return held, still


def _running_mean(x: np.ndarray, half: int) -> np.ndarray:
    """(M,) the mean of x (M,) over each sample's centred window of 2 half + 1 samples, cut at x's ends."""
    c = np.concatenate([[0.0], np.cumsum(x - x[0])])
    i = np.arange(len(x))
    lo, hi = np.maximum(i - half, 0), np.minimum(i + half + 1, len(x))
    return x[0] + (c[hi] - c[lo]) / (hi - lo)


def savgol_uniform(
    t_s: np.ndarray,
    q: np.ndarray,
    settings: Sequence[tuple[int, int]],
    steps: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, np.ndarray] | None:
    """SG smoothing of one gap-free segment with the setting of `settings` that `choose_setting` picks
    (the one setting, if one is given), still joints held (`hold_still`).

    Args:
        t_s: (M,) s, increasing sample times (any origin).
        q: (M, J) positions (rad).
        settings: (window, polyorder) pairs: SG window (samples, odd) and polynomial order.
        steps: (J,) rad, each joint's encoder step (`quantisation_step`; 0: none); None: no joint's.

    Returns:
        (q, dq, ddq, chosen, still): the first three (M, J) in rad, rad/s, rad/s^2 (a still sample's dq and
        ddq exactly 0), chosen the index in `settings` of the setting, still (M, J) bool the samples held
        still; None if the segment is shorter than every window.
    """
    from scipy.signal import savgol_filter  # here: params validation imports this module, not scipy

    if len(t_s) < 2:
        return None
    dt = float(np.median(np.diff(t_s)))
    n = int(round((t_s[-1] - t_s[0]) / dt)) + 1
    usable = [k for k, (w, _) in enumerate(settings) if w <= min(n, len(t_s))]
    if not usable:
        return None
    steps = np.zeros(q.shape[1]) if steps is None else np.asarray(steps, dtype=np.float64)
    held, still = hold_still(q, steps, max(max(w for w, _ in settings), int(round(STILL_WINDOW_S / dt)) | 1))
    grid = t_s[0] + np.arange(n) * dt
    uniform = _interp_rows(grid, t_s, held)
    floor = np.where(still.all(axis=0), 0.0, steps**2 / 12.0)  # a moving joint's lattice noise, rad^2
    picked = choose_setting(uniform, [settings[k] for k in usable], dt, floor) if len(usable) > 1 else 0
    chosen = usable[picked]
    w, p = settings[chosen]
    out = []
    for deriv in (0, 1, 2):
        g = _interp_rows(
            t_s, grid, savgol_filter(uniform, w, p, deriv=deriv, delta=dt, axis=0, mode="interp")
        )
        g[still] = held[still] if deriv == 0 else 0.0
        out.append(g)
    return out[0], out[1], out[2], chosen, still


def choose_setting(
    uniform: np.ndarray, settings: Sequence[tuple[int, int]], dt: float, floor: np.ndarray | None = None
) -> int:
    """The index in `settings` of the SG setting with the least estimated error of the joints' accelerations
    (summed over the joints), the quantity of the labels the smoothing decides (the dynamics are linear in
    it). One setting for all the joints: a link's motion composes theirs (a foot held still by a moving leg),
    and only one linear filter applied to every joint filters their composition alike (a setting per joint
    lets their errors add up where they cancel: measured, a standing foot's labels 0.086 -> 0.143 N/Nm).

    uniform: (M, J) positions (rad) on a uniform grid of step dt (s), M >= every window. A setting's
    acceleration error is its bias squared plus its noise variance. The least-biased setting, the narrowest
    window with its highest order, is the reference r: the encoder noise variance s2 of each joint is its
    residual's mean square divided by 1 - h_r (h_r the centre weight of r's smoothing: the residual of a
    linear least-squares smoother keeps that share of white noise), at most 4 times the estimate from its
    6th differences (a noise-free encoder's residual is r's bias), and at least `floor` (J,) rad^2 (an
    encoder's quantisation noise, step^2 / 12; None: 0); a setting c's noise variance is
    ``s2 |k_c|^2``, k_c its acceleration kernel; its bias squared (against r's) is the median over the
    samples of ``|a_c - a_r|^2`` (the joints summed) less the median of the noise that difference carries
    (``sum(s2) |k_c - k_r|^2`` its mean, a share of it its median). The median, not the mean: the segment's
    typical sample decides, not a rare fast moment (a load put on, after which the labels wait for the
    robot to settle); measured against the simulator's truth, the mean chose 41/7 for a known load whose
    labels it left 3 times the median's choice's error. A bias beats noise on a fast motion (a gait's
    steps: a narrow window), noise beats bias on a slow one (a known load: a wide window). Settings within
    2 % of the least error (or within 1e-6 rad/s^2 of it) go to the first listed: a choice does not hang
    on the last bits of the estimate.
    """
    from scipy.signal import savgol_coeffs, savgol_filter

    widest = max(w for w, _ in settings)
    narrowest = min(w for w, _ in settings)
    ref = (narrowest, max(p for w, p in settings if w == narrowest))
    half = widest // 2
    inner = slice(half, len(uniform) - half) if len(uniform) > 2 * half else slice(None)

    def kernel(setting: tuple[int, int], deriv: int) -> np.ndarray:  # (widest,), centred, zero-padded
        w, p = setting
        c = savgol_coeffs(w, p, deriv=deriv, delta=dt, use="dot")
        return np.pad(c, (widest - w) // 2)

    def fit(setting: tuple[int, int], deriv: int) -> np.ndarray:
        w, p = setting
        return savgol_filter(uniform, w, p, deriv=deriv, delta=dt, axis=0, mode="interp")[inner]

    h_ref = kernel(ref, 0)[half]
    s2 = np.mean((uniform[inner] - fit(ref, 0)) ** 2, axis=0) / (1.0 - h_ref)  # (J,) rad^2
    # a noise-free encoder's residual is r's bias, not noise: at most a multiple of the differences' estimate
    diff = np.mean(np.diff(uniform, DIFFERENCES, axis=0) ** 2, axis=0)
    s2 = np.minimum(s2, DIFFERENCES_BOUND * diff / math.comb(2 * DIFFERENCES, DIFFERENCES))
    if floor is not None:
        s2 = np.maximum(s2, floor)
    a_ref, k_ref = fit(ref, 2), kernel(ref, 2)
    # the median of noise alone in a sum of squares over the joints: Wilson-Hilferty's, with the sum's
    # effective degrees of freedom (1 joint: 0.47 of the mean, many alike: the mean)
    dof = max(1.0, np.sum(s2) ** 2 / max(np.sum(s2**2), np.finfo(float).tiny))  # 1 to J (still joints: 0)
    median_share = (1.0 - 2.0 / (9.0 * dof)) ** 3
    total = np.empty(len(settings))
    for k, setting in enumerate(settings):
        k_c = kernel(setting, 2)
        departure = np.sum((fit(setting, 2) - a_ref) ** 2, axis=1)  # (M,) summed over the joints
        bias2 = np.median(departure) - median_share * np.sum(s2) * np.sum((k_c - k_ref) ** 2)
        total[k] = max(bias2, 0.0) + np.sum(s2) * np.sum(k_c**2)  # (rad/s^2)^2
    return int(np.argmax(total <= total.min() * 1.02 + TIE_RAD2_S4))


@dataclass
class SmoothResult:
    """Smoothed kinematics of one log: arrays (N, J), per-joint ok (N, J) and every joint's ok (N,), plus
    segment bookkeeping (summed over the groups of joints sharing one validity mask)."""

    q: np.ndarray
    dq: np.ndarray
    ddq: np.ndarray
    ok: np.ndarray
    joint_ok: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=bool))
    segments: int = 0
    short_segments: int = 0  # too short to smooth: NaN, not ok
    periods_s: list[float] = field(default_factory=list)  # median step per smoothed segment
    chosen: dict[tuple[int, int], int] = field(default_factory=dict)  # (window, order): segments smoothed
    steps: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (J,) rad, encoder step (0: none)
    still: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=bool))  # (N, J) held still


def validity_groups(valid: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The joints of `valid` (N, J) bool grouped by identical columns: [(rows (M,), joint columns (K,))],
    groups without a valid row left out."""
    if valid.shape[1] == 0:
        return []
    masks, which = np.unique(valid.T, axis=0, return_inverse=True)
    which = np.asarray(which).reshape(-1)
    return [(np.flatnonzero(mask), np.flatnonzero(which == g)) for g, mask in enumerate(masks) if mask.any()]


def smooth_kinematics(
    stamps_ns: np.ndarray,
    q: np.ndarray,
    window: int,
    polyorder: int,
    max_gap_s: float,
    choices: Sequence[tuple[int, int]] = (),
    steps: Sequence[float] | None = None,
) -> SmoothResult:
    """Savitzky-Golay positions, velocities, accelerations of joint positions q (N, J) rad at stamps (N,) ns.

    Each joint is smoothed on its finite samples, segments split at stamp steps > max_gap_s (s) smoothed
    separately (see the module docstring), with `window` and `polyorder`, or, given `choices` ((window,
    polyorder) pairs), with the one `choose_setting` picks per segment. `steps` (J,) rad: each joint's
    encoder step where the recording knows it (0: found from q, `quantisation_step`). ``ok`` (N,) is
    ``joint_ok`` (N, J) of every joint.
    """
    settings = tuple(choices) or ((window, polyorder),)
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    q = np.asarray(q, dtype=np.float64)
    n, j = q.shape
    res = SmoothResult(
        np.full((n, j), np.nan),
        np.full((n, j), np.nan),
        np.full((n, j), np.nan),
        np.zeros(n, dtype=bool),
        np.zeros((n, j), dtype=bool),
        still=np.zeros((n, j), dtype=bool),
    )
    t_s = (stamps_ns - (stamps_ns[0] if n else 0)) / 1e9
    max_gap_ns = round(max_gap_s * 1e9)
    known = np.zeros(j) if steps is None else np.asarray(steps, dtype=np.float64)
    res.steps = np.array([known[k] or quantisation_step(q[:, k]) for k in range(j)])
    for rows, cols in validity_groups(np.isfinite(q)):
        every = len(rows) == n and len(cols) == j  # a complete log: the arrays as they are, no copy
        part_q = q if every else q[np.ix_(rows, cols)]
        for start, stop in segments(stamps_ns[rows], max_gap_ns):
            res.segments += 1
            smoothed = savgol_uniform(t_s[rows[start:stop]], part_q[start:stop], settings, res.steps[cols])
            if smoothed is None:
                res.short_segments += 1
                continue
            at = rows[start:stop]
            for out, values in zip(
                (res.q, res.dq, res.ddq, res.still), (*smoothed[:3], smoothed[4]), strict=True
            ):
                if every:
                    out[start:stop] = values
                else:
                    out[np.ix_(at, cols)] = values
            # within half a window of a segment's ends the fit is one-sided (mode "interp"): its
            # derivatives extrapolate, so those samples keep their values but are not ok for labelling
            setting = settings[smoothed[3]]
            half = setting[0] // 2
            res.joint_ok[np.ix_(at[half : len(at) - half], cols)] = True
            res.chosen[setting] = res.chosen.get(setting, 0) + 1
            res.periods_s.append(float(np.median(np.diff(t_s[at]))))
    res.ok = res.joint_ok.all(axis=1) if j else res.ok
    return res


# --- I/O -----------------------------------------------------------------------------------------


@dataclass
class SmoothReport:
    source: str
    output: str
    samples: int
    segments: int
    short_segments: int
    samples_not_ok: int
    seconds: float
    joints_never_ok: list[str] = field(default_factory=list)  # no ok sample in the log (absent streams)


def smooth_table(src: Path, dst: Path, cfg: SmoothParams) -> SmoothReport:
    """Read an ingested table, add the smoothed kinematics columns, write it atomically to `dst`."""
    from pipeline.core.io import atomic_path
    from pipeline.logs.sidecar import declared_steps
    from pipeline.logs.tables import read_table_metadata

    t0 = time.perf_counter()
    try:
        pf = pq.ParquetFile(src)
        names = pf.schema_arrow.names
    except (OSError, pa.ArrowException) as exc:
        raise DataError(f"{src}: cannot read Parquet table: {exc}") from None
    joints = S.joints_of(names, S.Q)
    if S.STAMP not in names or not joints:
        raise DataError(f"{src}: not an ingested table (no {S.STAMP} or {S.Q}.<joint> columns)")
    base = pf.read(columns=[S.STAMP, *S.joint_cols(S.Q, joints)])
    stamps = base.column(S.STAMP).to_numpy()
    if len(stamps) > 1 and not (np.diff(stamps) > 0).all():
        raise DataError(f"{src}: {S.STAMP} is not strictly increasing")
    q = (
        np.column_stack([base.column(c).to_numpy() for c in S.joint_cols(S.Q, joints)])
        if len(stamps)
        else np.empty((0, len(joints)))
    )
    del base
    meta = read_table_metadata(pf)
    known = declared_steps((meta.get(S.META_SOURCE.decode()) or {}).get("metadata") or {})
    steps = [known.get(jt, 0.0) for jt in joints]
    res = smooth_kinematics(stamps, q, cfg.window, cfg.polyorder, cfg.max_gap_s, cfg.choices, steps)
    extra = S.smoothed_extra_columns(joints)
    never = [jt for k, jt in enumerate(joints) if len(stamps) and not res.joint_ok[:, k].any()]
    smooth_meta = {
        **asdict(cfg),
        "segments": res.segments,
        "short_segments": res.short_segments,
        "samples_not_ok": int((~res.ok).sum()),
        "median_period_s": float(np.median(res.periods_s)) if res.periods_s else None,
        "chosen": {f"{w}/{p}": n for (w, p), n in sorted(res.chosen.items())},  # segments per setting
        "joints_never_ok": never,  # no ok sample: absent from the log (or never a smoothable stretch)
        # encoders on a lattice: each joint's step (deg) and the share of its samples held still
        "encoder_steps_deg": {
            jt: math.degrees(st) for jt, st in zip(joints, res.steps, strict=True) if st > 0
        },
        "still": {jt: float(res.still[:, k].mean()) for k, jt in enumerate(joints) if res.steps[k] > 0},
    }
    kv = {k.encode(): v for k, v in meta.items() if k != S.META_SCHEMA.decode()}
    kv[S.META_SMOOTH] = smooth_meta
    out_schema = S.arrow_schema([*names, *extra], S.KIND_SMOOTHED, kv)
    row = 0
    with atomic_path(dst) as tmp, pq.ParquetWriter(tmp, out_schema, compression="zstd") as writer:
        for batch in pf.iter_batches(batch_size=65_536):
            k = batch.num_rows
            cols = {name: batch.column(name) for name in names}
            sl = slice(row, row + k)
            for quantity, arr in ((S.QS, res.q), (S.DQS, res.dq), (S.DDQS, res.ddq)):
                for jj, name in enumerate(S.joint_cols(quantity, joints)):
                    cols[name] = pa.array(arr[sl, jj])
            cols[S.ok_col(S.KINEMATICS_STREAM)] = pa.array(res.ok[sl])
            for jj, name in enumerate(S.joint_ok_cols(joints)):
                cols[name] = pa.array(res.joint_ok[sl, jj])
            writer.write_table(pa.Table.from_pydict(cols, schema=out_schema))
            row += k
    return SmoothReport(
        str(src),
        str(dst),
        len(stamps),
        res.segments,
        res.short_segments,
        int((~res.ok).sum()),
        time.perf_counter() - t0,
        never,
    )


def find_tables(in_dir: Path) -> list[Path]:
    """The ingested tables of a directory (not the truth tables), sorted."""
    truth = S.TRUTH_SUFFIX + S.PARQUET_SUFFIX
    return sorted(p for p in in_dir.glob(f"*{S.PARQUET_SUFFIX}") if not p.name.endswith(truth))
