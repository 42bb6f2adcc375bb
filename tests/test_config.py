"""params.yaml loading: the real file loads; every bad input is a ConfigError naming the file and key."""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import pytest
import yaml

from pipeline.core.config import (
    FootPairParams,
    Params,
    RobotParams,
    load_params,
    repo_root,
    resolve_urdf,
)
from pipeline.core.errors import ConfigError
from tests.factories.params import repo_params

ROOT = Path(__file__).resolve().parent.parent
REPO_PARAMS = ROOT / "params.yaml"


@pytest.fixture(scope="module")
def real_dict() -> dict[str, Any]:
    """params.yaml with the foot pairs written out (as a user may: by default they come from the URDF)."""
    data = repo_params()
    data["robot"]["foot_pairs"] = {
        side: {"front": f"{side}_front_ft", "rear": f"{side}_rear_ft", "sole": f"{side[0]}_sole"}
        for side in ("l_foot", "r_foot")
    }
    return data


def write(path: Path, data: Any) -> Path:
    path.write_text(data if isinstance(data, str) else yaml.safe_dump(data, sort_keys=False))
    return path


def set_key(data: dict[str, Any], dotted: str, value: Any) -> dict[str, Any]:
    """Copy of `data` with the dotted key set (value `DELETE` removes it)."""
    out = copy.deepcopy(data)
    *parents, last = dotted.split(".")
    node = out
    for key in parents:
        node = node[key]
    if value is DELETE:
        del node[last]
    else:
        node[last] = value
    return out


DELETE = object()


def test_real_params_load() -> None:
    params = load_params()
    assert isinstance(params, Params)
    assert params.seed == 42
    assert params.robot.urdf == "iCubGenova09"
    assert math.isclose(params.robot.gravity, 9.80665)
    assert params.robot.foot_pairs is None  # derived from the URDF (tests/test_feet.py)
    assert params.raw["robot"]["urdf"] == "iCubGenova09"
    assert load_params(ROOT / "params.yaml") == params


def test_params_are_frozen() -> None:
    params = load_params()
    with pytest.raises(AttributeError):
        params.robot.gravity = 1.0  # type: ignore[misc]


