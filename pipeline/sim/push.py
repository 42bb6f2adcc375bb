"""External pushes on a simulated motion: a hand pushing a foot of the robot on the pole (Test C), and the
pushes and carried loads of interaction logs at every sensor's site (Test D).

A push is a wrench on one link: a half-sine force profile along a fixed world direction, applied at the
link frame's origin. It changes no joint trajectory (the joints track their references, as under stiff
position control); it shows in the true wrench of every sensor between it and the fixed link and in the
true joint torques (:mod:`pipeline.sim.truth`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from pipeline.core.errors import ConfigError
from pipeline.sim.interaction import InteractionParams
from pipeline.sim.kinematics import Kinematics, cross3, smoothstep
from pipeline.sim.motion import Motion
from pipeline.sim.params import PushParams
from pipeline.sim.sites import KIND_HAND, Site


def push_profile(t: np.ndarray, p: PushParams, n_links: int) -> tuple[np.ndarray, np.ndarray]:
    """Per sample (N,): the push force magnitude (N) and the index of the pushed link (-1: none).

    Pushes start at ``(k + 1/2) * period_s`` and last ``duration_s``; push k goes to link ``k % n_links``.
    """
    k = np.floor(t / p.period_s - 0.5).astype(int)
    phase = t - (k + 0.5) * p.period_s
    on = (k >= 0) & (phase < p.duration_s)
    force = np.where(on, p.force_n * np.sin(np.pi * np.clip(phase, 0, p.duration_s) / p.duration_s), 0.0)
    return force, np.where(on, k % max(n_links, 1), -1)


def add_pushes(kin: Kinematics, motion: Motion, links: Sequence[str], p: PushParams) -> Motion:
    """A copy of `motion` whose ``pushes`` hold the pushes of `p` on `links` in turn.

    The world frame must be the root_link frame (the pole), where `kin` gives link poses. Each wrench is
    (N, 6), N / Nm, about the world origin, zero outside that link's pushes.
    """
    force, who = push_profile(motion.t, p, len(links))
    direction = np.asarray(p.direction)
    pushes = {}
    for i, link in enumerate(links):
        wrench = np.zeros((motion.n, 6))
        for k in np.flatnonzero(who == i):
            f = force[k] * direction
            wrench[k] = np.concatenate((f, cross3(kin.frame_pose(motion.q[k], link).translation, f)))
        pushes[link] = wrench
    return replace(motion, pushes=pushes)


# --- interaction logs: pushes and a carried load at every sensor's site ---------------------------------


PUSH, LOAD = "push", "load"
LEVELS = 4  # push peak forces cycle through this many levels evenly spaced in force_n
LOAD_RAMP_S = 0.3  # a load is put into the hand and taken away over this long (smoothstep), s
FIRST_S = 1.0  # the first event starts after this long (the filters and the hysteresis settle), s


@dataclass(frozen=True)
class Event:
    """One push or carried load of an interaction log, at `site` between `start_s` and `end_s`.

    push: `magnitude` is the peak force (N) along `direction` (world frame); load: the mass (kg).
    """

    kind: str
    site: Site
    start_s: float
    end_s: float
    magnitude: float
    direction: tuple[float, float, float] = (0.0, 0.0, 0.0)


def interaction_events(sites: Sequence[Site], p: InteractionParams) -> list[Event]:
    """Every site pushed once per direction (one push every `period_s`), then every hand's load."""
    lo, hi = p.force_n
    levels = np.linspace(lo, hi, LEVELS)
    events, t = [], FIRST_S
    for i, site in enumerate(sites):
        for j, direction in enumerate(p.directions):
            force = float(levels[(i + j) % LEVELS])
            events.append(Event(PUSH, site, t, t + p.duration_s, force, direction))
            t += p.period_s
    if p.load_kg > 0 and p.load_s > 0:
        for site in sites:
            if site.kind == KIND_HAND:
                events.append(Event(LOAD, site, t, t + p.load_s, p.load_kg))
                t += p.load_s + p.period_s
    return events


def event_profile(t: np.ndarray, event: Event) -> np.ndarray:
    """(N,) in [0, 1]: a push's half-sine, or a load's plateau with smoothstep ramps, 0 outside."""
    span = event.end_s - event.start_s
    s = np.clip((t - event.start_s) / span, 0.0, 1.0)
    inside = (t >= event.start_s) & (t <= event.end_s)
    if event.kind == PUSH:
        return np.where(inside, np.sin(np.pi * s), 0.0)
    ramp = min(LOAD_RAMP_S / span, 0.5)
    up, down = np.clip(s / ramp, 0, 1), np.clip((1 - s) / ramp, 0, 1)
    return np.where(inside, smoothstep(np.minimum(up, down)), 0.0)


def add_interaction(
    kin: Kinematics, motion: Motion, events: Sequence[Event], gravity: float, duration_s: float
) -> Motion:
    """A copy of the pole `motion` whose ``pushes`` hold the wrenches of `events` (world = root_link frame).

    A push is its profile times the peak force along its direction at the site's point; a load is the weight
    and inertial force of a point mass at the site's point, ``m (g - a_p)``, with a_p the point's
    acceleration, times its profile. Raises ConfigError if the events do not fit in `duration_s`.
    """
    end = max((e.end_s for e in events), default=0.0)
    if end > duration_s:
        raise ConfigError(
            f"deploy.logs: the interaction log lasts {duration_s:g} s, its {len(events)} pushes and loads "
            f"need {end:g} s (raise its duration_s, or lower deploy.interaction.period_s)"
        )
    g = np.array([0.0, 0.0, -gravity])
    pushes: dict[str, np.ndarray] = {}
    for event in events:
        weight = event_profile(motion.t, event)
        active = np.flatnonzero(weight > 0)
        wrench = pushes.setdefault(event.site.link, np.zeros((motion.n, 6)))
        point = np.asarray(event.site.point)
        for k in active:
            where, acc = kin.point_motion(motion.q[k], motion.dq[k], motion.ddq[k], event.site.link, point)
            if event.kind == PUSH:
                force = weight[k] * event.magnitude * np.asarray(event.direction)
            else:
                force = weight[k] * event.magnitude * (g - acc)
            wrench[k] += np.concatenate((force, cross3(where, force)))
    return replace(motion, pushes={**motion.pushes, **pushes})
