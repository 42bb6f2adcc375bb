"""The ``affine`` family: an affine map of the raw wrench and temperature (least squares), the map the
networks correct (fitted first, in the training process)."""

from __future__ import annotations

from pipeline.calib.families.base import LINEAR
from pipeline.calib.families.closed_form import ClosedForm

FAMILY = ClosedForm(
    "affine", 2, LINEAR, False, False, "affine map with temperature (least squares)", "#bcbd22",
    inline=True,
    spec=lambda name, gp, group, data: {"order": 1, "ridge": 0.0},
)  # fmt: skip
