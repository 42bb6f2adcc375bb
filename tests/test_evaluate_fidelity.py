"""evaluate: the fidelity flag, the fallback it causes and how the page explains it; the excitation section.

On the synthetic groups of tests/factories/reports.py (those of the evaluate tests), train's metrics get a
`fidelity` record in which nn7 reads the front sensor's fx at a slope of 0.40 (nn13 is noise-flagged there
already): the recommendation must fall back to the affine map, and the page must say why each preferred
model was passed over and what the fallback costs.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from pipeline.calib.excitation import excitation
from pipeline.evaluation.fidelity import unfaithful
from tests.factories.labelled import FRONT, PAIR, REAR
from tests.factories.reports import build_fixture, evaluate_both

pytestmark = pytest.mark.slow  # trains the groups it evaluates

FAITHFUL = [1.02, 0.98, 1.0, 1.01, 0.99, 1.0]


def test_unfaithful_names_the_worst_axis_and_spares_the_references() -> None:
    fidelity = {
        "raw": {FRONT: {"slopes": [0.1] * 6}},  # never flagged: the factory map is the reference
        "affine": {FRONT: {"slopes": FAITHFUL}},
        "nn7": {FRONT: {"slopes": [0.4, 1, 1, 1, 1, 1]}, REAR: {"slopes": [1, 1, 1, 1, 1.2, 1]}},
    }
    assert unfaithful(fidelity, 0.15) == {"nn7": f"{FRONT} fx slope 0.40"}
    assert unfaithful(fidelity, 0.7) == {}


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    root = tmp_path_factory.mktemp("evaluate_fidelity")
    dirs = build_fixture(root)
    path = dirs["models"] / PAIR / "metrics.json"
    metrics = json.loads(path.read_text())
    slopes = {"nn7": [0.4, 1, 1, 1, 1, 1]}
    metrics["fidelity"] = {
        m: {FRONT: {"slopes": slopes.get(m, FAITHFUL), "imu_kg": None}, REAR: {"slopes": FAITHFUL}}
        for m in ("raw", "affine", "nn7", "nn13")
    }
    t = np.arange(2000) / 100.0
    force = np.stack([20 * np.sin((k + 1) * 0.5 * t) for k in range(3)], axis=1)
    on_relation = np.c_[force, np.cross([0.0, 0.0, 0.1], force)]  # a free limb's labels
    metrics["excitation"] = {FRONT: excitation(FRONT, on_relation, np.r_[[0.6] * 3, [0.03] * 3]).to_dict()}
    path.write_text(json.dumps(metrics))
    results, out = evaluate_both(root, dirs)
    return {"result": results[PAIR], "page": (out / "index.html").read_text(), "out": out}


def test_an_unfaithful_network_is_passed_over(evaluated: dict[str, Any]) -> None:
    r = evaluated["result"]
    assert r.noise.flagged == ["nn13"] and set(r.unfaithful) == {"nn7"}
    assert r.best_on_validation == "nn13" and r.recommended == "affine"
    metrics = json.loads((evaluated["out"] / "metrics" / PAIR / f"{PAIR}.json").read_text())
    assert metrics["deployed"] == "affine"


def test_the_page_says_why_and_what_it_costs(evaluated: dict[str, Any]) -> None:
    page = evaluated["page"]
    assert f"<b>Fidelity flags:</b> {PAIR}/nn7: not deployed" in page and f"<b>{PAIR}/nn7</b> (" in page
    for model, why in (("nn13", "output noise"), ("nn7", f"unfaithful to a push: {FRONT} fx slope 0.40")):
        assert f"<b>{model}</b>, preferred by cross-validation, was passed over: {why}" in page
    assert "Deployed instead: <b>affine</b> (mean fold error" in page
    assert "Fidelity to a push" in page and "per-axis slopes" in page


def test_the_page_warns_of_a_narrow_excitation(evaluated: dict[str, Any]) -> None:
    page = evaluated["page"]
    assert "Excitation of the training labels" in page
    assert f"<b>{FRONT}</b>: 3 of 6 directions barely excited" in page
    assert "known-load experiment" in page
    assert REAR not in evaluated["result"].excitation  # none written for it: no row, no warning


def test_reports_without_fidelity_records_recommend_as_before(tmp_path: Path) -> None:
    assert unfaithful({}, 0.15) == {}
