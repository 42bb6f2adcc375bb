"""The deploy section: errors name the dotted key; a deployment day keeps training's distortions."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from pipeline.core.config import load_params
from pipeline.core.errors import ConfigError
from pipeline.deploy.params import deploy_params, deployment_simulation
from pipeline.sim.params import simulate_params
from pipeline.sim.world import build_world


def _with(params, **deploy):
    raw = copy.deepcopy(params.raw)
    raw["deploy"].update(deploy)
    return type(params)(seed=params.seed, robot=params.robot, topics=params.topics, raw=raw)


@pytest.mark.parametrize(
    "change,message",
    [
        ({"seed": -1}, "deploy.seed"),
        (
            {"later": {"temperature_c": 5.0, "offset_force": -1.0, "offset_torque": 0.1}},
            "deploy.later.offset_force",
        ),
        (
            {"push": {"force_n": 10.0, "duration_s": 9.0, "period_s": 5.0, "direction": [1, 0, 0]}},
            "deploy.push",
        ),
        ({"logs": [{"type": "walking", "duration_s": 20}]}, "standing log"),
        ({"colour": 1}, "unknown key deploy.colour"),
    ],
)
def test_bad_deploy_params_name_the_key(change, message):
    with pytest.raises(ConfigError, match=message):
        deploy_params(_with(load_params(), **change))


def test_deployment_world_keeps_training_distortions_with_drifted_offsets():
    params = load_params()
    train = build_world(params, simulate_params(params))
    sim = deployment_simulation(params, "drifted")
    day = build_world(params, sim)
    assert day.params.seed == sim.shift.seed and day.base_params is params
    for s, d in train.distortions.items():
        np.testing.assert_array_equal(day.distortions[s].coupling, d.coupling)
        shift = day.distortions[s].offset - d.offset
        assert np.all(np.abs(shift[:3]) <= sim.shift.offset_force) and np.any(shift != 0)
    assert sim.thermal.baseline == simulate_params(params).thermal.baseline + 15.0
