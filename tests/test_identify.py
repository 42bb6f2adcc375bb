"""The identification's pieces with analytic references: the held inertia of `with_change`, `to_inertial`,
the URDF writer's refusals and the params' checks (the whole identification runs in tests/test_e2e.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from pipeline.core.errors import ConfigError, RobotModelError
from pipeline.labels.identify import to_inertial
from pipeline.labels.imu_params import IdentifyParams
from pipeline.labels.inertials import link_basis, with_change
from pipeline.physics.urdf_write import write_inertials

GOOD = {"step": 20, "weight": 0.002, "shrink": 0.5, "play_widths_n": [10.0], "play_widths_nm": [0.5]}


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


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("step", 0, "step must be a positive integer"),
        ("weight", -1.0, "weight must be a positive number"),
        ("shrink", 1.0, "shrink must be below 1"),
        ("play_widths_nm", [0.5, 1.0], "as many widths"),
        ("play_widths_n", [-1.0], "list of positive numbers"),
    ],
)
def test_identify_params_name_the_bad_key(key: str, value: object, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        IdentifyParams.from_mapping(GOOD | {key: value})
    with pytest.raises(ConfigError, match="unknown key label.identify.x"):
        IdentifyParams.from_mapping(GOOD | {"x": 1})
