"""The ``play`` family: the affine map and play operators of the raw wrench (memory: hysteresis), the
widths chosen from the training logs (`pipeline.calib.memory`)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from pipeline.calib.families.base import LINEAR
from pipeline.calib.families.closed_form import ClosedForm

if TYPE_CHECKING:
    from pipeline.calib.data import Group, GroupData
    from pipeline.calib.params import GroupParams


class Play(ClosedForm):
    def names(self, gp: GroupParams, group: Group) -> list[str]:
        return [self.key] if group.widths is not None else []


def _spec(name: str, gp: GroupParams, group: Group, data: GroupData) -> dict[str, Any]:
    import numpy as np

    return {"order": 1, "ridge": 0.0, "widths": np.asarray(group.widths), "memory": data.memory}


FAMILY = Play(
    "play", 4, LINEAR, True, False,
    "affine map and play operators of the raw wrench (memory: hysteresis)", "#9467bd",
    spec=_spec,
)  # fmt: skip
