"""The identification's pieces with analytic references: the held inertia of `with_change`, `to_inertial`,
the URDF writer's refusals and the params' checks (the whole identification runs in tests/test_e2e.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from pipeline.core.errors import ConfigError, RobotModelError
from pipeline.labels.identify import part_table, to_inertial
from pipeline.labels.imu_params import IdentifyParams
from pipeline.labels.inertials import FREE, Posterior, link_basis, with_change
from pipeline.physics.regressor import link_params
from pipeline.physics.robot import RobotModel
from pipeline.physics.urdf_write import write_inertials
from tests.factories.params import repo_params

pytestmark = pytest.mark.slow  # labels and identifies simulated logs

GOOD = {
    "step": 20,
    "weight": 0.002,
    "shrink": 0.5,
    "reject_p": 0.001,
    "play_widths_n": [10.0],
    "play_widths_nm": [0.5],
}


def _links(n: int = 3) -> np.ndarray:
    pin.seed(5)
    return np.concatenate([pin.Inertia.Random().toDynamicParameters() for _ in range(n)])


def test_with_change_keeps_the_inertia_about_the_centre_of_mass() -> None:
    pi = _links()
    change = np.random.default_rng(0).normal(size=12) * 0.05
    new = with_change(pi, change)
    for k in range(3):
        a, b = to_inertial(pi[10 * k : 10 * k + 10]), to_inertial(new[10 * k : 10 * k + 10])
        np.testing.assert_allclose(b.inertia, a.inertia, atol=1e-12)
        assert b.mass == pytest.approx(a.mass + change[4 * k])
        np.testing.assert_allclose(b.mass * b.com, a.mass * a.com + change[4 * k + 1 : 4 * k + 4], atol=1e-12)


def test_link_basis_is_the_first_order_of_with_change() -> None:
    pi, step = _links(), np.random.default_rng(1).normal(size=12)
    for eps in (1e-3, 1e-4):
        err = np.abs(with_change(pi, eps * step) - (pi + link_basis(pi) @ (eps * step))).max()
        assert err < 50 * eps**2  # second order: halving eps quarters it


def test_to_inertial_inverts_pinocchios_parameters() -> None:
    inertia = pin.Inertia.Random()
    back = to_inertial(inertia.toDynamicParameters())
    assert back.mass == pytest.approx(inertia.mass)
    np.testing.assert_allclose(back.com, inertia.lever, atol=1e-14)
    np.testing.assert_allclose(back.inertia, inertia.inertia, atol=1e-14)


def test_the_urdf_writer_refuses_an_unknown_link_and_bad_xml(tmp_path: Path) -> None:
    src = tmp_path / "r.urdf"
    src.write_text('<robot name="r"><link name="a"><inertial><mass value="1"/></inertial></link></robot>')
    with pytest.raises(RobotModelError, match="no link 'b'"):
        write_inertials(src, tmp_path / "o.urdf", {"b": to_inertial(_links(1))})
    assert not (tmp_path / "o.urdf").exists()
    (tmp_path / "bad.urdf").write_text("<robot>")
    with pytest.raises(RobotModelError, match="bad.urdf"):
        write_inertials(tmp_path / "bad.urdf", tmp_path / "o.urdf", {})


def test_a_part_is_re_estimated_where_its_change_rejects_the_urdf(icub: RobotModel) -> None:
    """The chi-square statistic of a part's change (independent: the sum of squared z-scores of a diagonal
    posterior) against scipy's quantile: a part just past it is re-estimated, one just short is not; a part
    whose mass sd is shrunk is identified either way; the freed parts are the union."""
    from scipy.stats import chi2

    links = [lk for lk, i in icub.links.items() if i is not None and i.mass > 0]
    pi = link_params(icub, links)
    n_p = FREE * len(links)
    sd = np.full(n_p, 0.01)
    parts = part_table(
        icub, links, pi, Posterior(np.zeros(n_p), np.diag(sd**2), np.zeros((2, n_p)), sd), None, 0.5, 1e-3
    )
    arm = next(p for p in parts if p.name == "r_upper_arm")
    own = [FREE * links.index(lk) + j for lk in arm.links for j in range(FREE)]
    edge = chi2.isf(1e-3, len(own))
    for factor, rejected in ((1.01, True), (0.99, False)):
        delta = np.zeros(n_p)
        delta[own] = sd[own] * np.sqrt(factor * edge / len(own))  # sum of squared z-scores: factor x edge
        post = Posterior(delta, np.diag(sd**2), np.zeros((2, n_p)), 1.5 * sd)
        got = {p.name: p for p in part_table(icub, links, pi, post, None, 0.5, 1e-3)}
        assert got["r_upper_arm"].chi2 == pytest.approx(factor * edge, rel=1e-9)
        assert got["r_upper_arm"].dof == len(own)
        assert got["r_upper_arm"].rejected is rejected and got["r_upper_arm"].freed is rejected
        assert not got["r_upper_arm"].identified  # its mass sd: 1 / 1.5 of the prior's, above 0.5
        assert all(p.chi2 == 0 and not p.rejected for n, p in got.items() if n != "r_upper_arm")
        state = got["r_upper_arm"].state
        assert state.startswith("re-estimated") if rejected else state == "not identified (URDF's)"
    shrunk = part_table(
        icub,
        links,
        pi,
        Posterior(np.zeros(n_p), np.diag(sd**2), np.zeros((2, n_p)), 10 * sd),
        None,
        0.5,
        1e-3,
    )
    assert all(p.identified and p.freed and not p.rejected for p in shrunk)


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("step", 0, "step must be a positive integer"),
        ("weight", -1.0, "weight must be a positive number"),
        ("shrink", 1.0, "shrink must be below 1"),
        ("reject_p", 0.0, "reject_p must be a positive number"),
        ("reject_p", 1.0, "reject_p must be below 1"),
        ("play_widths_nm", [0.5, 1.0], "as many widths"),
        ("play_widths_n", [-1.0], "list of distinct positive numbers"),
        ("play_widths_n", [10.0, 10.0], "list of distinct positive numbers"),
    ],
)
def test_identify_params_name_the_bad_key(key: str, value: object, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        IdentifyParams.from_mapping(GOOD | {key: value})
    with pytest.raises(ConfigError, match="unknown key label.identify.x"):
        IdentifyParams.from_mapping(GOOD | {"x": 1})


@pytest.fixture(scope="module")
def identified_run(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Three short training logs (pole, known loads, balancing) of a robot whose URDF is 10 % / 2 cm off,
    labelled, identified with label.inertials: identified (a weight and a shrink threshold of a few
    logs' worth)."""
    import shutil

    import yaml

    from pipeline.core.config import load_params
    from pipeline.stages import identify, ingest, label, simulate, smooth

    tmp = tmp_path_factory.mktemp("identified")
    data = repo_params()
    data["simulate"].update(workers=1, plots=False, mass_error=0.10, com_error_m=0.02)
    loads = [{"link": "hands", "mass_kg": 2.0}, {"link": "feet", "mass_kg": 6.0}]
    data["simulate"]["logs"] = [
        {"type": "pole", "duration_s": 10, "role": "train"},
        {"type": "known_load", "duration_s": 10, "role": "train", "loads": loads},
        {"type": "balancing", "duration_s": 10, "role": "train", "foot": "l_foot"},
    ]
    data["label"]["inertials"] = "identified"
    data["label"]["identify"].update(weight=0.02, shrink=0.5)  # 30 s of logs: their own weight and threshold
    (tmp / "params.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    patch = pytest.MonkeyPatch()
    patch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp / 'mlflow.db'}")
    try:
        params = load_params(tmp / "params.yaml")
        d = {k: tmp / k for k in ("sim", "ingested", "smoothed", "labelled", "identified")}
        simulate.run(params, d["sim"], progress=False)
        ingest.run(params, d["sim"], d["ingested"], progress=False)
        smooth.run(params, d["ingested"], d["smoothed"], progress=False)
        label.run(params, d["smoothed"], d["labelled"], truth_dir=d["ingested"], progress=False)
        shutil.copytree(d["labelled"], tmp / "urdf_labels")
        res = identify.run(params, d["smoothed"], d["labelled"], d["identified"], d["ingested"])
    finally:
        patch.undo()
    return {"dirs": d, "res": res, "params": params, "tmp": tmp}


