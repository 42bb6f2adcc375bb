"""Shared fixtures: the robots every physics test runs on, throwaway MLflow stores, iCub's short logs and
tiny trained models."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.physics.robot import RobotModel, load_robot
from tests.factories.params import repo_params
from tests.pgserver import mlflow_server, pg_url  # noqa: F401 (session fixtures)

REPO = Path(__file__).resolve().parents[1]
# ergoCub's URDF (BSD-3, its LICENSE beside it), vendored so that its tests run on every clone and in CI
ERGOCUB_URDF = REPO / "tests" / "robots" / "ergoCubSN001" / "model.urdf"
ROBOTS = ["iCubGenova09", "ergoCubSN001"]
GRAVITY = 9.80665
FOOT_PAIRS = {
    "l_foot": ("l_foot_front_ft", "l_foot_rear_ft", "l_sole"),
    "r_foot": ("r_foot_front_ft", "r_foot_rear_ft", "r_sole"),
}


def robot_source(name: str) -> str:
    """URDF path or icub-models name of a test robot."""
    return str(ERGOCUB_URDF) if name == "ergoCubSN001" else name


_CACHE: dict[str, RobotModel] = {}


@pytest.fixture(scope="module")
def mlflow_store(tmp_path_factory: pytest.TempPathFactory):
    """A throwaway MLflow sqlite store for one test module's stage runs (monkeypatch is per function)."""
    patch = pytest.MonkeyPatch()
    patch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path_factory.mktemp('mlflow')}/mlflow.db")
    yield
    patch.undo()


@pytest.fixture(params=ROBOTS, scope="session")
def robot(request: pytest.FixtureRequest) -> RobotModel:
    """Each test robot, loaded once per session."""
    source = robot_source(request.param)
    if source not in _CACHE:
        _CACHE[source] = load_robot(source)
    return _CACHE[source]


@pytest.fixture(scope="session")
def icub() -> RobotModel:
    return load_robot("iCubGenova09")


def foot_pairs(robot: RobotModel) -> list:
    return [robot.foot_pair(name, *sensors) for name, sensors in FOOT_PAIRS.items()]


@pytest.fixture(scope="module")
def mlflow_db(tmp_path_factory: pytest.TempPathFactory) -> str:
    """The URI of a throwaway MLflow sqlite store for one test module's ingest runs through the CLI."""
    return f"sqlite:///{tmp_path_factory.mktemp('mlflow') / 'mlflow.db'}"


@pytest.fixture(scope="module")
def icub_logs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[str], list[str]]:
    """Two short good logs of iCub (its URDF's joints and FT sensors) and one truncated one."""
    from pipeline.core.config import load_params
    from tests.factories.logs import write_log

    robot = load_robot("iCubGenova09")
    joints, sensors = robot.joint_names, list(robot.sensors)
    src = tmp_path_factory.mktemp("icub_src")
    params = load_params(REPO / "params.yaml")
    for name in ("a", "b"):
        write_log(src / "sub" / f"{name}.mcap", joints, sensors, topics=params.topics, duration=1.0)
    good = (src / "sub" / "a.mcap").read_bytes()
    (src / "sub" / "c_truncated.mcap").write_bytes(good[: len(good) // 2])
    return src, joints, sensors


@pytest.fixture(scope="session")
def trained_models(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Tiny trained models of r_leg_ft and the r_foot pair (every family: raw, affine, poly1-2, nn7, nn13)
    on synthetic labelled tables, written by the real train stage into a throwaway MLflow store.

    Returns {"root", "labelled", "models", "params" (a params.yaml path), "mlflow_uri"}. Shared by the
    export and calibrate tests (training is the slow part).
    """
    import yaml

    from pipeline.core.config import load_params
    from pipeline.stages import train as T
    from tests.factories.labelled import LEG, PAIR, write_labelled_logs
    from tests.factories.params import write_params

    root = tmp_path_factory.mktemp("trained")
    labelled = write_labelled_logs(root / "labelled", n=400)
    params_path = write_params(root, n_trials=1, epochs=2)
    data = yaml.safe_load(params_path.read_text())
    data["export"] = repo_params()["export"]
    params_path.write_text(yaml.safe_dump(data, sort_keys=False))
    uri = f"sqlite:///{root / 'mlflow.db'}"
    patch = pytest.MonkeyPatch()
    patch.setenv("MLFLOW_TRACKING_URI", uri)
    try:
        params = load_params(params_path)
        for group in (LEG, PAIR):
            T.train_group(
                params, group, labelled, root / "models" / group, root / "studies" / group, progress=False
            )
    finally:
        patch.undo()
    return {
        "root": root,
        "labelled": labelled,
        "models": root / "models",
        "params": params_path,
        "mlflow_uri": uri,
    }
