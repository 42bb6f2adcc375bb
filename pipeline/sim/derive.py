"""Robot-dependent defaults of the simulated motions, measured on the URDF.

A user changing ``robot.urdf`` should not have to retune the motions: every length and angle of
``simulate.motion`` left None is derived here from the robot's geometry at its home posture (every joint
at 0, clipped into its range), measured with the same kinematics the motions use:

- leg length L: height of root_link above the soles with straight legs (mean over the feet);
- hip half width W: half the lateral distance between the soles (smallest over the feet);
- foot length F: distance from the rear to the front contact part of a foot along the sole's x axis (the
  origins of the links below the foot's two FT sensors: the support polygon along the walking direction;
  for a foot of one sensor, the centres of its two halves, `pipeline.physics.feet`).

The rules (lengths rounded to 1 cm, small ones to 1 mm, angles to 0.01 rad, as one would write them in
params.yaml; for iCub 3 they give the values its motions were tuned with):

=====================  ===========================  ===================================================
field                  rule                          why
=====================  ===========================  ===================================================
root_height_m          L (1 - 1/15)                  knees bent: away from the straight-knee singularity
stance_lean_rad        atan(W / L)                   pelvis roll that puts the root over a foot
swing_lift_m           L / 20                        free foot clear of the floor
swing_forward_m        F                             free foot held one foot length ahead
swing_motion_m         F / 8                         free-foot wander
com_margin_m           F / 12                        CoM inside the edge of a supporting part
step_length_m          L / 8                         a short, quasi-static step
step_lift_m            L / 20                        swing-foot clearance
=====================  ===========================  ===================================================

Joints whose moving subtree weighs less than ``still_mass_fraction`` of the robot (fingers, cameras) are
held still: they load no sensor measurably and real experiments do not move them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from pipeline.physics.robot import RobotModel
from pipeline.sim.kinematics import Foot, Kinematics
from pipeline.sim.params import MotionParams


@dataclass(frozen=True)
class RobotGeometry:
    """What the motion defaults are derived from (home posture, root_link frame, m)."""

    leg_length_m: float  # root_link height above the soles, straight legs (mean over the feet)
    hip_half_width_m: float  # half the lateral distance between the soles (smallest over the feet)
    foot_length_m: float  # rear to front contact part along the sole x axis (smallest over the feet)
    still_joints: tuple[str, ...]  # joints held still (light subtrees)


def measure_geometry(
    robot: RobotModel, kin: Kinematics, feet: Sequence[Foot], still_mass_fraction: float
) -> RobotGeometry:
    """Measure `robot` at its home posture (every joint at 0 clipped to its range, minus the margin)."""
    home = np.clip(np.zeros(len(robot.joint_names)), kin.lower, kin.upper)
    soles = np.array([kin.frame_pose(home, f.sole).translation for f in feet])
    lengths = [f.centers(robot)[0][0] - f.centers(robot)[1][0] for f in feet]
    total = robot.total_mass()
    still = tuple(
        name
        for name in robot.joint_names
        if robot.mass_of(robot.subtree(robot.joints[name].child)) < still_mass_fraction * total
    )
    return RobotGeometry(
        leg_length_m=float(-soles[:, 2].mean()),
        hip_half_width_m=float(np.abs(soles[:, 1]).min()),
        foot_length_m=float(min(lengths)),
        still_joints=still,
    )


def derived_values(g: RobotGeometry) -> dict[str, float]:
    """Every derivable field of MotionParams from the geometry (module docstring: the rules)."""
    leg, foot = g.leg_length_m, g.foot_length_m
    return {
        "root_height_m": round(leg * (1.0 - 1.0 / 15.0), 2),
        "stance_lean_rad": round(math.atan2(g.hip_half_width_m, leg), 2),
        "swing_lift_m": round(leg / 20.0, 2),
        "swing_forward_m": round(foot, 2),
        "swing_motion_m": round(foot / 8.0, 3),
        "com_margin_m": round(foot / 12.0, 3),
        "step_length_m": round(leg / 8.0, 2),
        "step_lift_m": round(leg / 20.0, 2),
    }


def derive_motion(p: MotionParams, g: RobotGeometry) -> MotionParams:
    """`p` with every None field replaced by its derived value; numbers in `p` are kept (overrides)."""
    values = derived_values(g)
    return replace(p, **{k: v for k, v in values.items() if getattr(p, k) is None})