def test_repo_root_from_a_subdirectory(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(ROOT / "tests")
    assert repo_root() == ROOT


def test_every_section_is_validated_at_load(tmp_path: Path, real_dict: dict[str, Any]) -> None:
    """A typo in any stage's section (or a misspelt section) is reported when params.yaml is loaded."""
    cases = [
        ({**real_dict, "smooth": {"window": 31, "polyorder": 1}}, "smooth.polyorder must be an integer"),
        ({**real_dict, "evaluate": {**real_dict["evaluate"], "zoom": 1}}, "unknown key evaluate.zoom"),
        ({**real_dict, "evalute": {}}, "unknown key evalute"),
    ]
    for data, message in cases:
        with pytest.raises(ConfigError, match=rf"params.yaml: {message}"):
            load_params(write(tmp_path / "params.yaml", data))


@pytest.mark.parametrize("key", ["seed", "robot.gravity", "smooth.max_gap_s", "train.defaults.lr"])
def test_a_key_left_out_takes_its_default(tmp_path: Path, real_dict: dict[str, Any], key: str) -> None:
    from pipeline.core.defaults import read_defaults

    loaded = load_params(write(tmp_path / "params.yaml", set_key(real_dict, key, DELETE))).raw
    default: Any = read_defaults()
    for part in key.split("."):
        loaded, default = loaded[part], default[part]
    assert loaded == default


@pytest.mark.parametrize(
    ("key", "value", "expected"),
    [
        ("robot.gravity", -1, "robot.gravity must be a positive number, got -1"),
        ("robot.gravity", 0, "robot.gravity must be a positive number, got 0"),
        ("robot.gravity", math.inf, "robot.gravity must be a positive number, got inf"),
        ("robot.gravity", "9.8", "robot.gravity must be a positive number, got '9.8'"),
        ("robot.gravity", True, "robot.gravity must be a positive number, got True"),
        ("robot.urdf", "", "robot.urdf must be a non-empty string"),
        ("robot.urdf", 3, "robot.urdf must be a non-empty string, got 3"),
        ("seed", -1, "seed must be an integer in [0, 2**32), got -1"),
        ("seed", 1.5, "seed must be an integer"),
        ("robot", None, "robot must be a mapping, got None"),
        ("robot.foot_pairs", [], "robot.foot_pairs must be a mapping"),
        ("robot.foot_pairs.l_foot.rear", "l_foot_front_ft", "robot.foot_pairs.l_foot.rear must differ"),
        ("robot.foot_pairs.r_foot.front", "l_foot_front_ft", "sensor 'l_foot_front_ft' is already in"),
        ("robot.foot_pairs.l_foot.sole", None, "robot.foot_pairs.l_foot.sole must be a non-empty string"),
        ("robot.colour", "red", "unknown key robot.colour"),
        ("robot.foot_pairs.l_foot.toe", "x", "unknown key robot.foot_pairs.l_foot.toe"),
        ("robot.foot_pairs.r_foot.sole", DELETE, "missing key robot.foot_pairs.r_foot.sole"),
    ],
)
def test_invalid_value_names_file_and_key(
    tmp_path: Path, real_dict: dict[str, Any], key: str, value: Any, expected: str
) -> None:
    path = write(tmp_path / "bad_params.yaml", set_key(real_dict, key, value))
    with pytest.raises(ConfigError) as info:
        load_params(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ")  # tmp_path is outside the cwd: shown absolute
    assert expected in message
    assert "\n" not in message


def test_yaml_syntax_error_names_line(tmp_path: Path) -> None:
    path = write(tmp_path / "params.yaml", "seed: 42\nrobot:\n  urdf: iCubGenova09\n  gravity: [9.8\n")
    with pytest.raises(ConfigError, match=r"params\.yaml: invalid YAML at line \d+") as info:
        load_params(path)
    assert str(path) in str(info.value)


def test_duplicate_key_is_an_error(tmp_path: Path) -> None:
    text = "seed: 42\nrobot:\n  urdf: a\n  urdf: b\n  gravity: 9.8\n  foot_pairs: {}\n"
    with pytest.raises(ConfigError, match=r"line 4.*duplicate key 'urdf'"):
        load_params(write(tmp_path / "params.yaml", text))


@pytest.mark.parametrize(
    ("text", "expected"),
    [("", "the file is empty"), ("- 1\n- 2\n", "the top level must be a mapping")],
)
def test_empty_or_non_mapping_file(tmp_path: Path, text: str, expected: str) -> None:
    with pytest.raises(ConfigError, match=expected):
        load_params(write(tmp_path / "params.yaml", text))


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.yaml"
    with pytest.raises(ConfigError, match=r"nope\.yaml: file not found"):
        load_params(path)


def test_relative_path_is_shown_as_given(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    write(tmp_path / "p.yaml", "seed: 42\nrobot: {urdf: x, gravity: -1, foot_pairs: {}}\n")
    with pytest.raises(ConfigError) as info:
        load_params("p.yaml")
    assert str(info.value) == "p.yaml: robot.gravity must be a positive number, got -1"


def test_dataclasses_validate_on_construction() -> None:
    with pytest.raises(ConfigError, match="robot.foot_pairs.x.rear must differ"):
        FootPairParams("x", "a", "a", "sole")
    with pytest.raises(ConfigError, match="robot.gravity"):
        RobotParams(urdf="iCubGenova09", gravity=float("nan"))
    pair = FootPairParams("p", "a", "b", "s")
    with pytest.raises(ConfigError, match="robot.foot_pairs.p is defined twice"):
        RobotParams(urdf="iCubGenova09", gravity=9.8, foot_pairs=(pair, pair))
    assert RobotParams(urdf="x", gravity=10).gravity == 10.0


def test_resolve_urdf() -> None:
    root = Path("/repo")
    assert resolve_urdf("iCubGenova09", root) == "iCubGenova09"
    assert resolve_urdf("robots/x/model.urdf", root) == str(root / "robots/x/model.urdf")
    assert resolve_urdf("/abs/model.urdf", root) == "/abs/model.urdf"


def test_topics_section(tmp_path: Path) -> None:
    params = load_params()
    assert params.topics.sensor_topic("ft_wrench", "l_leg_ft") == "/ft/l_leg_ft/wrench"
    from pipeline.core.defaults import DEFAULTS_FILE

    text = DEFAULTS_FILE.read_text().replace("ft_imu: /ft/{sensor}/imu", "ft_imu: /ft/imu")
    with pytest.raises(ConfigError, match=r"topics.ft_imu must contain \{sensor\}"):
        load_params(write(tmp_path / "params.yaml", text))


def test_stage_section_names_the_key(tmp_path: Path) -> None:
    from dataclasses import dataclass

    from pipeline.core.config import stage_section

    @dataclass(frozen=True)
    class Demo:
        rate_hz: float

        def __post_init__(self) -> None:
            if self.rate_hz <= 0:
                raise ConfigError(f"demo.rate_hz must be > 0, got {self.rate_hz}")

    params = load_params(REPO_PARAMS)
    params.raw["demo"] = {"rate_hz": 100}
    assert stage_section(params, "demo", Demo).rate_hz == 100
    for section, message in (
        ({"rate_hz": -1}, "demo.rate_hz must be > 0"),
        ({"rate": 1}, "unknown key demo.rate"),
        (None, "missing section demo"),
    ):
        params.raw.pop("demo", None)
        if section is not None:
            params.raw["demo"] = section
        with pytest.raises(ConfigError, match=rf"params.yaml: {message}"):
            stage_section(params, "demo", Demo)
