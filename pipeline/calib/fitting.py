"""Every family's models of a group fitted on one fold, in the order the families start from each other.

The families (`pipeline.calib.registry.families`) that train a model for the group are fitted in batches:
first the ones fitted in the training process (``inline``: the raw wrench, the affine map the networks
start from), then every family whose ``after`` families are fitted, their jobs in forked processes side by
side (`pipeline.core.parallel.forked_map`: the same numbers as one after the other), and so on (the windowed
network after the play model).
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import TYPE_CHECKING

from pipeline.calib.families.base import Family, Task, Trained
from pipeline.calib.registry import AFFINE, by_key, families
from pipeline.core.parallel import forked_map

if TYPE_CHECKING:
    from pipeline.calib.data import Group, GroupData
    from pipeline.calib.linear import LinearBaseline
    from pipeline.calib.params import GroupParams
    from pipeline.core.progress import ProgressLog


def training(gp: GroupParams, group: Group) -> list[Family]:
    """The families that train at least one model for the group, simplest first."""
    return [f for f in families() if f.names(gp, group)]


def fit_fold(task: Task, ui: ProgressLog) -> tuple[dict[str, Trained], dict[str, float]]:
    """(model name -> fitted model, in the families' order; job -> seconds) of every family training for
    `task`'s group, on `task`'s fold (module docstring)."""
    pending = training(task.gp, task.group)
    keys = {f.key for f in pending}
    fitted: dict[str, Trained] = {}
    seconds: dict[str, float] = {}
    done: set[str] = set()
    while pending:
        ready = [f for f in pending if all(a in done or a not in keys for a in f.after)]
        if not ready:
            raise ValueError(f"{task.group.name}: families {[f.key for f in pending]} wait for each other")
        batch = [f for f in ready if f.inline] or ready
        current = replace(task, fitted=dict(fitted))
        jobs = [(f, job) for f in batch for job in f.jobs(current)]
        run = [lambda job=job: _timed(job.run) for _, job in jobs]
        fold = f" fold {task.fold + 1}" if task.fold else ""
        labels = [f"{task.group.name}: {job.what or job.label}{fold}" for _, job in jobs]
        if batch[0].inline:
            results = [r() for r in run]
        else:
            results = list(forked_map(run, costs=[job.cost for _, job in jobs], labels=labels))
        for (family, job), (models, secs) in zip(jobs, results, strict=True):
            seconds[job.label] = secs
            for name, model in models.items():
                fitted[name] = model
                if (line := family.line(task.group, task.fold, model)) is not None:
                    ui.line(line)
        done |= {f.key for f in batch}
        pending = [f for f in pending if f.key not in done]
    order = [name for f in training(task.gp, task.group) for name in f.names(task.gp, task.group)]
    return {name: fitted[name] for name in order if name in fitted}, seconds


def _timed(run) -> tuple[dict[str, Trained], float]:
    t = time.perf_counter()
    return run(), time.perf_counter() - t


def fit_affine(gp: GroupParams, group: Group, train: GroupData, seed: int) -> LinearBaseline:
    """The affine map alone (`pipeline.calib.families.affine`): the map the group's networks correct."""
    from pipeline.calib.families.closed_form import fit_closed_form

    return fit_closed_form(gp, group, train, seed, [AFFINE], by_key(AFFINE))[AFFINE]


def fit_plain_affine(gp: GroupParams, group: Group, train: GroupData, seed: int) -> LinearBaseline:
    """The plain least-squares affine map (`fit_affine` without the virtual pushes), named LS_AFFINE: the
    in-situ reference any lab computes from its labels, scored beside the models of recorded logs."""
    from pipeline.calib.params import LS_AFFINE

    return replace(fit_affine(replace(gp, lambda_push=0.0), group, train, seed), name=LS_AFFINE)
