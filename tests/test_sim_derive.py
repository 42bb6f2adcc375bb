"""Motion defaults derived from the URDF: iCub 3 keeps the values its motions were tuned with, ergoCub
gets its own, params override, and `simulate` runs on ergoCub with nothing but robot.urdf changed."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml

from pipeline.core.config import load_params
from pipeline.core.errors import ConfigError
from pipeline.sim.experiment import make_motion
from pipeline.sim.params import LogSpec, simulate_params
from pipeline.sim.world import build_world
from pipeline.stages.simulate import run
from tests.conftest import robot_source
from tests.factories.params import repo_params

pytestmark = pytest.mark.slow  # simulates on both robots

REPO = Path(__file__).resolve().parents[1]
SHORT_LOGS = [
    {"type": "pole", "duration_s": 3, "role": "train"},
    {"type": "balancing", "duration_s": 3, "role": "train", "foot": "l_foot"},
    {"type": "half_foot", "duration_s": 3, "role": "test", "foot": "r_foot", "part": "rear"},
    {"type": "walking", "duration_s": 6, "role": "test"},
]


def params_file(tmp: Path, urdf: str, logs: list | None = None, **motion: object) -> Path:
    """The repo's params.yaml with only robot.urdf (and optionally logs and motion keys) changed."""
    data = repo_params()
    data["robot"]["urdf"] = urdf
    data["simulate"]["motion"].update(motion)
    if logs is not None:
        data["simulate"].update({"logs": copy.deepcopy(logs), "workers": 1, "plots": False})
    path = tmp / "params.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def straight_leg_length(urdf: str) -> float:
    """Height of root_link above l_sole with every joint at 0, from Pinocchio's own URDF parser."""
    from pipeline.physics.robot import resolve_urdf

    model = pin.buildModelFromUrdf(str(resolve_urdf(urdf)))
    data = model.createData()
    pin.framesForwardKinematics(model, data, pin.neutral(model))
    return -data.oMf[model.getFrameId("l_sole")].translation[2]


def test_icub3_derives_the_values_its_motions_were_tuned_with(tmp_path: Path) -> None:
    params = load_params(params_file(tmp_path, "iCubGenova09"))
    world = build_world(params, simulate_params(params))
    p = world.motions.p
    tuned = dict(root_height_m=0.59, stance_lean_rad=0.1, swing_lift_m=0.03, swing_forward_m=0.12)
    tuned.update(swing_motion_m=0.015, com_margin_m=0.01, step_length_m=0.08, step_lift_m=0.03)
    assert {k: getattr(p, k) for k in tuned} == tuned
    assert world.motions.geometry.still_joints == ()  # iCub 3's lightest moving subtree is a 0.26 kg hand
    assert world.motions.geometry.leg_length_m == pytest.approx(straight_leg_length("iCubGenova09"), abs=1e-9)


def test_params_override_the_derivation_and_are_validated(tmp_path: Path) -> None:
    params = load_params(params_file(tmp_path, "iCubGenova09", root_height_m=0.57, step_length_m=0.05))
    p = build_world(params, simulate_params(params)).motions.p
    assert (p.root_height_m, p.step_length_m, p.step_lift_m) == (0.57, 0.05, 0.03)
    bad = params_file(tmp_path, "iCubGenova09", root_height_m=-0.5)
    with pytest.raises(ConfigError, match=r"params.yaml: simulate.motion.root_height_m must be in \(0, 5\)"):
        load_params(bad)  # every section is validated when params.yaml is loaded


@pytest.fixture(scope="module")
def ergocub(tmp_path_factory: pytest.TempPathFactory, mlflow_store: None) -> tuple:
    """`simulate` of the short logs on ergoCubSN001, robot.urdf being the only change to params.yaml."""
    urdf = robot_source("ergoCubSN001")
    tmp = tmp_path_factory.mktemp("ergocub")
    params = load_params(params_file(tmp, urdf, SHORT_LOGS))
    run(params, tmp / "sim", progress=False)
    return urdf, params, tmp / "sim"


def test_ergocub_runs_with_its_own_lengths_and_still_fingers(ergocub: tuple) -> None:
    urdf, params, sim_dir = ergocub
    assert len(list(sim_dir.glob("*.mcap"))) == len(SHORT_LOGS)
    summary = json.loads((sim_dir / "summary.json").read_text())
    leg = straight_leg_length(urdf)
    assert summary["geometry"]["leg_length_m"] == pytest.approx(leg, abs=1e-9)
    assert summary["motion"]["root_height_m"] == round(leg * 14 / 15, 2) == 0.73  # iCub 3: 0.59
    assert summary["motion"]["step_length_m"] == round(leg / 8, 2) == 0.10
    still = summary["geometry"]["still_joints"]
    assert len(still) == 25 and "camera_tilt" in still and "r_thumb_prox" in still  # 24 fingers + camera

    world = build_world(params, simulate_params(params))
    motion = make_motion(world, LogSpec("balancing", 3.0, "train", "r_foot"), np.random.default_rng(0))
    joints = world.robot.joint_names
    finger = [joints.index(j) for j in still]
    assert np.ptp(motion.q[:, finger], axis=0).max() < 1e-12  # still (up to the spline's rounding)
    assert np.ptp(motion.q[:, joints.index("r_elbow")]) > 0.05
    np.testing.assert_allclose(motion.root_pose[:, 2, 3], 0.73)


def test_ergocub_raw_errors_in_the_thesis_ranges(ergocub: tuple) -> None:
    """Pooled raw vs truth on ergoCub: legs 25-50 N and 1.5-6 Nm, foot-pair sums 50-100 N (as iCub 3)."""
    logs = json.loads((ergocub[2] / "summary.json").read_text())["logs"]

    def pooled(table: str, name: str, part: str) -> float:
        return math.sqrt(np.mean([entry[table][name][part] ** 2 for entry in logs]))

    for leg in ("l_leg_ft", "r_leg_ft"):
        assert 25.0 <= pooled("raw_rmse", leg, "force") <= 50.0, leg
        assert 1.5 <= pooled("raw_rmse", leg, "torque") <= 6.0, leg
    for pair in ("l_foot", "r_foot"):
        assert 50.0 <= pooled("pair_raw_rmse", pair, "force") <= 100.0, pair
