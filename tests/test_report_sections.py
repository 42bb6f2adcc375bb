"""Report page parts: contact phases from contact sets and foot cut sets, the cross-validation table from
a hand-made `cv` record, and the summary's one row per headline."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.config import load_params, stage_section
from pipeline.evaluation import phases as P
from pipeline.evaluation.page import summary_table
from pipeline.evaluation.params import EvaluateParams
from pipeline.evaluation.results import GroupReport, NoiseResult, score
from pipeline.evaluation.sections import cv_section

# A toy robot: the left foot's links, the right foot's, and the rest (what each foot pair's cut isolates).
L_FOOT, R_FOOT = {"l_front", "l_rear", "l_sole"}, {"r_front", "r_rear", "r_sole"}
REST = {"root_link", "torso", "l_leg", "r_leg"}
META = {
    "pairs": {"l_foot": {"sole": "l_sole"}, "r_foot": {"sole": "r_sole"}},
    "cut_sets": {
        "lf+lr": {"label": "l_foot", "part": sorted(REST | R_FOOT)},  # the rest of the robot
        "rf+rr": {"label": "r_foot", "part": sorted(R_FOOT)},  # the other orientation: the foot itself
        "l_leg+r_leg": {"label": "l_leg+r_leg", "part": ["root_link", "torso"]},
    },
}


def test_phase_of_contact_sets() -> None:
    feet = P.feet_of(META)
    cases = {
        "l_front,l_rear": P.SINGLE,
        "r_rear": P.SINGLE,
        "l_sole": P.SINGLE,
        "l_front,l_rear,r_front,r_rear": P.DOUBLE,
        "root_link": P.POLE,
        "": P.AIR,
        "root_link,r_front": P.OTHER,
    }
    for contacts, phase in cases.items():
        assert P.phase_of(contacts, feet) == phase, contacts
    got = P.phases_of(np.array(list(cases) + [None], dtype=object), feet)
    assert got.tolist() == [*cases.values(), P.AIR]
    # without cut sets, only the soles are known as feet
    bare = P.feet_of({"pairs": META["pairs"]})
    assert P.phase_of("l_sole,r_sole", bare) == P.DOUBLE and P.phase_of("l_front", bare) == P.POLE


def test_phase_table_counts_and_errors() -> None:
    rng = np.random.default_rng(3)
    target = rng.normal(size=(10, 6))
    pred = target + rng.normal(size=(10, 6))
    phases = np.array([P.SINGLE] * 4 + [P.DOUBLE] * 3 + [P.OTHER] * 3, dtype=object)
    mask = np.ones(10, bool)
    mask[0] = False
    out = P.phase_table({"m": pred}, target, mask, phases, score)
    assert list(out) == [P.SINGLE, P.DOUBLE, P.POLE, P.AIR, P.OTHER]
    assert [out[p]["samples"] for p in out] == [3, 3, 0, 0, 3]
    err = (pred - target)[1:4]
    assert out[P.SINGLE]["models"]["m"]["rmse"] == pytest.approx(math.sqrt(np.mean(err**2)))
    assert out[P.SINGLE]["models"]["m"]["rmse_force"] == pytest.approx(math.sqrt(np.mean(err[:, :3] ** 2)))
    assert out[P.POLE]["models"]["m"]["rmse"] is None


def test_phase_models_pick_the_best_polynomial_on_validation() -> None:
    models = ["raw", "affine", "poly1", "poly2", "nn7", "nn13", "oracle"]
    ranking = ["nn13", "poly2", "nn7", "poly1", "affine", "raw"]
    assert P.phase_models(models, ranking, "nn7") == ["raw", "affine", "poly2", "nn7", "nn13", "oracle"]
    assert P.phase_models(models, ranking, "poly1")[-2:] == ["poly1", "oracle"]


CV = {
    "folds": [
        {"val": ["08_walking_train"], "train": ["00_pole_train", "09_walking_train"]},
        {"val": ["09_walking_train"], "train": ["00_pole_train", "08_walking_train"]},
    ],
    "scores": {"affine": [1.25, 1.5], "nn7": [0.5, 0.9]},
    "mean": {"affine": 1.375, "nn7": 0.7},
    "spread": {"affine": 0.125, "nn7": 0.2},
    "rule": "lowest mean; a more complex model must beat the simpler by more than the spread",
    "chosen": "nn7",
}


def _rows(html: str) -> list[list[str]]:
    body = html[html.index("<tbody>") : html.index("</tbody>")]
    return [re.findall(r"<td[^>]*>(.*?)</td>", row) for row in body.split("</tr>") if "<td" in row]


def test_cv_section_shows_folds_mean_spread_and_choice() -> None:
    html = cv_section(CV)
    assert "<th>fold 1</th><th>fold 2</th><th>mean</th><th>spread</th>" in html
    assert _rows(html) == [
        ["affine", "1.25", "1.50", "1.38", "0.125"],
        ["<b>nn7</b> (chosen)", "0.5", "0.9", "0.7", "0.2"],
    ]
    assert "validation 08_walking_train (trained on 2 logs)" in html and CV["rule"] in html
    for missing in (None, {}, {"scores": {}}, {"rule": "x"}):
        assert cv_section(missing) == ""


def _report(group: str, headlines: list[str] | None, rmse: dict[str, float]) -> GroupReport:
    names = headlines or [group]
    models = ["raw", "nn7", "nn13", "oracle"]
    tables = {n: {"labels": {m: {"rmse": rmse[n] * (1 + k)} for k, m in enumerate(models)}} for n in names}
    noise = NoiseResult(1.0, 1, {"nn7": 1.0}, {}, {}, {}, None, [])
    return GroupReport(
        group=group,
        sensors=names,
        pair=None,
        headline=names[0],
        names=names,
        models=models,
        samples_test=10,
        tables=tables,
        by_experiment={},
        noise=noise,
        best_on_validation="nn7",
        validation_ranking=["nn7", "raw"],
        recommended="nn7",
        headlines=headlines,
    )


def test_summary_has_one_row_per_headline() -> None:
    cfg = stage_section(
        load_params(Path(__file__).resolve().parents[1] / "params.yaml"), "evaluate", EvaluateParams
    )
    legs = _report("legs", ["l_leg", "r_leg", "l_foot"], {"l_leg": 1.0, "r_leg": 2.0, "l_foot": 4.0})
    arm = _report("arm", None, {"arm": 8.0})
    rows = _rows(summary_table([legs, arm], cfg))
    assert [r[0] for r in rows] == ["legs", "r_leg", "l_foot", "arm"]  # the group cell spans its rows
    assert rows[0][:6] == ["legs", "l_leg", "1.00", "2.00", "2.00", "4.00"]  # raw, best on val., NN7, oracle
    assert rows[1][:5] == ["r_leg", "2.00", "4.00", "4.00", "8.00"] and len(rows[1]) < len(rows[0])
    assert rows[2][1] == "4.00" and rows[3][:3] == ["arm", "arm", "8.00"]
    assert "<td rowspan=3>legs</td>" in summary_table([legs], cfg)


def test_the_wholebodydynamics_section_gives_the_affine_maps_cost_per_headline() -> None:
    from pipeline.evaluation.sections import wbd_section

    legs = _report("legs", ["l_leg", "r_leg"], {"l_leg": 1.0, "r_leg": 2.0})
    for name, affine in (("l_leg", 3.0), ("r_leg", 2.5)):
        legs.tables[name]["labels"]["affine"] = {"rmse": affine}
    html = wbd_section([legs, _report("arm", None, {"arm": 8.0})])  # the arm has no affine map: no row
    rows = _rows(html)
    assert rows == [
        ["l_leg", "nn7", "2.00", "3.00", "1.50", "labels"],
        ["r_leg", "nn7", "4.00", "2.50", "0.625", "labels"],
    ]
    assert "exported/wholebodydynamics.xml" in html and wbd_section([]) == ""
