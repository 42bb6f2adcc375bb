"""Stage `train@<group>`: baselines and neural networks for one sensor group (thesis chapter 5).

``ftcal train GROUP LABELLED_DIR OUT_DIR`` reads the labelled tables (`pipeline.logs.schema`, "Labelled
table"), splits them by whole logs, fits the baselines, trains the 7- and 13-input networks with an
Optuna search, scores every model and writes ``OUT_DIR``:

- ``metrics.json``: per model (raw, affine, poly1-4, play, arx, nn7, nn13, win: `pipeline.calib.registry`),
  validation and test errors against the labels (MSE/MAE/RMSE global, force, torque, per axis; per sensor
  and, for a foot, of the sum in the sole frame; a group of several sensors: also each cut set's sum),
  ``cv``: every model's validation error on each cross-validation fold, their mean and spread, and
  ``best_on_validation``: the model to deploy, the simplest (raw < offset < affine < poly < play < arx < nn7 <
  nn13 < win) unless a more complex one's mean fold error is lower by more than ``train.selection_margin``
  and by more than the spread of its per-fold improvements (`pipeline.calib.crossval`); ``windowed``: the
  windowed network's window, best epoch and history.
- ``nn7.json`` + ``nn7.pt``, ``nn13.json`` + ``nn13.pt``: the best networks (`calib.models.load_model`
  rebuilds them from the JSON and a weights-only state dict; normalisation constants are in the weights).
- ``baselines.json``: the fitted affine, polynomial and play coefficients (the play model: memory, its
  state over each log's readings in time order, `pipeline.calib.linear`).
- ``win.json``: the windowed network (`pipeline.calib.window.WindowModel.from_dict`: the play model it
  corrects, its windows and its networks' weights), where the group trains one
  (``window_time_constants_s``).
- ``predictions.parquet``: the test samples, ``log``, ``stamp_ns``, ``time_s``, the group's labels and
  switches, and ``pred.<model>.<sensor or pair>.<axis>`` for every model (for `evaluate`).

Split: logs whose ``ftcal.experiment`` metadata says ``role: test`` are the test set; ``train.val_logs``
training logs are held out as validation, whole logs, chosen by a seeded draw that takes at most one log
per experiment kind (type, foot, part) and never a kind's last training log (the same for every group).
Models are fitted on the remaining training logs only; validation chooses epochs and Optuna trials. That
split is fold 0 of a cross-validation by whole logs (``train.folds``): fold k holds out the k-th next log of
the same kinds, refits the baselines and retrains each network with its search's best hyperparameters; the
folds' scores choose the model to deploy. The deployed networks are fold 0's.

Samples: a sample is used when every input stream of the group's sensors is ok (wrench, temperature, IMU:
the same samples for every model); training keeps those with at least one switch set (the others
contribute nothing to the loss). Errors are computed where the label is exact: a sensor's where its switch
is 1, a foot's sum where ``sw.<pair>`` is 1. ``rmse_labelled`` pools the squared errors of all of a group's
exact labels (sensor parts and sum) and decides validation; ``rmse`` is the headline (the sensor's, or the
foot's sum, as the thesis reports).

Optuna: one study per network size, stored in a journal file under ``--studies`` (or, with ``train.storage``
or ``$FTCAL_OPTUNA_STORAGE``, in a database shared with ``ftcal worker GROUP`` processes:
`pipeline.calib.studies`) and named after a hash of everything that determines its result (group params
except n_trials, seed, validation logs, data, this code): a rerun after an interruption resumes it,
a rerun with more trials extends it. Trial k is seeded from (seed, group, inputs, k) and its sampler is a TPE
sampler seeded the same way; the first trial is the group's own params (the thesis's defaults), and a trial
whose validation error lags the earlier trials' median by more than ``prune_margin`` is pruned
(`pipeline.calib.pruning`): a search is reproducible whether or not it was resumed, and whether one process
ran it or several (`pipeline.calib.search`). Every trial is a nested MLflow
run of the stage's run; the best networks are logged with `mlflow.pytorch.log_model` in MLflow's ``pt2``
format (`torch.export`, loadable without unpickling) and registered as ``ftcal-<group>-<7|13>``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from pipeline.core.cliargs import add_params_option

STAGE = "train"
STUDIES_DIR = ".optuna"  # default --studies parent, at the repo root (git-ignored)


def train_group(
    params: Any,
    group_name: str,
    in_dir: str | Path,
    out_dir: str | Path,
    studies: str | Path | None = None,
    *,
    progress: bool | None = None,
) -> Any:
    """Run the stage for one group (module docstring); returns the `TrainResult`.

    `studies` defaults to ``.optuna/<group>`` at the repo root.
    """
    from pipeline.calib.run import train_group as run_group
    from pipeline.core.config import repo_root

    studies = Path(studies) if studies is not None else repo_root() / STUDIES_DIR / group_name
    return run_group(params, group_name, in_dir, out_dir, studies, progress=progress)


def _cmd(args: argparse.Namespace) -> int:
    from pipeline.calib.exact import LEFT_OUT, NOT_CALIBRATED_TEXT, left_out_text, not_calibrated
    from pipeline.core.config import load_params

    params = load_params(args.params)
    result = train_group(params, args.group, args.inputs, args.out, args.studies)
    m = result.metrics
    if (why := not_calibrated(m)) is not None:  # the other groups go on: a warning, not an error
        print(f"ftcal: warning: {result.group}: {NOT_CALIBRATED_TEXT}: {why}", file=sys.stderr)
        return 0
    test = m["test"]
    head = " + ".join(m.get("headlines") or [m["headline"]])
    summary = ", ".join(f"{name} {test[name]['rmse']:.3g}" for name in test)
    left = f"; left out: {left_out_text(m[LEFT_OUT])}" if m.get(LEFT_OUT) else ""
    print(
        f"{result.group}: test RMSE of {head} (N, Nm pooled): {summary}; "
        f"chosen on validation: {m['best_on_validation']} ({result.seconds:.0f} s){left}"
    )
    for note in m.get("notes") or []:  # e.g. a 13-input network refused: a board's IMU failed its check
        print(f"ftcal: warning: {note}", file=sys.stderr)
    return 0


def add_cli(subparsers: Any) -> None:
    """Add `ftcal train GROUP IN OUT`."""
    parser = subparsers.add_parser(
        STAGE,
        help="baselines and neural networks of one sensor group",
        description=(__doc__ or "").split("\n\n")[0],
    )
    parser.add_argument("group", help="sensor group: a key of train.groups in params.yaml")
    parser.add_argument("inputs", type=Path, metavar="IN", help="directory of labelled <log>.parquet tables")
    parser.add_argument("out", type=Path, help="output directory of the group's models and metrics")
    parser.add_argument(
        "--studies",
        type=Path,
        default=None,
        metavar="DIR",
        help=f"directory of the group's Optuna journal (default: {STUDIES_DIR}/GROUP at the repo root; "
        "unused with train.storage); a rerun with the same inputs resumes from it",
    )
    add_params_option(parser)
    parser.set_defaults(func=_cmd)
