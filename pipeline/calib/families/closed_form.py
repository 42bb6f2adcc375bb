"""The families fitted in closed form (offset, affine, poly, play, arx): what they share.

Each is a `pipeline.calib.linear.LinearBaseline` fitted on the networks' switched loss with the group's
virtual pushes (`pipeline.calib.pushes`), saved in the group's baselines.json and exported as one
`pipeline.calib.parts.LinearPart` per sensor. A family says which models it fits for a group (`names`) and
with which features (`spec`: the monomials' order, the ridge, the play widths or the filters); this module
fits them. A group of several sensors is fitted part by part: each foot pair (a cut set with constant
transforms) jointly with its sum term, every other sensor alone; the cut sets whose transforms depend on
the joints are left to the networks (per-sample transforms make the normal equations of the polynomials too
big).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.calib.families.base import Family, Saving, Task
from pipeline.core.errors import DataError

if TYPE_CHECKING:
    import numpy as np

    from pipeline.calib.data import Group, GroupData
    from pipeline.calib.linear import LinearBaseline
    from pipeline.calib.params import GroupParams
    from pipeline.calib.parts import GroupModel

BASELINES_FILE = "baselines.json"
Spec = Callable[[str, "GroupParams", "Group", "GroupData"], dict[str, Any]]


@dataclass
class ClosedFormModel:
    """A fitted closed-form model (`Trained`)."""

    model: LinearBaseline
    n_inputs: int = 7  # it reads the wrench and temperature of its inputs (of x's first 7 columns)

    @property
    def name(self) -> str:
        return self.model.name

    def predict(self, data: GroupData) -> np.ndarray:
        return self.model.predict(data.x, data.memory)

    def fidelity(self, data: GroupData) -> tuple[Callable[..., np.ndarray], np.ndarray | None]:
        return self.model.predict, data.memory if self.model.memory else None


@dataclass(frozen=True)
class ClosedForm(Family):
    """A family of closed-form models: `spec` gives a model's features (module docstring)."""

    spec: Spec | None = None  # (name, params, group or part, its data) -> `fit_linear_baseline` features

    def fit(self, task: Task) -> dict[str, ClosedFormModel]:
        fitted = fit_closed_form(
            task.gp, task.group, task.train, task.seed, self.names(task.gp, task.group), self
        )
        return {name: ClosedFormModel(b) for name, b in fitted.items()}

    def save(self, saving: Saving, models: Mapping[str, ClosedFormModel]) -> None:
        saving.baselines.update({name: m.model.to_dict() for name, m in models.items()})

    def read(self, model_dir: Path, name: str, group: str, sensors: tuple[str, ...]) -> GroupModel:
        return read_linear(model_dir, name, group, sensors)

    def loaded(self, model_dir: Path, name: str, sensors: Sequence[str]) -> tuple[Callable, int]:
        return read_baseline(model_dir, name).predict_log, 7


def read_baseline(model_dir: Path, name: str) -> LinearBaseline:
    """Model `name` of `model_dir`'s baselines.json."""
    from pipeline.calib.linear import LinearBaseline

    path = model_dir / BASELINES_FILE
    try:
        return LinearBaseline.from_dict(json.loads(path.read_text(encoding="utf-8"))[name])
    except FileNotFoundError:
        raise DataError(f"{path}: not found") from None
    except KeyError as exc:
        raise DataError(f"{path}: no entry {exc} (models: {name} was not trained?)") from None
    except (OSError, ValueError, TypeError) as exc:
        raise DataError(f"{path}: not a baselines file: {exc}") from None


def read_linear(model_dir: Path, name: str, group: str, sensors: tuple[str, ...]) -> GroupModel:
    """A closed-form model of baselines.json in its export form: one `LinearPart` per sensor."""
    from pipeline.calib.parts import linear_parts, log_model

    path, baseline = model_dir / BASELINES_FILE, read_baseline(model_dir, name)
    n_sensors, width = len(sensors), baseline.offset.shape[-1]  # width: 7, or 6 without temperature
    if (
        baseline.weights.shape[0] != n_sensors
        or baseline.offset.shape != (n_sensors, width)
        or width not in (6, 7)
    ):
        raise DataError(f"{path}: {name} has {baseline.weights.shape[0]} sensors, metrics.json {n_sensors}")
    order = int(baseline.powers.sum(axis=1).max(initial=0))
    info: dict[str, Any] = {"order": order, "monomials": len(baseline.powers)}
    if baseline.widths is not None:
        info["play_widths"] = baseline.widths.tolist()
    if baseline.time_constants is not None:
        info["time_constants_s"], info["period_s"] = baseline.time_constants.tolist(), baseline.period
    return log_model(group, name, sensors, width, linear_parts(baseline), baseline, info)


