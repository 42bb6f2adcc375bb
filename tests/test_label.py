"""The label stage: contact detection, guard bands, expected wrenches against truth and iDynTree."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
import yaml

from pipeline.core.config import load_params
from pipeline.core.errors import ConfigError, DataError, RobotModelError
from pipeline.labels.contacts import guard_band, hysteresis
from pipeline.logs import schema as S
from pipeline.physics.cuts import pose_wrench_transforms
from pipeline.stages.label import run
from tests.factories.params import repo_params
from tests.relabel import relabel_with_idyntree

pytestmark = pytest.mark.slow  # labels simulated logs on both robots

REPO = Path(__file__).resolve().parents[1]
LOGS = [
    {"type": "pole", "duration_s": 6, "role": "train"},
    {"type": "balancing", "duration_s": 6, "role": "train", "foot": "l_foot"},
    {"type": "half_foot", "duration_s": 6, "role": "test", "foot": "r_foot", "part": "rear"},
    {"type": "walking", "duration_s": 30, "role": "test"},
]


def write_params(tmp: Path, name: str, **simulate: object) -> Path:
    data = repo_params()
    data["simulate"].update({"logs": copy.deepcopy(LOGS), "workers": 1, "plots": False, **simulate})
    path = tmp / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def pipeline_through_label(tmp: Path, params_path: Path) -> Path:
    from pipeline.stages import ingest, simulate, smooth

    params = load_params(params_path)
    simulate.run(params, tmp / "sim", progress=False)
    ingest.run(params, tmp / "sim", tmp / "ingested", progress=False)
    smooth.run(params, tmp / "ingested", tmp / "smoothed", progress=False)
    run(params, tmp / "smoothed", tmp / "labelled", tmp / "ingested", progress=False)
    return tmp


@pytest.fixture(scope="module")
def default_run(tmp_path_factory: pytest.TempPathFactory, mlflow_store: None) -> Path:
    tmp = tmp_path_factory.mktemp("default")
    return pipeline_through_label(tmp, write_params(tmp, "default"))


@pytest.fixture(scope="module")
def ideal_run(tmp_path_factory: pytest.TempPathFactory, mlflow_store: None) -> Path:
    """No model error, no sensor or encoder noise, no timing jitter: labels must equal truth."""
    tmp = tmp_path_factory.mktemp("ideal")
    data = yaml.safe_load(write_params(tmp, "x").read_text())
    sim = data["simulate"]
    sim.update(
        {"mass_error": 0.0, "com_error_m": 0.0, "encoder_resolution_rad": 0.0, "encoder_noise_rad": 0.0}
    )
    sim["sensors"].update({"noise_force": 0.0, "noise_torque": 0.0})
    sim["timing"].update({"jitter_s": 0.0, "drop_rate": 0.0, "duplicate_rate": 0.0, "ft_offset_s": 0.0})
    data["smooth"].update({"window": 7, "polyorder": 6, "choices": []})  # noise-free: a short, high-order fit
    path = tmp / "ideal.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return pipeline_through_label(tmp, path)


def labelled(run_dir: Path, log: str) -> tuple[pd.DataFrame, pd.DataFrame]:
    table = pd.read_parquet(run_dir / "labelled" / f"{log}.parquet")
    truth = pd.read_parquet(run_dir / "ingested" / f"{log}.truth.parquet").set_index(S.STAMP)
    return table, truth.reindex(table[S.STAMP].to_numpy())


def test_hysteresis_and_guard_band() -> None:
    force = np.array([0, 5, 12, 8, 3, 1, 9, 11, np.nan, 2])
    np.testing.assert_array_equal(hysteresis(force, on=10, off=2), [0, 0, 1, 1, 1, 0, 0, 1, 1, 1])
    t = np.arange(10) * 0.01
    changed = np.zeros(10, dtype=bool)
    changed[4] = True  # change halfway between t = 0.03 and 0.04
    np.testing.assert_array_equal(np.flatnonzero(guard_band(t, changed, 0.01)), [3, 4])
    np.testing.assert_array_equal(np.flatnonzero(guard_band(t, changed, 0.016)), [2, 3, 4, 5])


def test_walking_contacts_detected(default_run: Path) -> None:
    """>= 99% agreement with the true contact set outside the guard bands, guard bands < 5% of samples."""
    table, truth = labelled(default_run, "03_walking_test")
    outside = ~table[S.GUARD].to_numpy()
    agree = table[S.CONTACTS].to_numpy()[outside] == truth[S.CONTACTS].fillna("").to_numpy()[outside]
    assert agree.mean() >= 0.99
    assert table[S.GUARD].mean() < 0.05
    assert table[S.CONTACTS].nunique() == 3  # left, right, both
    # every switch is 0 inside guard bands
    for col in [c for c in table.columns if c.startswith(S.SWITCH + ".")]:
        assert not table.loc[table[S.GUARD], col].any()


def cut_sets(path: Path) -> dict[str, dict]:
    """The cut sets with columns of their own, from a labelled table's ftcal.label metadata."""
    meta = S.read_metadata(pq.read_schema(path), S.META_LABEL)
    return {name: c for name, c in meta["cut_sets"].items() if c["label"] == name}


