"""The ``raw`` family: the factory map (the raw wrench), nothing fitted: what every other model is
measured against."""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from pipeline.calib.families.base import IDENTITY, Family, Saving, Task
from pipeline.calib.families.closed_form import BASELINES_FILE

if TYPE_CHECKING:
    import numpy as np

    from pipeline.calib.data import GroupData
    from pipeline.calib.parts import GroupModel

WRENCH = 6


def _wrench(x: np.ndarray) -> np.ndarray:
    return x[:, :, :WRENCH].copy()


@dataclass
class RawModel:
    """The raw wrench of a group's inputs (`Trained`)."""

    name: str = "raw"
    n_inputs: int = 7

    def predict(self, data: GroupData) -> np.ndarray:
        return _wrench(data.x)

    def fidelity(self, data: GroupData) -> tuple[Callable[..., np.ndarray], None]:
        return _wrench, None


class Raw(Family):
    def fit(self, task: Task) -> dict[str, RawModel]:
        return {self.key: RawModel(self.key)}

    def save(self, saving: Saving, models: Mapping[str, RawModel]) -> None:
        pass  # nothing to keep

    def read(self, model_dir: Path, name: str, group: str, sensors: tuple[str, ...]) -> GroupModel:
        """The raw wrench, on the inputs of the group's baselines (7, or 6 without temperature)."""
        import numpy as np

        from pipeline.calib.parts import GroupModel, IdentityPart, input_columns, output_columns

        n, width = len(sensors), _baseline_width(model_dir)

        def reference(x: np.ndarray) -> np.ndarray:
            return (
                np.asarray(x, dtype=np.float64).reshape(len(x), n, width)[:, :, :WRENCH].reshape(len(x), -1)
            )

        return GroupModel(
            group,
            name,
            self.key,
            sensors,
            width,
            tuple(IdentityPart() for _ in sensors),
            [c for s in sensors for c in input_columns(s, width)],
            [c for s in sensors for c in output_columns(s)],
            reference,
        )


def _baseline_width(model_dir: Path) -> int:
    """The inputs per sensor of a group's baselines: 7 (wrench, temperature), or 6 where it has none."""
    import numpy as np

    try:
        entry = json.loads((model_dir / BASELINES_FILE).read_text(encoding="utf-8")).get("affine") or {}
        return int(np.shape(entry.get("offset", [[0] * 7]))[-1])
    except (OSError, ValueError):
        return 7


FAMILY = Raw("raw", 0, IDENTITY, False, False, "the factory map (the raw wrench)", "#8c8c8c", inline=True)
