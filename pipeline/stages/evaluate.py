"""Stage `evaluate@<group>`: what a researcher reads to decide which calibration of a group goes on the robot.

``ftcal evaluate GROUP MODELS LABELLED OUT [--truth INGESTED]`` reads ``MODELS`` (the train@<group> output:
``predictions.parquet`` of the test samples and ``metrics.json``), the labelled test tables (experiment
type, FT-board gyroscopes, contact sets, foot-pair transforms) and, for simulated logs, the truth tables;
it writes, under the reports directory ``OUT``:

- ``groups/<group>/report.json``: the thesis's tables per sensor (a foot: the pair's sum in the sole frame
  and each part) and model, MSE/MAE/RMSE global, force, torque and per axis, against the labels (where the
  sensor's switch is 1) and, for simulated logs, against the true wrench (labelled samples, and every
  sample); the simulator's ``oracle`` calibration is an extra model (the noise floor); RMSE per experiment
  type; the noise check; the model to deploy; the training's loss curves and MLflow links.
- ``groups/<group>/plots/*.png``: the group's figures; ``plots_data/*/<group>*.csv`` for ``dvc plots``.
- ``metrics/<group>.json``: the few numbers to compare between runs (``dvc metrics show``).

The deployment noise check and the references are described in `pipeline.evaluation.noise` and
`pipeline.evaluation.inputs`. Model to deploy: the group's lowest-validation-error model
(``best_on_validation`` of train) unless noise-flagged, else the next of ``validation_ranking`` that is not.
The page assembling every group is the `report` stage.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from pipeline.core.cliargs import add_params_option
from pipeline.core.errors import DataError

STAGE = "evaluate"


def run(
    params: Any,
    group: str,
    models_dir: str | Path,
    labelled_dir: str | Path,
    out_dir: str | Path,
    truth_dir: str | Path | None = None,
    *,
    smoothed_dir: str | Path | None = None,
    progress: bool | None = None,
) -> Any:
    """Evaluate one group into `out_dir` (module docstring) in one MLflow run ``evaluate@<group>``.

    Returns the `GroupResult` (with its samples).

    Raises:
        ConfigError: `group` is not a group of train.groups.
        DataError: a missing or unusable input directory, table or training output.
    """
    from dataclasses import asdict

    import mlflow

    from pipeline.calib.params import TrainParams
    from pipeline.core.config import stage_section
    from pipeline.core.io import write_json
    from pipeline.core.tracking import stage_run
    from pipeline.evaluation import figures, links, results
    from pipeline.evaluation.answer import answers
    from pipeline.evaluation.params import GROUP_REPORT, GROUPS_DIR, METRICS_DIR, EvaluateParams

    t0 = time.perf_counter()
    cfg = stage_section(params, STAGE, EvaluateParams)
    stage_section(params, "train", TrainParams).group(group)  # a group of params, or ConfigError
    models, labelled, out = Path(models_dir), Path(labelled_dir), Path(out_dir)
    truth = Path(truth_dir) if truth_dir is not None else None
    if not labelled.is_dir():
        raise DataError(f"{labelled}: labelled directory not found")
    if truth is not None and not truth.is_dir():
        raise DataError(f"{truth}: truth directory not found")
    with stage_run(f"{STAGE}@{group}", {STAGE: asdict(cfg), "group": group}) as active:
        smoothed = Path(smoothed_dir) if smoothed_dir is not None else None
        result = _scored(group, models, labelled, out, truth, cfg, progress, smoothed)
        files = figures.write_plot_data(out, result)
        report_path = out / GROUPS_DIR / group / GROUP_REPORT
        write_json(report_path, result.report().to_dict())
        metrics_dir = out / METRICS_DIR / group  # one file (one `dvc metrics` row) per headline
        metrics_dir.mkdir(parents=True, exist_ok=True)
        for old in metrics_dir.glob("*.json"):
            old.unlink()
        for answer in answers(result):
            write_json(metrics_dir / f"{answer.name}.json", answer.metrics_row())
        tags = {"group": group, "recommended": result.recommended or "none"}
        tags["flagged"] = ",".join(result.noise.flagged) or "none"
        if result.train_run:
            tags["train_run"] = result.train_run
        for network, mv in result.model_versions.items():
            tags[f"model.{network}"] = f"{mv['name']}/{mv['version']}"
        mlflow.set_tags(tags)
        mlflow.log_metrics(results.mlflow_metrics(result))
        mlflow.log_metric("seconds", time.perf_counter() - t0)
        links.log_model_metrics(result)
        mlflow.log_artifact(str(report_path))
        if result.figures:
            mlflow.log_artifacts(str(out / GROUPS_DIR / group / "plots"), "plots")
        result.seconds = time.perf_counter() - t0
        result.run_id = active.info.run_id
        result.files = files
    return result


def _scored(
    group: str,
    models: Path,
    labelled: Path,
    out: Path,
    truth: Path | None,
    cfg: Any,
    progress: bool | None,
    smoothed: Path | None = None,
) -> Any:
    """The group's `GroupResult` with its figures written under `out`; a group that train could not
    calibrate (its record says why) gets the result saying so, no score and no figure."""
    from pipeline.calib.exact import not_calibrated
    from pipeline.core.progress import progress_bar
    from pipeline.evaluation import figures, links, results
    from pipeline.evaluation.inputs import load_group
    from pipeline.evaluation.params import TRAIN_METRICS
    from pipeline.export.trained import read_metrics

    record = read_metrics(models) if (models / TRAIN_METRICS).is_file() else {}
    if not_calibrated(record) is not None:
        return results.not_calibrated_result(record)
    with progress_bar(progress) as bar:
        task = bar.add_task(f"evaluate {group}: scoring", total=None)
        inputs = load_group(group, models, labelled, truth, cfg)
        result = results.evaluate_group(inputs, cfg)
        joints = None
        if not inputs.has_truth:  # a recording: where its held-out error comes from
            result.held_out, joints = _held_out(inputs, result, models, labelled, smoothed)
        links.read_train_links(result, inputs.train)
        bar.remove_task(task)
        result.figures = figures.write_group_figures(out, result, cfg, bar)
        if joints is not None:
            result.figures["held_out"] = _plot_held_out(out, result, inputs, joints)
    return result


def _plot_held_out(out: Path, result: Any, inputs: Any, joints: Any) -> dict[str, str]:
    """The held-out residual figure of each sensor of a recorded group; name -> path relative to `out`."""
    from pipeline.calib.params import LS_AFFINE
    from pipeline.evaluation.params import GROUPS_DIR, PLOTS_DIR
    from pipeline.evaluation.residual import plot_held_out

    shown = [m for m in dict.fromkeys([result.recommended, LS_AFFINE]) if m in inputs.models]
    paths = {}
    for name in result.held_out:
        rel = f"{GROUPS_DIR}/{result.group}/{PLOTS_DIR}/{name}_held_out.png"
        plot_held_out(inputs.frame, joints, name, shown, out / rel)
        paths[name] = rel
    return paths


def _held_out(
    inputs: Any, result: Any, models: Path, labelled: Path, smoothed: Path | None
) -> tuple[dict[str, Any], Any]:
    """`pipeline.evaluation.residual.held_out` of a recorded group, with train's linear maps and the joints
    of the smoothed tables (none without `smoothed`); and those joints per test sample."""
    import json

    from pipeline.calib.linear import LinearBaseline
    from pipeline.evaluation import residual

    path = models / "baselines.json"
    entries = json.loads(path.read_text()) if path.is_file() else {}
    baselines = {k: LinearBaseline.from_dict(v) for k, v in entries.items() if "weights" in v}
    joints = residual.read_joints(inputs.frame, smoothed)
    held = residual.held_out(
        inputs.frame,
        joints,
        inputs.names,
        inputs.models,
        result.recommended,
        inputs.train,
        baselines,
        inputs.sensors,
        result.unfaithful,
        residual.read_inertial(labelled),
    )
    return held, joints


def _cmd(args: argparse.Namespace) -> int:
    from pipeline.core.config import load_params
    from pipeline.evaluation.answer import answers
    from pipeline.evaluation.html import fmt

    params = load_params(args.params)
    r = run(params, args.group, args.models, args.labelled, args.out, args.truth, smoothed_dir=args.smoothed)
    for a in answers(r):
        if a.against is None:
            print(f"{a.group}: {a.name} not calibrated: {a.detail}")
            continue
        shown = {"oracle": a.oracle, "floor": a.floor, "ls": a.ls, "raw": a.raw}
        beside = ", ".join(f"{k} {fmt(v)}" for k, v in shown.items() if v is not None)
        answer = f"deploy {a.deployed}, {fmt(a.rmse)} against {a.against} ({beside})"
        print(f"{a.group}/{a.name}: {answer}: {a.verdict}")
    if r.noise.flagged:
        print(f"{r.group}: noisy, not deployed: {', '.join(r.noise.flagged)} ({r.seconds:.0f} s)")
    return 0


def add_cli(subparsers: Any) -> None:
    """Add `ftcal evaluate GROUP MODELS LABELLED OUT [--truth DIR] [--smoothed DIR]`."""
    parser = subparsers.add_parser(
        STAGE,
        help="error tables, figures and noise check of one group's models",
        description=(__doc__ or "").split("\n\n")[0],
    )
    parser.add_argument("group", help="sensor group: a key of train.groups in params.yaml")
    parser.add_argument("models", type=Path, help="the group's model directory (output of train@GROUP)")
    parser.add_argument("labelled", type=Path, help="directory of labelled <log>.parquet tables")
    parser.add_argument("out", type=Path, help="reports directory (groups/GROUP/, metrics/GROUP.json)")
    parser.add_argument(
        "--truth",
        type=Path,
        default=None,
        help="directory of simulated <log>.truth.parquet tables (optional): adds the errors against the "
        "true wrench and the oracle calibration",
    )
    parser.add_argument(
        "--smoothed",
        type=Path,
        default=None,
        help="directory of smoothed <log>.parquet tables (optional): recorded test logs' held-out residual "
        "set against their joints' positions and speeds",
    )
    add_params_option(parser)
    parser.set_defaults(func=_cmd)