def map_sum(table: pd.DataFrame, cut: dict, wrenches: dict[str, np.ndarray]) -> np.ndarray:
    """A cut set's signed sum of (N, 6) sensor wrenches, mapped as the metadata says (what training does)."""
    total = np.zeros((len(table), 6))
    for s in cut["sensors"]:
        if s in cut["X"]:
            term = wrenches[s] @ np.array(cut["X"][s]).reshape(6, 6).T
        else:
            xs = pose_wrench_transforms(table[cut["pose_columns"][s]].to_numpy())
            term = np.einsum("nij,nj->ni", xs, wrenches[s])
        total += cut["signs"][s] * term
    return total


def test_walking_cut_sets_exact_in_double_support(default_run: Path) -> None:
    """Outside guard bands, > 95% of walking samples have an exact leg-pair and four-foot sum label, double
    support included, though neither leg sensor alone is exact there."""
    path = default_run / "labelled" / "03_walking_test.parquet"
    table = pd.read_parquet(path)
    cuts = cut_sets(path)
    legs = S.cut_set_name(["l_leg_ft", "r_leg_ft"])
    feet = next(n for n, c in cuts.items() if set(c["sensors"]) == set(FEET))
    outside = ~table[S.GUARD].to_numpy()
    double = outside & (table[S.CONTACTS].str.count(",") == 3).to_numpy()
    assert double.mean() > 0.2
    for name in (legs, feet):
        on = table[S.cut_switch_col(name)].to_numpy() == 1
        assert on[outside].mean() > 0.95 and on[double].mean() > 0.95, name
        nan = table[S.cut_sum_cols(name)].isna().all(axis=1).to_numpy()
        assert (nan == ~on).all()
    assert (table.loc[double, S.switch_col("l_leg_ft")] == 0).all()
    for cut in cuts.values():  # every pose column the metadata names is in the table
        for cols in cut["pose_columns"].values():
            assert set(cols) <= set(table.columns)


FEET = ("l_foot_front_ft", "l_foot_rear_ft", "r_foot_front_ft", "r_foot_rear_ft")


def test_declared_contacts_and_switches(default_run: Path) -> None:
    table, _ = labelled(default_run, "02_half_foot_r_foot_rear_test")
    assert set(table[S.CONTACTS]) == {"r_foot_rear"} and set(table[S.FIXED_LINK]) == {"r_sole"}
    ok = table[S.switch_col("r_leg_ft")] == 1
    assert ok.mean() >= 1 - 61 / len(ok)  # all but the smoothing margins (half the widest window each end)
    for part in ("r_foot_front_ft", "r_foot_rear_ft", "r_foot"):
        assert (table[S.switch_col(part)] == table[S.switch_col("r_leg_ft")]).all()
    table, _ = labelled(default_run, "01_balancing_l_foot_train")
    assert not table[S.switch_col("l_foot_front_ft")].any() and table[S.switch_col("l_foot")].mean() > 0.85
    # NaN exactly where the switch is 0
    for name in ("l_foot_front_ft", "l_foot", "l_leg_ft"):
        nan = table[S.wrench_cols(S.EXPECTED, name)].isna().all(axis=1)
        assert (nan == (table[S.switch_col(name)] == 0)).all()


