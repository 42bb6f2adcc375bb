"""Cross-validation by whole training logs: every model of a group scored on every fold.

Fold 0 is the train/validation split the Optuna search uses (`pipeline.calib.split.split_logs`); on each
other fold the baselines are fitted again and each network is trained again with its search's best
hyperparameters and seed (the windowed network with its params, on that fold's play model), its epoch chosen
on that fold's validation logs. A model's fold scores are its
validation ``rmse_labelled`` (N and Nm pooled) per fold; the model to deploy is chosen from them
(`pipeline.calib.params.select_by_folds`): the simplest, unless a more complex one's mean is lower by more
than ``train.selection_margin`` and by more than the spread of its per-fold improvements.

Fold 0's network scores are their search's best trial: chosen among trials on that fold, they are slightly
optimistic there; the other folds' are not.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.calib.data import GroupData, group_errors
from pipeline.calib.families.base import Task, Trained
from pipeline.calib.fitting import fit_fold
from pipeline.calib.params import fold_spread, select_by_folds, selection_steps
from pipeline.calib.registry import complexity, patterns
from pipeline.core.progress import ProgressLog

# How far apart a network's fold errors land between two trainings whose inputs differ beyond their last
# bits (a float32 step and more: another simulation or recording of the same experiments), as a fraction:
# up to 2.5 % measured on r_arm_ft's 13-input network. A selection step whose gain lies this close to the
# margin can go either way on such data (on the same data, any machine makes the same choice).
CLOSE = 0.025

if TYPE_CHECKING:
    from pipeline.calib.fit import Prepared


def _fold_predictions(
    prep: Prepared, first: Mapping[str, Trained], k: int, train: GroupData, val: GroupData, ui: ProgressLog
) -> dict[str, np.ndarray]:
    """Predictions (N, S, 6) on fold `k`'s validation samples of every model refitted on its training ones
    (each family from fold 0's models `first`: the networks with their searches' hyperparameters)."""
    task = Task(prep.gp, prep.group, train, val, prep.seed, fold=k, first=first)
    models, _ = fit_fold(task, ui)
    return {name: model.predict(val) for name, model in models.items()}


def cross_validate(
    prep: Prepared,
    val_preds: Mapping[str, np.ndarray],
    first: Mapping[str, Trained],
    margin: float,
    ui: ProgressLog,
) -> dict[str, Any]:
    """The ``cv`` entry of metrics.json: folds (their train/val logs), per-fold scores of every model,
    mean and spread, the rule and the model it chooses. `val_preds`: fold 0's validation predictions of its
    models `first`."""
    group = prep.group
    scores = {m: [group_errors(group, prep.val, p)["rmse_labelled"]] for m, p in val_preds.items()}
    for k, (train, val) in enumerate(prep.folds, start=1):
        preds = _fold_predictions(prep, first, k, train, val, ui)
        for m in scores:
            scores[m].append(group_errors(group, val, preds[m])["rmse_labelled"])
    scores = {m: scores[m] for m in sorted(scores, key=complexity)}
    chosen = select_by_folds(scores, margin)
    steps = selection_steps(scores, margin)
    for step in close_steps(steps, margin):
        ui.line(
            f"{group.name}: {step['model']} against {step['against']}: mean gain {step['gain']:.1%} against "
            f"the {margin:.0%} margin, closer than networks trained on data that differ beyond their last "
            f"bits differ ({CLOSE:.1%}): such data can make the other choice"
        )
    return {
        "folds": prep.split["folds"],
        "scores": scores,
        "mean": {m: float(np.mean(v)) for m, v in scores.items()},
        "spread": {m: fold_spread(v) for m, v in scores.items()},
        "rule": (
            f"simplest model ({' < '.join(patterns())}) unless a more complex one's mean validation "
            f"rmse_labelled over the {len(prep.split['folds'])} folds is lower by more than {margin:.0%} and "
            f"its mean improvement exceeds the spread (std over folds) of its improvements"
        ),
        "chosen": chosen,
        "steps": steps,  # the walk of the rule (`selection_steps`) ...
        "close": [s["model"] for s in close_steps(steps, margin)],  # ... and its steps within CLOSE of it
    }


def close_steps(steps: list[dict[str, Any]], margin: float) -> list[dict[str, Any]]:
    """The steps of the selection whose gain lies within `CLOSE` of the margin."""
    return [s for s in steps if s["gain"] is not None and abs(s["gain"] - margin) < CLOSE]
