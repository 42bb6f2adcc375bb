"""A group's fit: prepared data, baselines, scores and the model to deploy."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.calib.data import (
    ROLE_TRAIN,
    Group,
    GroupData,
    LogInfo,
    concat,
    derive_seed,
    expand_feet,
    find_logs,
    group_errors,
    load_group_data,
    resolve_group,
)
from pipeline.calib.exact import LEFT_OUT, calibrable
from pipeline.calib.imu_gate import refuse_flagged_imu
from pipeline.calib.memory import structure
from pipeline.calib.params import GroupParams, TrainParams
from pipeline.calib.records import flatten_metrics
from pipeline.calib.split import split_logs, time_blocks
from pipeline.core.config import Params, stage_section
from pipeline.core.errors import DataError
from pipeline.logs import schema as S


@dataclass
class Prepared:
    """A group's data, split by whole logs, ready to fit (see `prepare`)."""

    cfg: TrainParams
    gp: GroupParams
    seed: int  # the baselines' virtual pushes (derived from params' seed and the group)
    group: Group
    split: dict[str, list[str]]  # train/val/test -> log names
    log_names: list[str]  # every log, in the order `GroupData.log` indexes
    train: GroupData  # training samples with at least one loss term
    val: GroupData  # every validation sample with ok inputs
    test: GroupData  # every test sample with ok inputs
    # the other cross-validation folds (1..folds-1): (training samples with a loss term, validation samples)
    folds: list[tuple[GroupData, GroupData]] = field(default_factory=list)
    recorded: list[str] = field(default_factory=list)  # the logs that are recordings (no truth)
    notes: list[str] = field(default_factory=list)  # what the group does not train and why (imu_gate)
    memory: dict[str, Any] = field(default_factory=dict)  # the memory models' structure the data chose


def prepare(params: Params, group_name: str, in_dir: Path) -> Prepared:
    """Read the group's samples from the labelled tables of `in_dir` and split them (module docstring).

    A sensor of a group of several without any exact label on the training logs (its joint streams absent)
    is left out of the group (`pipeline.calib.exact`), the others train.

    Raises:
        ConfigError: unknown group, or a group naming a sensor or pair the data does not have.
        NotCalibrated: no sensor of the group has an exact label on the training logs (checked first).
        DataError: missing directory or tables, no train/test logs, no exact label to train or validate on.
    """
    cfg = stage_section(params, "train", TrainParams)
    logs = find_logs(in_dir)
    gp = expand_feet(cfg.group(group_name), logs)
    gp, group = _calibrable(params, gp, resolve_group(gp, params, logs), logs)
    gp, group, notes = refuse_flagged_imu(gp, group, logs)  # a board whose IMU check failed: no nn13
    logs, blocked = time_blocks(logs, cfg.folds)
    notes += [f"{group.name}: {blocked}"] if blocked else []
    split = split_logs(logs, cfg.val_logs, params.seed, cfg.folds)
    log_names = [log.name for log in logs]
    training = [logs[log_names.index(n)] for n in split["train"]]
    group, memory = structure(group, training, gp.play_width_fractions, gp.arx_time_constants_s)
    data = {}
    for k in ("train", "val", "test"):
        part = load_group_data(group, [logs[log_names.index(n)] for n in split[k]])
        part.log = np.array([log_names.index(n) for n in split[k]])[part.log]  # split-local -> global index
        data[k] = part
    tested = data["test"].switches.any(axis=0)
    group = replace(group, tested=tuple(s for s, on in zip(group.sensors, tested, strict=True) if on))
    train = data["train"].subset(data["train"].labelled())
    if len(train) == 0:
        names = (*group.sensors, *([group.pair] if group.pair else []))
        switch = " or ".join(S.switch_col(n) for n in names)
        raise DataError(f"{group.name}: no training sample with an exact label ({switch} = 1) in {in_dir}")
    folds = []
    every = concat([data["train"], data["val"]])
    for k, fold in enumerate(split["folds"]):
        held = np.isin(every.log, [log_names.index(n) for n in fold["val"]])
        val, fold_train = every.subset(held), every.subset(~held)
        if not (val.switches.any() or (val.sum_switch is not None and val.sum_switch.any())):
            raise DataError(
                f"{group.name}: the validation logs ({', '.join(fold['val'])}) have no exact label"
            )
        if k:
            folds.append((fold_train.subset(fold_train.labelled()), val))
    recorded = [log.name for log in logs if not log.simulated]
    seed = derive_seed(params.seed, group_name, "pushes")
    test = data["test"]
    return Prepared(
        cfg, gp, seed, group, split, log_names, train, data["val"], test, folds, recorded, notes, memory
    )