def test_ideal_labels_equal_truth(ideal_run: Path) -> None:
    """No model error, no noise: wherever a switch is 1, expected == true wrench, every sensor, pair and
    cut set (true wrenches mapped as the metadata says; what remains is the smoothing of exact positions)."""
    from pipeline.physics.robot import load_robot

    robot = load_robot("iCubGenova09")
    pairs = [
        robot.foot_pair("l_foot", "l_foot_front_ft", "l_foot_rear_ft", "l_sole"),
        robot.foot_pair("r_foot", "r_foot_front_ft", "r_foot_rear_ft", "r_sole"),
    ]
    worst, compared = {}, 0
    for log in (
        "00_pole_train",
        "01_balancing_l_foot_train",
        "02_half_foot_r_foot_rear_test",
        "03_walking_test",
    ):
        table, truth = labelled(ideal_run, log)
        true = {s: truth[S.wrench_cols(S.TRUE, s)].to_numpy() for s in robot.sensors}
        for p in pairs:
            true[p.name] = true[p.front] @ p.sole_X_front.T + true[p.rear] @ p.sole_X_rear.T
        cut_sets_of = cut_sets(ideal_run / "labelled" / f"{log}.parquet")
        for name, cut in cut_sets_of.items():
            true[name] = map_sum(table, cut, true)
        for name, value in true.items():
            on = (table[S.switch_col(name)] == 1).to_numpy() & np.isfinite(value).all(axis=1)
            err = table[S.wrench_cols(S.EXPECTED, name)].to_numpy()[on] - value[on]
            scale = len(cut_sets_of.get(name, {}).get("sensors", [0]))  # a sum adds its members' errors
            worst[(log, name)] = float(np.abs(err).max()) / scale if on.any() else 0.0
            compared += int(on.sum())
    assert compared > 10_000
    assert max(worst.values()) < IDEAL_TOLERANCE, {k: v for k, v in worst.items() if v >= IDEAL_TOLERANCE}


IDEAL_TOLERANCE = 1e-3  # N / Nm, per sensor (a cut-set sum may be off by its sensor count times this)


@pytest.mark.parametrize(
    "log", ["00_pole_train", "01_balancing_l_foot_train", "02_half_foot_r_foot_rear_test", "03_walking_test"]
)
def test_relabel_with_idyntree(default_run: Path, log: str) -> None:
    """500 labelled samples of each experiment type, recomputed with iDynTree from the same kinematics."""
    table, smoothed = (default_run / k / f"{log}.parquet" for k in ("labelled", "smoothed"))
    assert relabel_with_idyntree(table, smoothed, "iCubGenova09", samples=500) < 1e-6


