"""The ``win`` family: the windowed network (`pipeline.calib.window`), a Lipschitz-bounded correction of the
play model over a causal window of the raw wrench (memory), trained with Adam on the play model of its fold
(``window_*`` params). Saved as ``win.json``; exported as one `pipeline.calib.parts.WindowPart` per sensor.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.calib.families.base import WINDOW, Family, Saving, Task
from pipeline.core.errors import DataError

if TYPE_CHECKING:
    import numpy as np

    from pipeline.calib.data import Group, GroupData
    from pipeline.calib.params import GroupParams
    from pipeline.calib.parts import GroupModel
    from pipeline.calib.window import WindowFit

WINDOW_SUFFIX = ".json"  # a windowed network's file: models/<group>/<name>.json (win.json)


@dataclass
class WindowedModel:
    """A trained windowed network (`Trained`)."""

    fit: WindowFit
    name: str = "win"
    n_inputs: int = 7

    @property
    def history(self) -> list[dict[str, float]]:
        return self.fit.history

    def predict(self, data: GroupData) -> np.ndarray:
        from pipeline.calib.window import window_memory

        model = self.fit.model
        return model.predict(data.x, window_memory(model.base, data))

    def fidelity(self, data: GroupData) -> tuple[Callable[..., np.ndarray], np.ndarray]:
        from pipeline.calib.window import window_memory

        return self.fit.model.predict, window_memory(self.fit.model.base, data)


class Windowed(Family):
    def names(self, gp: GroupParams, group: Group) -> list[str]:
        return [self.key] if group.windows is not None and group.widths is not None else []

    def fit(self, task: Task) -> dict[str, WindowedModel]:
        from pipeline.calib.window import fit_windowed

        play = {"play": task.fitted["play"].model}
        return {
            self.key: WindowedModel(fit_windowed(task.gp, task.group, task.train, task.val, play, task.seed))
        }

    def line(self, group: Group, fold: int, model: WindowedModel) -> str | None:
        best = min(model.history, key=lambda h: h["val_rmse"])
        head = f"{group.name} fold {fold + 1}: {model.name}" if fold else f"{group.name}: windowed network"
        epoch, seconds = int(best["epoch"]) + 1, model.fit.seconds
        return f"{head} val RMSE {best['val_rmse']:.4g} (epoch {epoch}) {seconds:.1f} s"

    def record(self, models: Mapping[str, WindowedModel], gp: GroupParams) -> dict[str, Any]:
        return {"windowed": models[self.key].fit.info()}

    def save(self, saving: Saving, models: Mapping[str, WindowedModel]) -> None:
        from pipeline.core.io import write_json

        for name, m in models.items():
            write_json(saving.out / f"{name}{WINDOW_SUFFIX}", m.fit.model.to_dict())
            saving.files.append(f"{name}{WINDOW_SUFFIX}")

    def read(self, model_dir: Path, name: str, group: str, sensors: tuple[str, ...]) -> GroupModel:
        return read_windowed(model_dir, name, group, sensors)

    def loaded(self, model_dir: Path, name: str, sensors: Sequence[str]) -> tuple[Callable, int]:
        from pipeline.calib.window import read_window

        return read_window(model_dir / f"{name}{WINDOW_SUFFIX}").predict_log, 7


def read_windowed(model_dir: Path, name: str, group: str, sensors: tuple[str, ...]) -> GroupModel:
    """The windowed network of ``<name>.json`` (`pipeline.calib.window.WindowModel.to_dict`)."""
    import numpy as np

    from pipeline.calib.parts import Dense, WindowPart, linear_parts, log_model
    from pipeline.calib.window import read_window

    path = model_dir / f"{name}{WINDOW_SUFFIX}"
    model = read_window(path)
    base, n_sensors = model.base, len(sensors)
    width = base.offset.shape[-1]  # 7, or 6 without temperature
    taus = np.asarray(model.time_constants, dtype=np.float64)
    if (why := _window_fault(model, n_sensors)) is not None:
        raise DataError(f"{path}: {why}")
    filters = np.zeros((*base.weights.shape[:2], 6 * len(taus)))  # the play model reads none of them
    with_filters = replace(
        base,
        weights=np.concatenate([base.weights, filters], axis=2),
        time_constants=taus,
        period=model.period,
    )
    parts = tuple(
        WindowPart(
            play,
            net.in_offset,
            net.in_scale,
            net.out_scale,
            tuple(Dense(y.weight, y.bias, y.activation, float(y.alpha)) for y in net.layers),
        )
        for play, net in zip(linear_parts(with_filters), model.nets, strict=True)
    )

    info: dict[str, Any] = {
        "time_constants_s": taus.tolist(),
        "period_s": float(model.period),
        "play_widths": base.widths.tolist(),
        "layers": [[int(y.weight.shape[0]), y.activation] for y in model.nets[0].layers],
    }
    return log_model(group, name, sensors, width, parts, model, info)


def _window_fault(model: Any, n_sensors: int) -> str | None:
    """What makes a `pipeline.calib.window.WindowModel` of a group of `n_sensors` unexportable, else None."""
    import numpy as np

    from pipeline.calib.parts import ACTIVATIONS, WRENCH

    base, taus = model.base, np.asarray(model.time_constants)
    if base.weights.shape[0] != n_sensors or len(model.nets) != n_sensors:
        return f"{base.weights.shape[0]} play sensors, {len(model.nets)} networks; metrics.json {n_sensors}"
    if base.widths is None or base.time_constants is not None or base.offset.shape[-1] not in (6, 7):
        return "its base is not a play model"
    if not len(taus) or not np.all((taus > 0) & np.isfinite(taus)):
        return f"time constants {taus.tolist()} s are not positive"
    if not 0 < model.period < math.inf:
        return f"sample period {model.period} s"
    n_features = WRENCH * (len(taus) + 1) + base.offset.shape[-1] - WRENCH
    for net in model.nets:
        width = n_features
        for y in net.layers:
            if y.weight.ndim != 2 or y.weight.shape[1] != width or y.bias.shape != (y.weight.shape[0],):
                return f"a network's layers do not chain from its {n_features} inputs"
            if y.activation not in ACTIVATIONS:
                return f"activation {y.activation!r} cannot be exported"
            width = y.weight.shape[0]
        shapes = (net.in_offset.shape, net.in_scale.shape, net.out_scale.shape)
        if width != WRENCH or shapes != ((n_features,), (n_features,), (WRENCH,)):
            return f"a network is not {n_features} inputs to {WRENCH} outputs"
    return None


FAMILY = Windowed(
    "win", 7, WINDOW, True, False,
    "windowed network (a Lipschitz-bounded correction of the play model over a causal window of the raw "
    "wrench: memory)", "#8c564b",
    after=("play",),
)  # fmt: skip