def _calibrable(
    params: Params, gp: GroupParams, group: Group, logs: Sequence[LogInfo]
) -> tuple[GroupParams, Group]:
    """The group without its sensors that have no exact label on the training logs (`calibrable`);
    NotCalibrated if none has one. A sensor or foot-pair group is calibrated whole or not at all."""
    cuts = {c.label: [group.sensors[m] for m in c.members] for c in group.cuts}
    if group.pair is not None:
        cuts[group.pair] = list(group.sensors)
    paths = [log.path for log in logs if log.role == ROLE_TRAIN]
    if not paths:  # no training log at all: `split_logs` says so
        return gp, group
    kept, left_out = calibrable(group.name, group.sensors, cuts, paths)
    if not left_out or gp.sensors is None:
        return gp, group
    gp = replace(gp, sensors=tuple(kept)) if len(kept) > 1 else replace(gp, sensors=None, sensor=kept[0])
    return gp, replace(resolve_group(gp, params, logs), left_out=tuple(left_out.items()))


def score(
    prep: Prepared, preds: Mapping[str, Mapping[str, np.ndarray]], cv: Mapping[str, Any]
) -> dict[str, Any]:
    """metrics.json: validation and test errors of every model, the cross-validation (`cv`, from
    `pipeline.calib.crossval.cross_validate`) and the model to deploy it chooses (a family adds its own
    entries: `pipeline.calib.families.base.Family.record`)."""
    group = prep.group
    metrics: dict[str, Any] = {
        "group": group.name,
        "kind": "pair" if group.pair is not None else "sensors" if group.cuts else "sensor",
        "sensors": list(group.sensors),
        "pair": group.pair,
        "headline": group.headline,
        "headlines": list(group.headlines),
        # several sensors: each foot pair's sensors (front, rear) and the cut sets trained with a sum term
        "pairs": {c.label: [group.sensors[m] for m in c.members] for c in group.cuts if c.pair is not None},
        "cut_sets": [c.label for c in group.cuts],
        "logs": prep.split,
        # simulated (with truth), recorded (labels only: nothing to check against a truth) or mixed
        "data": "simulated"
        if not prep.recorded
        else "recorded"
        if len(prep.recorded) == len(prep.log_names)
        else "mixed",
        "samples": {"train": len(prep.train), "val": len(prep.val), "test": len(prep.test)},
        "selection": cv["rule"],
        "cv": dict(cv),
        "memory": prep.memory,  # the play widths and arx time constants the training data chose
    }
    if group.left_out:  # sensors of the group without any exact label: not calibrated, and why
        metrics[LEFT_OUT] = dict(group.left_out)
    for k, data in (("val", prep.val), ("test", prep.test)):
        metrics[k] = {name: group_errors(group, data, pred) for name, pred in preds[k].items()}
    means = cv["mean"]
    chosen = cv["chosen"]
    ranked = sorted(means, key=lambda m: (not np.isfinite(means[m]), means[m]))
    # the chosen model first, then the others by mean fold error (the fallbacks if it is noise-flagged)
    metrics["best_on_validation"] = chosen
    metrics["lowest_on_validation"] = ranked[0]
    metrics["validation_ranking"] = [chosen, *(m for m in ranked if m != chosen)]
    return metrics


def mlflow_metrics(group: Group, metrics: Mapping[str, Any]) -> dict[str, float]:
    """The headline errors as flat MLflow metric names, e.g. ``test.nn7.r_leg_ft.rmse_force``."""
    flat: dict[str, float] = {}
    for k in ("val", "test"):
        for name, errors in metrics[k].items():
            keep = {"rmse": errors["rmse"], "rmse_labelled": errors["rmse_labelled"]}
            keep.update({s: errors[s] for s in dict.fromkeys((*group.sensors, *group.headlines))})
            flat.update(flatten_metrics(f"{k}.{name}", keep))
    flat.update({f"seconds.{k}": v for k, v in metrics["seconds"].items()})
    return flat
