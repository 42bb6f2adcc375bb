"""The simulate stage: MCAP contract, determinism, kinematic truth and raw-error magnitudes."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml
from mcap_ros2.reader import read_ros2_messages

from pipeline.core.config import load_params
from pipeline.core.errors import ConfigError
from pipeline.sim.experiment import make_motion
from pipeline.sim.params import simulate_params
from pipeline.sim.world import build_world
from pipeline.stages.simulate import run
from tests.factories.params import repo_params

pytestmark = pytest.mark.slow  # simulates whole logs

REPO = Path(__file__).resolve().parents[1]
SHORT_LOGS = [
    {"type": "pole", "duration_s": 4, "role": "train"},
    {"type": "balancing", "duration_s": 4, "role": "train", "foot": "l_foot"},
    {"type": "half_foot", "duration_s": 4, "role": "test", "foot": "r_foot", "part": "front"},
    {"type": "walking", "duration_s": 6, "role": "test"},
]


def write_params(tmp: Path, seed: int = 42, plots: bool = False, **simulate: object) -> Path:
    data = repo_params()
    data["seed"] = seed
    data["simulate"].update({"logs": copy.deepcopy(SHORT_LOGS), "workers": 1, "plots": plots, **simulate})
    path = tmp / f"params_{seed}_{plots}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory: pytest.TempPathFactory, mlflow_store: None) -> Path:
    tmp = tmp_path_factory.mktemp("sim")
    out = tmp / "sim"
    run(load_params(write_params(tmp, plots=True)), out, progress=False)
    return out


def test_outputs_and_plots(sim_dir: Path) -> None:
    logs = sorted(p.name for p in sim_dir.glob("*.mcap"))
    assert logs == [
        "00_pole_train.mcap",
        "01_balancing_l_foot_train.mcap",
        "02_half_foot_r_foot_front_test.mcap",
        "03_walking_test.mcap",
    ]
    plots = sorted(p.name for p in (sim_dir / "plots").glob("*.png"))
    assert len(plots) == 16 and "03_walking_test_contacts.png" in plots
    truth = json.loads((sim_dir / "truth.json").read_text())
    assert len(truth["distortions"]) == 8
    assert not list(sim_dir.parent.glob("*.tmp"))


def test_every_topic_decodes_with_the_standard_decoder(sim_dir: Path) -> None:
    params = load_params()
    summary = json.loads((sim_dir / "summary.json").read_text())
    # no wall-clock time in the stage's output: the same params give the same bytes
    assert "wall_seconds" not in summary and not any("seconds" in entry for entry in summary["logs"])
    for entry in summary["logs"]:
        path = sim_dir / f"{entry['name']}.mcap"
        count, topics, schemas = 0, set(), set()
        for msg in read_ros2_messages(str(path)):
            count += 1
            topics.add(msg.channel.topic)
            schemas.add(msg.schema.name)
        assert count == entry["messages"]
        sensors = [s for s in truth_sensors(sim_dir)]
        expected = {params.topics.joint_states, params.topics.sim_contacts}
        per_sensor = [k for k in params.topics.PER_SENSOR if k != "sim_wrench_external"]  # pushed logs only
        for s in sensors:
            expected |= {params.topics.sensor_topic(k, s) for k in per_sensor}
        assert topics == expected
        assert schemas == {
            "sensor_msgs/msg/JointState",
            "geometry_msgs/msg/WrenchStamped",
            "sensor_msgs/msg/Imu",
            "sensor_msgs/msg/Temperature",
            "std_msgs/msg/String",
        }


def truth_sensors(sim_dir: Path) -> list[str]:
    return list(json.loads((sim_dir / "truth.json").read_text())["distortions"])


def test_experiment_metadata(sim_dir: Path) -> None:
    from mcap.reader import make_reader

    with open(sim_dir / "02_half_foot_r_foot_front_test.mcap", "rb") as f:
        records = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    exp = records["experiment"]
    assert exp["type"] == "half_foot" and exp["role"] == "test" and exp["contacts"] == "r_foot_front"
    assert exp["fixed_link"] == "r_sole" and exp["sim"] == "true" and exp["gravity"] == "0 0 -9.80665"
    with open(sim_dir / "03_walking_test.mcap", "rb") as f:
        exp = {m.name: m.metadata for m in make_reader(f).iter_metadata()}["experiment"]
    assert exp["contacts"] == "" and exp["fixed_link"] == ""  # they change during a walk


def test_same_seed_same_logs_other_seed_other_logs(tmp_path: Path, sim_dir: Path, mlflow_store: None) -> None:
    again, other = tmp_path / "again", tmp_path / "other"
    run(load_params(write_params(tmp_path, plots=True)), again, progress=False)
    run(load_params(write_params(tmp_path, seed=7)), other, progress=False)
    for path in sim_dir.glob("*.mcap"):
        assert (again / path.name).read_bytes() == path.read_bytes(), path.name
        assert (other / path.name).read_bytes() != path.read_bytes(), path.name


@pytest.fixture(scope="module")
def world_and_motions(tmp_path_factory: pytest.TempPathFactory) -> tuple:
    params = load_params(write_params(tmp_path_factory.mktemp("p")))
    sim = simulate_params(params)
    world = build_world(params, sim)
    rng = np.random.default_rng(3)
    return world, {spec.type: make_motion(world, spec, rng) for spec in sim.logs}


def test_joint_limits_hold(world_and_motions: tuple) -> None:
    world, motions = world_and_motions
    lower = np.array([world.robot.joints[j].lower for j in world.robot.joint_names])
    upper = np.array([world.robot.joints[j].upper for j in world.robot.joint_names])
    for kind, motion in motions.items():
        assert np.all(motion.q >= lower) and np.all(motion.q <= upper), kind
        assert np.all(np.isfinite(motion.ddq)), kind


def test_soles_in_contact_do_not_move(world_and_motions: tuple) -> None:
    """Every foot in contact: flat on the floor (z = 0, level) and still, seen from the fixed sole.

    The fixed sole is still by construction; the other sole in double support is still to 2e-4 m/s:
    joint velocities are cubic-spline derivatives between exact IK postures (measured: 6e-5 m/s and
    0.02 m/s^2 at most, i.e. < 0.01 N on a foot part: far below what any sensor resolves).
    """
    world, motions = world_and_motions
    robot = world.robot
    for kind in ("balancing", "half_foot", "walking"):
        motion = motions[kind]
        checked = 0
        for k in range(0, motion.n, 7):
            fixed = motion.fixed_links[k]
            rooted = robot.rooted(fixed)
            model, data = rooted.model, rooted.model.createData()
            qs = pin.neutral(model)
            qs[rooted.q_index] = motion.q[k] * rooted.sign
            vs = np.zeros(model.nv)
            vs[rooted.v_index] = motion.dq[k] * rooted.sign
            pin.forwardKinematics(model, data, qs, vs)
            pin.updateFramePlacements(model, data)
            contacts = motion.contact_sets[motion.contact_index[k]]
            for foot in world.feet:
                if not contacts & foot.links:
                    continue
                fid = model.getFrameId(foot.sole)
                pose = data.oMf[fid]
                vel = pin.getFrameVelocity(model, data, fid, pin.LOCAL_WORLD_ALIGNED).vector
                assert abs(pose.translation[2]) < 1e-6, (kind, k, foot.sole)
                np.testing.assert_allclose(pose.rotation[:, 2], [0, 0, 1], atol=1e-6)
                np.testing.assert_allclose(vel, 0.0, atol=2e-4, err_msg=f"{kind} {k} {foot.sole}")
                checked += 1
        assert checked > 0


def test_raw_error_magnitudes_match_the_thesis(sim_dir: Path) -> None:
    """Raw vs truth, pooled over the logs: legs 25-50 N and 1.5-6 Nm, foot-pair sums 50-100 N."""
    summary = json.loads((sim_dir / "summary.json").read_text())
    logs = summary["logs"]

    def pooled(table: str, name: str, part: str) -> float:
        return float(np.sqrt(np.mean([entry[table][name][part] ** 2 for entry in logs])))

    for leg in ("l_leg_ft", "r_leg_ft"):
        assert 25.0 <= pooled("raw_rmse", leg, "force") <= 50.0, leg
        assert 1.5 <= pooled("raw_rmse", leg, "torque") <= 6.0, leg
    for pair in ("l_foot", "r_foot"):
        assert 50.0 <= pooled("pair_raw_rmse", pair, "force") <= 100.0, pair
    # the oracle calibration leaves only noise and hysteresis: far below raw
    for sensor in ("l_leg_ft", "r_leg_ft"):
        assert pooled("oracle_rmse", sensor, "force") < 0.2 * pooled("raw_rmse", sensor, "force")


def test_invalid_params_name_the_key(tmp_path: Path) -> None:
    bad = yaml.safe_load(write_params(tmp_path).read_text())
    bad["simulate"]["logs"][1]["foot"] = "tail"
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(bad))
    with pytest.raises(ConfigError, match=r"simulate.logs\[1\].foot must be one of l_foot, r_foot"):
        params = load_params(path)  # the feet come from the URDF: checked when the world is built
        build_world(params, simulate_params(params))
    bad["simulate"]["logs"][1]["foot"] = "l_foot"
    bad["simulate"]["sensors"]["coupling"] = 3
    path.write_text(yaml.safe_dump(bad))
    with pytest.raises(ConfigError, match=r"simulate.sensors.coupling"):
        simulate_params(load_params(path))