def fit_closed_form(
    gp: GroupParams, group: Group, train: GroupData, seed: int, names: Sequence[str], family: ClosedForm
) -> dict[str, LinearBaseline]:
    """Models `names` of `family` on the switched loss of the networks (module docstring), each with the
    group's virtual pushes sampled from `seed` (each fit is independent of the others)."""
    from pipeline.calib.training import NetSetting

    if group.cuts:
        return _by_part(gp, group, train, seed, names, family)
    return _fit_part(gp, group, train, NetSetting.of(gp, 7).lambdas, gp.lambda_sum, seed, names, family)


def _fit_part(
    gp: GroupParams,
    group: Group,
    train: GroupData,
    lambdas: tuple[float, ...],
    lambda_sum: float,
    seed: int,
    names: Sequence[str],
    family: ClosedForm,
) -> dict[str, LinearBaseline]:
    """Models `names` of a group of one sensor or one foot pair (its sum term with `lambda_sum`)."""
    from pipeline.calib.linear import fit_linear_baseline
    from pipeline.calib.params import baseline_inputs

    args = {
        "push": gp.push,
        "seed": seed,
        "x": train.x,
        "labels": train.labels,
        "switches": train.switches,
        "lambdas": lambdas,
        "sum_label": train.sum_label,
        "alpha_sum": train.alpha_sum,
        "transforms": group.transforms,
        "lambda_sum": lambda_sum,
        "n_inputs": baseline_inputs(gp.inputs),
    }
    assert family.spec is not None, family.key
    return {name: fit_linear_baseline(name, **args, **family.spec(name, gp, group, train)) for name in names}


def _by_part(
    gp: GroupParams, group: Group, train: GroupData, seed: int, names: Sequence[str], family: ClosedForm
) -> dict[str, LinearBaseline]:
    """`fit_closed_form` of a group of several sensors: its foot pairs and lone sensors, stacked per
    sensor."""
    import numpy as np

    from pipeline.calib.data import Group, GroupData, derive_seed

    parts: list[tuple[list[int], int | None]] = []  # (sensor indices, fixed cut index or None)
    taken: set[int] = set()
    for c, cut in enumerate(group.cuts):
        if cut.is_fixed and cut.pair is not None and not taken & set(cut.members):
            parts.append((list(cut.members), c))
            taken |= set(cut.members)
    parts += [([s], None) for s in range(len(group.sensors)) if s not in taken]
    fitted: list[tuple[list[int], dict[str, LinearBaseline]]] = []
    for members, c in parts:
        sub = Group(
            group.name,
            tuple(group.sensors[s] for s in members),
            widths=group.widths,
            time_constants=group.time_constants,
        )
        part = GroupData(
            train.log,
            train.stamp,
            train.time,
            train.x[:, members],
            train.labels[:, members],
            train.switches[:, members],
            memory=None if train.memory is None else train.memory[:, members],
            period=train.period,
        )
        if c is not None:
            sub = replace(sub, pair=group.cuts[c].label, transforms=group.cuts[c].fixed)
            part.sum_label, part.sum_switch = train.cut_labels[:, c], train.cut_switches[:, c]
        lambdas = (gp.lambda_expected,) * len(members)
        data, part_seed = part.subset(part.labelled()), derive_seed(seed, *members)
        fitted.append((members, _fit_part(gp, sub, data, lambdas, gp.lambda_cut, part_seed, names, family)))
    out = {}
    for name in names:
        stack = sorted(
            (s, b, k) for members, models in fitted for k, s in enumerate(members) for b in [models[name]]
        )
        out[name] = replace(
            stack[0][1],
            offset=np.stack([b.offset[k] for _, b, k in stack]),
            scale=np.stack([b.scale[k] for _, b, k in stack]),
            weights=np.stack([b.weights[k] for _, b, k in stack]),
        )
    return out
