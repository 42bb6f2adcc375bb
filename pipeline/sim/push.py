"""External pushes on a simulated motion: a hand pushing a foot of the robot on the pole.

A push is a wrench on one link: a half-sine force profile along a fixed world direction, applied at the
link frame's origin. It changes no joint trajectory (the joints track their references, as under stiff
position control); it shows in the true wrench of every sensor between it and the fixed link and in the
true joint torques (:mod:`pipeline.sim.truth`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from pipeline.sim.kinematics import Kinematics
from pipeline.sim.motion import Motion
from pipeline.sim.params import PushParams


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
            wrench[k] = np.r_[f, np.cross(kin.frame_pose(motion.q[k], link).translation, f)]
        pushes[link] = wrench
    return replace(motion, pushes=pushes)
