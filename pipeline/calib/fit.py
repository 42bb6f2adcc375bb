"""A group's fit: prepared data, baselines, scores and the model to deploy."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
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
    input_cols,
    load_group_data,
    resolve_group,
)
from pipeline.calib.exact import LEFT_OUT, calibrable
from pipeline.calib.imu_gate import refuse_flagged_imu
from pipeline.calib.linear import LinearBaseline, fit_linear_baseline
from pipeline.calib.memory import structure
from pipeline.calib.params import LS_AFFINE, GroupParams, TrainParams, baseline_inputs
from pipeline.calib.records import flatten_metrics
from pipeline.calib.registry import AFFINE, ARX, OFFSET, PLAY, poly_name
from pipeline.calib.search import NetResult
from pipeline.calib.split import split_logs, time_blocks
from pipeline.calib.training import NetSetting
from pipeline.core.config import Params, stage_section
from pipeline.core.errors import DataError
from pipeline.core.parallel import forked_map
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


def fit_baselines(
    gp: GroupParams, group: Group, train: GroupData, seed: int, affine: bool = True
) -> dict[str, LinearBaseline]:
    """The affine (least squares) and polynomial (ridge) baselines on the switched loss of the networks, each
    with the group's virtual pushes (`pipeline.calib.pushes`; the polynomials' sampled from `seed`); without
    `affine`, the offset, the polynomials and the models with memory (each fit is independent of the others).

    A group of several sensors is fitted part by part: each foot pair (a cut set with constant transforms)
    jointly with its sum term, every other sensor alone; the cut sets whose transforms depend on the joints
    are left to the networks (per-sample transforms make the normal equations of the polynomials too big).
    """
    if group.cuts:
        return _fit_baselines_by_part(gp, group, train, seed, affine)
    return _fit_group_baselines(gp, group, train, NetSetting.of(gp, 7).lambdas, gp.lambda_sum, seed, affine)


def fit_affine(gp: GroupParams, group: Group, train: GroupData, seed: int) -> LinearBaseline:
    """The affine baseline of `fit_baselines` alone: the map the group's networks correct."""
    alone = replace(gp, poly_orders=(), play_width_fractions=(), arx_time_constants_s=())
    return fit_baselines(alone, group, train, seed)[AFFINE]


def fit_plain_affine(gp: GroupParams, group: Group, train: GroupData, seed: int) -> LinearBaseline:
    """The plain least-squares affine map (`fit_affine` without the virtual pushes), named LS_AFFINE: the
    in-situ reference any lab computes from its labels, scored beside the models of recorded logs."""
    return replace(fit_affine(replace(gp, lambda_push=0.0), group, train, seed), name=LS_AFFINE)


def fit_beside(
    gp: GroupParams,
    group: Group,
    train: GroupData,
    seed: int,
    jobs: Sequence[Callable[[LinearBaseline], Any]],
    labels: Sequence[str],
) -> tuple[dict[str, LinearBaseline], list[Any], float]:
    """`fit_baselines`, and the results of `jobs` (each given the affine map the networks start from), with
    the polynomials and the play model fitted in a forked process beside the jobs (`forked_map`: the same
    numbers as one after the other, the polynomials in the time the jobs leave a core idle; `labels` name
    the jobs in an error).
    Returns (baselines, the jobs' results, seconds of the baselines' own fits)."""
    t = time.perf_counter()
    start = fit_affine(gp, group, train, seed)
    seconds = time.perf_counter() - t

    def polynomials() -> tuple[dict[str, LinearBaseline], float]:
        t = time.perf_counter()
        return fit_baselines(gp, group, train, seed, affine=False), time.perf_counter() - t

    work = [*(lambda job=job: job(start) for job in jobs), polynomials]
    named = [*(f"{group.name}: {label}" for label in labels), f"{group.name}: polynomial baselines"]
    *results, (polys, poly_seconds) = forked_map(work, costs=[2.0] * len(jobs) + [1.0], labels=named)
    return {AFFINE: start, **polys}, results, seconds + poly_seconds


def _fit_group_baselines(
    gp: GroupParams,
    group: Group,
    train: GroupData,
    lambdas: tuple[float, ...],
    lambda_sum: float,
    seed: int,
    affine: bool = True,
) -> dict[str, LinearBaseline]:
    """The baselines of a group of one sensor or one foot pair (its sum term with `lambda_sum`): with
    `affine` the affine map alone, without the others (offset, polynomials, play and arx models)."""
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
    out = {AFFINE: fit_linear_baseline(AFFINE, order=1, ridge=0.0, **args)} if affine else {}
    if not affine:  # with the polynomials: the networks start from the affine map alone (`fit_affine`)
        out[OFFSET] = fit_linear_baseline(OFFSET, order=0, ridge=0.0, **args)
    for order in gp.poly_orders:
        out[poly_name(order)] = fit_linear_baseline(poly_name(order), order=order, ridge=gp.ridge, **args)
    if group.widths is not None:
        widths, memory = np.asarray(group.widths), train.memory
        out[PLAY] = fit_linear_baseline(PLAY, order=1, ridge=0.0, widths=widths, memory=memory, **args)
    if group.time_constants is not None:  # at the training logs' (median) sample period
        tcs, period = np.asarray(group.time_constants), float(np.median(train.period))
        out[ARX] = fit_linear_baseline(
            ARX, order=1, ridge=0.0, time_constants=tcs, period=period, memory=train.memory, **args
        )
    return out


def _fit_baselines_by_part(
    gp: GroupParams, group: Group, train: GroupData, seed: int, affine: bool = True
) -> dict[str, LinearBaseline]:
    """`fit_baselines` of a group of several sensors: its foot pairs and lone sensors, stacked per sensor."""
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
        fitted.append(
            (
                members,
                _fit_group_baselines(
                    gp,
                    sub,
                    part.subset(part.labelled()),
                    lambdas,
                    gp.lambda_cut,
                    derive_seed(seed, *members),
                    affine,
                ),
            )
        )
    out = {}
    for name in fitted[0][1]:
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


def score(
    prep: Prepared,
    preds: Mapping[str, Mapping[str, np.ndarray]],
    nets: Mapping[str, NetResult],
    cv: Mapping[str, Any],
) -> dict[str, Any]:
    """metrics.json: validation and test errors of every model, the cross-validation (`cv`, from
    `pipeline.calib.crossval.cross_validate`) and the model to deploy it chooses, the chosen networks."""
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
    metrics["networks"] = {
        name: {
            "trial": r.trial,
            "hyperparameters": asdict(NetSetting.of(prep.gp, r.model.config.n_inputs, r.values)),
            "seed": r.seed,
            "best_epoch": r.best_epoch,
            "val_rmse_labelled": r.val_rmse,
            "study": r.study,
            "trials_run": r.trials_run,
            "trials_reused": r.trials_reused,
            "trials_pruned": r.trials_pruned,
            "history": r.history,
        }
        for name, r in nets.items()
    }
    return metrics


def network_info(prep: Prepared, r: NetResult, metrics: Mapping[str, Any], name: str) -> dict[str, Any]:
    n_inputs = r.model.config.n_inputs
    sensors = prep.group.sensors
    return {
        "group": prep.group.name,
        "sensors": list(sensors),
        "input_columns": [c for sensor in sensors for c in input_cols(sensor, n_inputs)],
        "output_columns": [c for sensor in sensors for c in S.wrench_cols(S.FT, sensor)],
        "hyperparameters": metrics["networks"][name]["hyperparameters"],
        "study": r.study,
        "trial": r.trial,
    }


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