def test_identified_labels_are_the_tables_relabelled_with_the_identified_model(identified_run: dict) -> None:
    """The model is accepted (the lower legs identified), the labels are made again with model.urdf, and
    the per-sensor errors against truth the step reports (first order, on every step-th exact sample) are
    those of the relabelled tables themselves."""
    import pandas as pd

    from pipeline.logs import schema as S

    d, res, step = identified_run["dirs"], identified_run["res"], identified_run["params"]
    assert res.status == "identified" and {p.name for p in res.parts if p.identified} >= {"r_lower_leg"}
    assert (d["identified"] / "labels.urdf").read_bytes() == (d["identified"] / "model.urdf").read_bytes()
    every = step.raw["label"]["identify"]["step"]
    for sensor in ("r_leg_ft", "l_arm_ft"):
        errors, before_after = [], []
        for table in sorted(d["labelled"].glob("*.parquet")):
            lab, old = (
                pd.read_parquet(table),
                pd.read_parquet(identified_run["tmp"] / "urdf_labels" / table.name),
            )
            sm = pd.read_parquet(d["smoothed"] / table.name)
            truth = pd.read_parquet(d["ingested"] / f"{table.stem}.truth.parquet").set_index(S.STAMP)
            truth = truth.reindex(lab[S.STAMP].to_numpy())
            names = S.sensors_of(lab.columns)
            sw = np.column_stack([lab[S.switch_col(s)].to_numpy() for s in names]).astype(bool)
            q, ddq = (sm[[c for c in sm.columns if c.startswith(f"{k}.")]].to_numpy() for k in (S.QS, S.DDQS))
            rows = np.flatnonzero(sw.any(1) & np.isfinite(q).all(1) & np.isfinite(ddq).all(1))[::every]
            rows = rows[lab[S.switch_col(sensor)].to_numpy()[rows].astype(bool)]
            cols = S.wrench_cols(S.EXPECTED, sensor)
            errors.append(lab[cols].to_numpy()[rows] - truth[S.wrench_cols(S.TRUE, sensor)].to_numpy()[rows])
            before_after.append(np.nanmax(np.abs(lab[cols].to_numpy() - old[cols].to_numpy())))
        rmse = float(np.sqrt(np.mean(np.concatenate(errors) ** 2)))
        assert rmse == pytest.approx(res.sensors[sensor]["error_identified"], rel=0.02), sensor
        changed = res.sensors[sensor]["label_change"] > 0
        assert (max(before_after) > 1e-3) == changed, sensor  # the arms are not identified: unchanged