def test_bad_inputs(tmp_path: Path, default_run: Path, mlflow_store: None) -> None:
    params = load_params(write_params(tmp_path, "p"))
    with pytest.raises(DataError, match="input directory not found"):
        run(params, tmp_path / "nope", tmp_path / "out")
    data = yaml.safe_load(write_params(tmp_path, "p").read_text())
    data["label"]["contact_on"] = 0.01
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match="label.contact_off and label.contact_on must satisfy"):
        run(load_params(path), default_run / "smoothed", tmp_path / "out")
    data["label"].update(contact_on=0.04, cut_max_sensors=0)
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"label.cut_max_sensors must be an integer in \[1, 6\], got 0"):
        run(load_params(path), default_run / "smoothed", tmp_path / "out")
    data = yaml.safe_load(write_params(tmp_path, "p").read_text())
    data["robot"]["foot_pairs"] = {
        "l_foot": {"front": "l_toe_ft", "rear": "l_foot_rear_ft", "sole": "l_sole"},
        "r_foot": {"front": "r_foot_front_ft", "rear": "r_foot_rear_ft", "sole": "r_sole"},
    }
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(RobotModelError, match="no force_torque sensor named 'l_toe_ft'"):
        run(load_params(path), default_run / "smoothed", tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_label_stage_on_ergocub(tmp_path: Path, mlflow_store: None, monkeypatch: pytest.MonkeyPatch) -> None:
    """Nothing iCub-specific: a smoothed table of ergoCub in declared double support (random kinematics)
    labels every cut set; the leg-pair and four-foot sums match iDynTree mapped to their frames. The
    table names its URDF relative to the working directory, so clones in other places label alike."""
    from pipeline.physics.robot import load_robot
    from tests.conftest import robot_source
    from tests.factories.oracles import oracle
    from tests.factories.physics import DOUBLE, wrench_X
    from tests.idyntree_ref import random_in_limits

    robot = load_robot(robot_source("ergoCubSN001"))
    n, joints, sensors = 40, robot.joint_names, list(robot.sensors)
    q, dq, ddq = random_in_limits(robot.urdf_path, joints, n, np.random.default_rng(5))
    cols: dict[str, np.ndarray] = {S.STAMP: np.arange(n) * 10_000_000, S.TIME: np.arange(n) * 0.01}
    for c in S.ingested_columns(joints, sensors)[2:] + S.smoothed_extra_columns(joints):
        cols[c] = np.ones(n, dtype=bool) if c.startswith(S.OK + ".") else np.zeros(n)
    for quantity, values in ((S.QS, q), (S.DQS, dq), (S.DDQS, ddq), (S.Q, q)):
        for k, c in enumerate(S.joint_cols(quantity, joints)):
            cols[c] = values[:, k]
    experiment = {"contacts": ",".join(DOUBLE), "fixed_link": "l_sole"}
    schema = S.arrow_schema(list(cols), S.KIND_SMOOTHED, {S.META_EXPERIMENT: experiment})
    (tmp_path / "smoothed").mkdir()
    pq.write_table(pa_table(cols, schema), tmp_path / "smoothed" / "ergo.parquet")
    data = repo_params()
    data["robot"]["urdf"] = str(robot.urdf_path)
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(data))
    params = load_params(tmp_path / "p.yaml")
    monkeypatch.chdir(Path(robot.urdf_path).resolve().parent.parent)
    run(params, tmp_path / "smoothed", tmp_path / "labelled")
    path = tmp_path / "labelled" / "ergo.parquet"
    table, cuts = pd.read_parquet(path), cut_sets(path)
    urdf = Path(robot.urdf_path).resolve()
    assert S.read_metadata(pq.read_schema(path), S.META_LABEL)["urdf"] == f"{urdf.parent.name}/{urdf.name}"
    ref = oracle(robot).expected(q, dq, ddq, DOUBLE, "l_sole", np.array([0.0, 0.0, -9.80665]))
    assert len(cuts) == 6
    for name, cut in cuts.items():
        assert (table[S.cut_switch_col(name)] == 1).all(), name
        theirs = np.zeros((n, 6))
        for s in cut["sensors"]:
            xs = np.array([wrench_X(h) for h in oracle(robot).sensor_poses(q, cut["frame"], s)])
            theirs += cut["signs"][s] * np.einsum("nij,nj->ni", xs, ref[s])
        np.testing.assert_allclose(table[S.cut_sum_cols(name)].to_numpy(), theirs, rtol=0, atol=1e-6)
        np.testing.assert_allclose(map_sum(table, cut, ref), theirs, rtol=0, atol=1e-6)


def pa_table(cols: dict[str, np.ndarray], schema):  # noqa: ANN201
    import pyarrow as pa

    return pa.Table.from_pydict(
        {k: pa.array(v, type=schema.field(k).type) for k, v in cols.items()}, schema=schema
    )


def test_declared_contact_the_urdf_lacks_names_the_log(tmp_path: Path, default_run: Path) -> None:
    """A log whose experiment metadata declares a link the URDF does not have: the error names the log."""
    import json

    import pyarrow.parquet as pq

    src = default_run / "smoothed" / "00_pole_train.parquet"
    table = pq.read_table(src)
    meta = dict(table.schema.metadata)
    experiment = json.loads(meta[S.META_EXPERIMENT])
    experiment["contacts"] = "l_toe"
    meta[S.META_EXPERIMENT] = json.dumps(experiment).encode()
    bad = tmp_path / "smoothed" / "00_pole_train.parquet"
    bad.parent.mkdir()
    pq.write_table(table.replace_schema_metadata(meta), bad)
    params = load_params(write_params(tmp_path, "p"))
    with pytest.raises(DataError, match=r"00_pole_train\.parquet: its experiment metadata .*l_toe"):
        run(params, bad.parent, tmp_path / "out")
    assert not (tmp_path / "out").exists()
