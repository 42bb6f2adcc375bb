"""The footstep plan of a simulated walk and its per-sample targets (feet, contacts, weight transfer, CoM).

A walk goes straight forward, then as far backward, alternating single support (stance sole fixed,
swing foot lifting and landing) and double support (weight transfer). World frame: floor z = 0, z up,
x forward, origin between the feet at the start. Lengths in m, times in s.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from pipeline.sim.kinematics import Foot, interp, smoothstep


class Phase(NamedTuple):
    """One phase of the walk. In single support ('ss') `foot` stands and `swing` moves from x_from to
    x_to; in double support ('ds') `foot` is the foot taking over the load."""

    start: float
    end: float
    kind: str  # 'ss' | 'ds'
    foot: str
    swing: str | None
    x_from: float
    x_to: float


def plan_steps(
    duration: float,
    names: list[str],
    y: dict[str, float],
    step_length: float,
    single_s: float,
    double_s: float,
    steps_per_direction: int,
) -> list[Phase]:
    """Phases covering `duration`: 1 s of double support, then steps (half steps to start and stop,
    feet side by side before turning back). The foot with the lowest y (the right one) swings first."""
    first = min(names, key=lambda f: y[f])
    second = next(f for f in names if f != first)
    x = {f: 0.0 for f in names}
    t0 = 1.0
    phases = [Phase(0.0, t0, "ds", second, None, 0.0, 0.0)]
    swing, stance, step, direction = first, second, 0, 1.0
    while t0 < duration:
        target = x[stance] + direction * step_length
        if step == 0 or step == steps_per_direction:
            target = x[stance] + direction * step_length / 2  # half steps to start and stop
        phases.append(Phase(t0, t0 + single_s, "ss", stance, swing, x[swing], target))
        x[swing] = target
        t0 += single_s
        phases.append(Phase(t0, t0 + double_s, "ds", swing, stance, 0.0, 0.0))
        t0 += double_s
        swing, stance = stance, swing
        step += 1
        if step == steps_per_direction + 1:
            if abs(x[swing] - x[stance]) < 1e-9:
                direction, step = -direction, 0
            else:  # bring the feet side by side before turning back
                step = steps_per_direction
    return phases


@dataclass
class GaitSamples:
    """Per-sample targets of a walk (N samples; feet in the order of `names`)."""

    contacts: list[frozenset[str]]
    fixed: np.ndarray  # (N,) object: the sole fixed in the world
    transfer: np.ndarray  # (N,) load fraction on the foot taking over in double support, NaN elsewhere
    transfer_to: np.ndarray  # (N,) object: that foot's name, '' elsewhere
    feet_x: np.ndarray  # (N, 2) sole x, m
    feet_z: np.ndarray  # (N, 2) sole height, m


def sample_gait(
    t: np.ndarray,
    phases: list[Phase],
    feet: dict[str, Foot],
    step_lift: float,
    skews: np.ndarray,
) -> GaitSamples:
    """Contacts, fixed sole, weight transfer and sole positions at the sample times `t` (s).

    skews: (len(phases),) exponent of each double support's transfer profile (a split the labeller
    cannot know). The swing foot rises ``step_lift`` m at mid-step, still at both ends up to the snap.
    """
    names = list(feet)
    n = t.shape[0]
    out = GaitSamples(
        [],
        np.empty(n, dtype=object),
        np.full(n, np.nan),
        np.full(n, "", dtype=object),
        np.zeros((n, 2)),
        np.zeros((n, 2)),
    )
    x_now = {f: 0.0 for f in names}
    both = feet[names[0]].links | feet[names[1]].links
    k = 0
    for i, (start, end, kind, foot, swing_foot, x_from, x_to) in enumerate(phases):
        while k < n and t[k] < end:
            s = (t[k] - start) / (end - start)
            if kind == "ss":
                out.contacts.append(feet[foot].links)
                out.fixed[k] = feet[foot].sole
                x_now[swing_foot] = x_from + (x_to - x_from) * smoothstep(np.array(s))
                out.feet_z[k, names.index(swing_foot)] = step_lift * 1024 * (s * (1 - s)) ** 5
            else:
                out.contacts.append(both)
                other = next(f for f in names if f != foot)
                out.fixed[k] = feet[other].sole if i > 0 else feet[foot].sole
                out.transfer[k] = float(smoothstep(np.array(s ** skews[i])))
                out.transfer_to[k] = foot
            for j, f in enumerate(names):
                out.feet_x[k, j] = x_now[f]
            k += 1
        if k >= n:
            break
    return out


def walking_com(t: np.ndarray, phases: list[Phase], y: dict[str, float], root_height: float) -> np.ndarray:
    """(N, 2) CoM path of a dynamically feasible walk (linear inverted pendulum): a sideways sway
    phase-locked to the steps, over the stance foot at mid single support, with an amplitude whose
    ZMP (= c - z/g c'') stays on the feet; forward, a spline through the stance feet at mid stance."""
    singles = [(0.5 * (p.start + p.end), p.foot) for p in phases if p.kind == "ss"]
    step_period = phases[1].end - phases[1].start + phases[2].end - phases[2].start
    omega2 = (np.pi / step_period) ** 2
    zmp_gain = 1.0 + root_height * omega2 / 9.81  # ZMP amplitude / CoM amplitude
    half_width = min(abs(v) for v in y.values())
    amplitude = 0.6 * half_width / zmp_gain
    t_first, first_foot = singles[0]
    side = np.sign(y[first_foot])
    lateral = side * amplitude * np.cos(np.pi * (t - t_first) / step_period)
    lateral *= smoothstep(t / t_first)  # start from standing still
    knots_t = np.r_[0.0, [m for m, _ in singles]]
    knots_x = np.r_[0.0, _stance_x(phases)]
    forward = interp(knots_t, knots_x)(np.clip(t, 0, knots_t[-1]))
    return np.stack([forward, lateral], axis=1)


def _stance_x(phases: list[Phase]) -> list[float]:
    """Stance-foot x at each single support, replaying the footsteps."""
    x: dict[str, float] = {}
    out = []
    for p in phases:
        if p.kind == "ss":
            out.append(x.get(p.foot, 0.0))
            x[p.swing] = p.x_to
    return out
