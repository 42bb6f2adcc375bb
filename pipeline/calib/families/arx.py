"""The ``arx`` family: the affine map and low-pass departures of the raw wrench (memory: a lagged linear
map, ARX with fixed poles), its filters at the training logs' (median) sample period
(`pipeline.core.lowpass`)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from pipeline.calib.families.base import LINEAR
from pipeline.calib.families.closed_form import ClosedForm

if TYPE_CHECKING:
    from pipeline.calib.data import Group, GroupData
    from pipeline.calib.params import GroupParams


class Arx(ClosedForm):
    def names(self, gp: GroupParams, group: Group) -> list[str]:
        return [self.key] if group.time_constants is not None else []


def _spec(name: str, gp: GroupParams, group: Group, data: GroupData) -> dict[str, Any]:
    import numpy as np

    tcs, period = np.asarray(group.time_constants), float(np.median(data.period))
    return {"order": 1, "ridge": 0.0, "time_constants": tcs, "period": period, "memory": data.memory}


FAMILY = Arx(
    "arx", 5, LINEAR, True, False,
    "affine map and low-pass departures of the raw wrench (memory: a lagged linear map, ARX with fixed "
    "poles)",
    "#17becf",
    spec=_spec,
)  # fmt: skip
