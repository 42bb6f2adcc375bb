"""Contact sets of a log: declared by the experiment, or detected from the raw foot-sensor forces.

Detection, per foot: the foot's normal force is the sum of its sensors' raw readings (one, or front and
rear) mapped to the sole frame (minus sign: the floor pushes up). Raw readings carry offsets, so the
force is measured from the foot's zero level, the median of its lowest readings (the foot in the air).
A foot touches when that force rises above ``contact_on`` x robot weight and stops when it falls below
``contact_off`` x robot weight (hysteresis; robot weight = the URDF's total mass times gravity); a
touching foot touches with all its parts. Around every change of the contact set a guard band of
+- ``guard_s`` holds every switch at 0: the labels of either set are not trusted there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from pipeline.core.config import LabelParams
from pipeline.core.errors import DataError
from pipeline.physics.feet import Foot
from pipeline.physics.robot import RobotModel


def foot_normal_force(foot: Foot, raw: dict[str, np.ndarray]) -> np.ndarray:
    """(N,) force the floor would need to push the foot up with, N, from the raw readings (N, 6) of its
    sensors: minus the z component (sole frame) of what the rest of the robot exerts on the foot.
    Offsets and the foot's own weight remain in it (see `zero_level`)."""
    return -foot.rest_on_foot(raw)[:, 2]


def zero_level(normal: np.ndarray, quantile: float) -> float:
    """The reading of a foot in the air: the median of its readings below the `quantile` quantile."""
    finite = normal[np.isfinite(normal)]
    if finite.size == 0:
        return math.nan
    low = finite[finite <= np.quantile(finite, quantile)]
    return float(np.median(low))


def hysteresis(force: np.ndarray, on: float, off: float) -> np.ndarray:
    """(N,) bool: True from where `force` rises above `on` until it falls below `off` (N; NaN keeps state).
    Starts from the side of the first finite sample."""
    state = np.zeros(force.shape[0], dtype=bool)
    finite = np.flatnonzero(np.isfinite(force))
    current = bool(finite.size and force[finite[0]] > 0.5 * (on + off))
    for k, value in enumerate(force):
        if value > on:
            current = True
        elif value < off:
            current = False
        state[k] = current
    return state


def guard_band(time_s: np.ndarray, changed: np.ndarray, guard_s: float) -> np.ndarray:
    """(N,) bool: samples within `guard_s` of a change; a change at sample k happens halfway between
    samples k-1 and k (`changed[k]` True)."""
    events = 0.5 * (time_s[1:] + time_s[:-1])[changed[1:]]
    if events.size == 0 or guard_s <= 0:
        return np.zeros(time_s.shape[0], dtype=bool)
    idx = np.searchsorted(events, time_s)
    before = np.abs(time_s - events[np.clip(idx - 1, 0, events.size - 1)])
    after = np.abs(events[np.clip(idx, 0, events.size - 1)] - time_s)
    return np.minimum(before, after) < guard_s


@dataclass
class Contacts:
    """Contact sets of a log. sets: the distinct sets; index: (N,) per sample, -1 where no foot touches;
    fixed: (N,) the fixed link per sample ('' where none); guard: (N,) in a guard band; detected: whether
    the contacts were detected (else declared); zero_levels: per foot, N."""

    sets: list[frozenset[str]]
    index: np.ndarray
    fixed: np.ndarray
    guard: np.ndarray
    detected: bool
    zero_levels: dict[str, float] = field(default_factory=dict)  # per foot, N


def declared_contacts(robot: RobotModel, experiment: dict[str, str], n: int) -> Contacts | None:
    """The experiment's constant contact set, if its metadata declares one."""
    names = [c for c in experiment.get("contacts", "").split(",") if c]
    if not names:
        return None
    for name in names:
        robot.check_link(name, "contact link")
    contacts = frozenset(names)
    fixed = experiment.get("fixed_link") or ""
    if not fixed:
        fixed = sorted(contacts)[0]
    robot.check_link(fixed, "fixed link")
    return Contacts(
        [contacts],
        np.zeros(n, dtype=int),
        np.full(n, fixed, dtype=object),
        np.zeros(n, dtype=bool),
        detected=False,
    )


def detect_contacts(
    robot: RobotModel,
    pairs: list[Foot],
    raw: dict[str, np.ndarray],
    time_s: np.ndarray,
    cfg: LabelParams,
    gravity: float,
    source: str,
) -> Contacts:
    """Foot contacts from the raw foot-sensor normal forces of `pairs`, the feet (module docstring)."""
    weight = robot.total_mass() * gravity
    n = time_s.shape[0]
    touching, levels = {}, {}
    for pair in pairs:
        normal = foot_normal_force(pair, raw)
        level = zero_level(normal, cfg.zero_quantile)
        spread = np.nanquantile(normal, 0.95) - np.nanquantile(normal, 0.05) if np.isfinite(level) else 0.0
        if not spread > 2 * cfg.contact_on * weight:
            raise DataError(
                f"{source}: cannot detect the contacts of {pair.name}: its normal force never changes by "
                f"{2 * cfg.contact_on:.0%} of the robot's weight (the foot never lifts or never lands); "
                "declare the contacts in the log's experiment metadata"
            )
        levels[pair.name] = level
        touching[pair.name] = hysteresis(normal - level, cfg.contact_on * weight, cfg.contact_off * weight)
    links = {p.name: p.front_link for p in pairs}
    rear = {p.name: p.rear_link for p in pairs}
    labels = np.array(
        [",".join(p.name for p in pairs if touching[p.name][k]) for k in range(n)], dtype=object
    )
    keys, index = np.unique(labels, return_inverse=True)
    sets = [
        frozenset(c for name in key.split(",") if name for c in (links[name], rear[name])) for key in keys
    ]
    index = np.where(labels == "", -1, index)
    # fixed link: a sole of a touching foot, kept while that foot touches (both soles are still in double
    # support; the choice only picks the frame of the computation)
    sole = {p.name: p.sole for p in pairs}
    fixed = np.full(n, "", dtype=object)
    current = ""
    for k in range(n):
        on = [p.name for p in pairs if touching[p.name][k]]
        if current not in on:
            current = on[0] if on else ""
        fixed[k] = sole[current] if current else ""
    changed = np.r_[False, index[1:] != index[:-1]]
    return Contacts(sets, index, fixed, guard_band(time_s, changed, cfg.guard_s), True, levels)


__all__ = [
    "Contacts",
    "declared_contacts",
    "detect_contacts",
    "foot_normal_force",
    "guard_band",
    "hysteresis",
    "zero_level",
]
