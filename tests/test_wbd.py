"""The wholeBodyDynamics configuration an export writes, read back as the estimator reads it.

`ftcal export` writes ``exported/wholebodydynamics.xml``: per sensor the ``FT_SECONDARY_CALIBRATION``
(36, row-major), ``FT_TEMPERATURE_COEFFICIENTS`` (6 and the reference temperature) and ``FT_OFFSET`` (6)
groups of robotology's wholeBodyDynamics. Parsed here with the standard library's XML parser and applied
with the estimator's own formula, written out independently of ftcal (``SixAxisForceTorqueMeasureHelpers``:
``w = S w_raw - o + c (T - T_ref)``, and after ``usePreEstimatedOffset`` ``o = -FT_OFFSET``), it gives the
affine model's own outputs on every labelled sample; a re-zeroing's offset change moves FT_OFFSET so that
the estimator then gives the affine model on the re-zeroed raw readings.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from pipeline.cli import main
from pipeline.export import wbd
from pipeline.export.trained import read_group
from tests.factories.labelled import LEG, PAIR


def _parse(text: str) -> dict[str, dict[str, np.ndarray]]:
    """group name -> sensor -> its values, as the device reads them: one <param> per sensor, a
    parenthesised list of numbers."""
    root = ET.fromstring(f"<root>{text}</root>")
    out: dict[str, dict[str, np.ndarray]] = {}
    for group in root.iter("group"):
        for param in group.iter("param"):
            body = param.text.strip()
            assert body.startswith("(") and body.endswith(")"), body
            values = [float(v) for v in body[1:-1].replace("\n", " ").split(",")]
            out.setdefault(group.get("name"), {})[param.get("name")] = np.array(values)
    return out


def _estimator(groups: dict[str, dict[str, np.ndarray]], sensor: str, raw: np.ndarray, t: np.ndarray):
    """wholeBodyDynamics' filt(): S w_raw - o + c (T - T_ref) with o = -FT_OFFSET, per row of raw (N, 6)."""
    s = groups["FT_SECONDARY_CALIBRATION"][sensor].reshape(6, 6)  # secondaryCalibMat(r, c) = list[6 r + c]
    o = -groups.get("FT_OFFSET", {}).get(sensor, np.zeros(6))
    tc = groups.get("FT_TEMPERATURE_COEFFICIENTS", {}).get(sensor, np.zeros(7))
    return raw @ s.T - o + np.outer(t - tc[6], tc[:6])


@pytest.fixture(scope="module")
def exported(trained_models: dict, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Both export steps through the CLI, poly2 recommended for the leg and nn7 for the foot pair."""
    tmp = tmp_path_factory.mktemp("wbd")
    metrics = tmp / "metrics"
    for group, model in ((LEG, "poly2"), (PAIR, "nn7")):
        (metrics / group).mkdir(parents=True)
        (metrics / group / f"{group}.json").write_text(json.dumps({"deployed": model}))
    patch = pytest.MonkeyPatch()
    patch.setenv("MLFLOW_TRACKING_URI", trained_models["mlflow_uri"])
    try:
        args = [
            str(trained_models["models"]),
            str(metrics),
            str(trained_models["labelled"]),
            str(tmp / "out"),
        ]
        assert main(["export", *args, "--params", str(trained_models["params"])]) == 0
    finally:
        patch.undo()
    return tmp / "out"


def _samples(trained: dict, model: Any) -> np.ndarray:
    tables = [
        pd.read_parquet(p, columns=model.input_columns) for p in sorted(trained["labelled"].glob("*.parquet"))
    ]
    x = pd.concat(tables).to_numpy()
    return x[np.isfinite(x).all(axis=1)]


def test_the_fragment_applied_by_the_estimators_formula_is_the_affine_model(
    exported: Path, trained_models: dict
) -> None:
    groups = _parse((exported / wbd.FILE).read_text())
    manifest = json.loads((exported / "manifest.json").read_text())
    assert manifest[wbd.KEY]["file"] == wbd.FILE and manifest[wbd.KEY]["models"] == {
        LEG: "poly2",
        PAIR: "nn7",
    }
    checked = []
    for group in (LEG, PAIR):
        affine = read_group(trained_models["models"] / group, "affine", group)
        x = _samples(trained_models, affine)
        ours = affine.reference(x)
        k = affine.n_inputs
        for s, sensor in enumerate(affine.sensors):
            raw, t = x[:, s * k : s * k + 6], x[:, s * k + 6] if k > 6 else np.zeros(len(x))
            theirs = _estimator(groups, sensor, raw, t)
            assert np.max(np.abs(theirs - ours[:, 6 * s : 6 * s + 6])) < 1e-9, sensor
            assert len(x) > 100
            checked.append(sensor)
    assert sorted(checked) == sorted(groups["FT_SECONDARY_CALIBRATION"])
    if any(read_group(trained_models["models"] / g, "affine", g).n_inputs == 7 for g in (LEG, PAIR)):
        assert "FT_TEMPERATURE_COEFFICIENTS" in groups


def test_a_rezeroing_moves_ft_offset_so_the_estimator_reads_the_rezeroed_calibration(
    exported: Path, trained_models: dict
) -> None:
    manifest = json.loads((exported / "manifest.json").read_text())
    affine = read_group(trained_models["models"] / LEG, "affine", LEG)
    delta = np.array([3.0, -2.0, 15.0, 0.2, -0.1, 0.05])
    terms = wbd.rezeroed(manifest[wbd.KEY]["sensors"][LEG], delta)
    groups = _parse(wbd.fragment({LEG: terms}, "re-zeroed"))
    x = _samples(trained_models, affine)
    shifted = x.copy()
    shifted[:, :6] -= delta  # the re-zeroing's offsets are subtracted from the raw reading
    k = affine.n_inputs
    theirs = _estimator(groups, LEG, x[:, :6], x[:, 6] if k > 6 else np.zeros(len(x)))
    assert np.max(np.abs(theirs - affine.reference(shifted))) < 1e-9
    assert np.max(np.abs(theirs - affine.reference(x))) > 1.0  # the offset did move
