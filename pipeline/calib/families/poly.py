"""The ``poly<n>`` family: a polynomial of order n of the raw wrench and temperature (ridge ``ridge``), one
per order of ``poly_orders``."""

from __future__ import annotations

from typing import TYPE_CHECKING

from pipeline.calib.families.base import LINEAR
from pipeline.calib.families.closed_form import ClosedForm

if TYPE_CHECKING:
    from pipeline.calib.data import Group
    from pipeline.calib.params import GroupParams


class Polynomials(ClosedForm):
    def names(self, gp: GroupParams, group: Group) -> list[str]:
        return [self.name(order) for order in gp.poly_orders]


FAMILY = Polynomials(
    "poly", 3, LINEAR, False, True, "polynomial of wrench and temperature (ridge)", "#c8553d",
    ((1, "#d9b36c"), (2, "#e0894a"), (3, "#c8553d"), (4, "#8c2d04")),
    one_on_tables=True,
    spec=lambda name, gp, group, data: {"order": int(name[len("poly"):]), "ridge": gp.ridge},
)  # fmt: skip
