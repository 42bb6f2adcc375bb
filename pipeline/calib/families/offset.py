"""The ``offset`` family: the factory map and a constant correction per axis (least squares: the factory's
gains kept, what a re-zeroing does)."""

from __future__ import annotations

from pipeline.calib.families.base import LINEAR
from pipeline.calib.families.closed_form import ClosedForm

FAMILY = ClosedForm(
    "offset", 1, LINEAR, False, False,
    "the factory map and a constant offset (least squares: the factory's gains kept, as a re-zeroing does)",
    "#393b79",
    on_tables=False,
    spec=lambda name, gp, group, data: {"order": 0, "ridge": 0.0},
)  # fmt: skip
