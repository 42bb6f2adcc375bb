"""`ftcal rezero LOG [LOG ...] [--models DIR]`: re-zero the exported calibration, without retraining.

A lab's sensors' offsets move from day to day (mounting, temperature, a knock). From a few seconds of a
log in which the robot stood still where labels are exact (on the pole, on one foot, on both feet: any
declared or detected contacts), this estimates each sensor's raw-side offset change for the export's
calibration (`pipeline.deploy.rezero`: the calibration of ``raw - offset`` matches the exact labels) with
its uncertainty, and writes ``offsets.json`` beside the export (`pipeline.export.offsets`: which export,
when, from which log and stretch, how still the robot was, per sensor what the stretch determined, how the
offsets depend on the log's still poses). `ftcal calibrate` and the exported graphs' ``offsets`` input
use it: a robot's loop reads it at start-up.

Each LOG (MCAP, robot-logger ``.mat`` or dataDumper run, with its sidecar) is ingested, smoothed and
labelled as training logs are; the stretch is its first still one (``deploy.rezero``), or ``--start``;
several logs are solved together. Standing on both feet the legs and feet have exact labels only for
their sums (docs/labels.md): what a stretch cannot determine is said per sensor, and left as delivered.
Refused in one line: a log of another robot or another sensor board (serials), a stretch where the robot
moved, or without an exact label of the sensors asked for.
"""

from __future__ import annotations

import argparse
import sys
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from pipeline.core.cliargs import add_models_option, add_params_option, models_dir
from pipeline.core.errors import DataError

COMMAND = "rezero"


def _prepare(params: Any, robot: Any, log: Path, work: Path) -> Any:
    """The log ingested, smoothed and labelled into `work` (`pipeline.deploy.prepare`)."""
    from pipeline.deploy.prepare import prepare_logs

    if not log.exists():
        raise DataError(f"{log}: log not found")
    (prepared,) = prepare_logs(params, robot, [log], log.parent, work / log.stem)
    return prepared


def _sensors(deployment: Any, tables: list[Any], asked: list[str] | None) -> list[str]:
    """The sensors to re-zero: `asked` (each modelled by the export), else every modelled sensor whose raw
    wrench the logs carry."""
    import numpy as np

    from pipeline.logs import schema as S

    modelled = deployment.sensors()
    if asked:
        unknown = [s for s in asked if s not in modelled]
        if unknown:
            raise DataError(
                f"--sensors {unknown[0]}: not a sensor of {deployment.path} ({', '.join(modelled)})"
            )
        return list(asked)

    def carried(sensor: str) -> bool:
        cols = S.wrench_cols(S.FT, sensor)
        return all(
            all(c in t.labelled for c in cols) and np.isfinite(t.labelled[cols]).any().all() for t in tables
        )

    return [s for s in modelled if carried(s)]


def run(
    params: Any, logs: list[str | Path], models: str | Path, *, start_s: float | None = None,
    duration_s: float | None = None, sensors: list[str] | None = None, out: str | Path | None = None,
    urdf: str | Path | None = None,
) -> dict[str, Any]:  # fmt: skip
    """Re-zero the export in `models` from `logs` (module docstring); write and return the offsets file's
    content (`out`: its path, default ``<models>/offsets.json``; `duration_s` default
    ``deploy.rezero.duration_s``; `urdf`: the robot model the stretch is labelled with, as the training
    labels were (``models/identified/labels.urdf``), default ``robot.urdf``)."""
    import tempfile
    from dataclasses import replace

    from pipeline.deploy.params import deploy_params
    from pipeline.deploy.prepare import load_nominal_robot, robot_cuts
    from pipeline.deploy.rezeroing import log_tables, pick, pose_dependence, pose_spread, record, rezero_logs
    from pipeline.export.identity import check_serials
    from pipeline.export.manifest import sha256_file
    from pipeline.export.offsets import FILE, document
    from pipeline.export.runtime import Deployment, check_robot

    cfg = deploy_params(params).rezero
    if duration_s is not None:
        if not 0 < duration_s <= 3600:
            raise DataError(f"--duration {duration_s:g}: must be in (0, 3600] s")
        cfg = replace(cfg, duration_s=duration_s, min_s=min(cfg.min_s, duration_s))
    deployment = Deployment.load(models, offsets=False)
    robot = load_nominal_robot(params, urdf)
    _, _, cuts = robot_cuts(params, robot)
    warnings, tables, picked = [], [], []
    with tempfile.TemporaryDirectory(prefix="ftcal-rezero-") as work:
        for log in map(Path, logs):
            prepared = _prepare(params, robot, log, Path(work))
            check_robot(deployment, {"experiment": prepared.experiment}, log)
            warnings += check_serials(deployment.serials(), prepared.experiment, log, deployment.path)
            tables.append(log_tables(str(log), prepared.labelled, prepared.smoothed, robot, cfg))
            picked.append(pick(tables[-1], cfg, start_s))
        chosen = _sensors(deployment, tables, sensors)
        poses = [pose_dependence(deployment, t, chosen, cuts, cfg) for t in tables]
        try:
            result = rezero_logs(deployment, list(zip(tables, picked, strict=True)), chosen, cuts, cfg, poses)
        except DataError:
            if not sensors:
                raise
            raise DataError(_unreached(chosen, picked, cuts)) from None
        unreached = [s for s in chosen if result.status(s) == "none"]
        if sensors and unreached:
            raise DataError(_unreached(unreached, picked, cuts))
    serials, spread = deployment.serials(), pose_spread(poses)
    entries = {
        s: e | {"pose_spread": spread.get(s), "serial": serials.get(s)} for s, e in result.record().items()
    }
    doc = document(
        result.rezeroed().values, entries, deployment.manifest_sha256, robot=deployment.robot,
        created=datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        logs=[{"path": str(p), "sha256": sha256_file(Path(p)) if Path(p).is_file() else None} for p in logs],
        prior={"force_n": cfg.prior_force_n, "torque_nm": cfg.prior_torque_nm},
        significance={"label_mass_rel": cfg.label_mass_rel, "label_com_m": cfg.label_com_m,
                      "significance": cfg.significance},
        **record(result, picked, {"logs": poses}),
    )  # fmt: skip
    from pipeline.core.io import write_json

    target = Path(out) if out is not None else Path(models) / FILE
    write_json(target, doc)
    fragment = _rezero_wbd(deployment.manifest, target.parent, result.rezeroed().values)
    return doc | {"written": str(target), "wholebodydynamics": fragment, "warnings": warnings}


def _rezero_wbd(doc: dict[str, Any], out: Path, deltas: dict[str, Any]) -> str | None:
    """The wholeBodyDynamics fragment (`pipeline.export.wbd`) of the export whose manifest is `doc`, with
    each re-zeroed sensor's FT_OFFSET moved by its offset change (N, Nm), written into `out` beside the
    offsets file: its path (None: the export has no fragment)."""
    from pipeline.core.io import write_text
    from pipeline.export import wbd

    entry = doc.get(wbd.KEY) or {}
    if not entry.get("sensors"):
        return None
    sensors = {s: wbd.rezeroed(t, deltas[s]) if s in deltas else t for s, t in entry["sensors"].items()}
    note = wbd.about(str(doc.get("robot", "?")), entry.get("models") or {})
    write_text(out / wbd.FILE, wbd.fragment(sensors, f"{note} FT_OFFSET re-zeroed by ftcal rezero."))
    return str(out / wbd.FILE)


def _unreached(sensors: list[str], picked: list[Any], cuts: list[Any]) -> str:
    """The refusal when sensors asked for have no exact label in the stretches (nor any sum of them)."""
    from pipeline.deploy.rezeroing import stretch_name

    sums = sorted({c.label for c in cuts if set(sensors) & set(c.sensors)})
    hint = f"; their sums with other sensors ({', '.join(sums)}) need those re-zeroed too" if sums else ""
    where = ", ".join(stretch_name(p) for p in picked)
    return f"{where}: no exact label of {', '.join(sensors)} there{hint}, or re-zero from another stance"


def _print(doc: dict[str, Any]) -> None:
    for warning in doc["warnings"]:
        print(f"ftcal: warning: {warning}", file=sys.stderr)
    for stretch in doc["stretches"]:
        gyro = "n/a" if stretch["gyro_rad_s"] is None else f"{stretch['gyro_rad_s']:.3f}"
        print(
            f"{stretch['name']}: still (fastest joint {stretch['joint']} {stretch['joint_rad_s']:.4f} rad/s, "
            f"FT boards {gyro} rad/s)"
        )
    for sensor, e in doc["status"].items():
        entry = doc["sensors"].get(sensor)
        offset = " ".join(f"{v:+.2f}" for v in entry["offset"]) if entry else "-"
        std = " ".join(f"{v:.2f}" for v in entry["std"]) if entry else "-"
        what = {"all": "re-zeroed", "sums": "through sums only", "none": "not re-zeroed (no exact label)"}[e]
        spread = (entry or {}).get("pose_spread")
        over = f"; over the poses {' '.join(f'{v:.2f}' for v in spread)}" if spread else ""
        print(f"  {sensor}: {what}; offset {offset} (N, Nm) +- {std} (noise){over}")
        if entry and entry["offset"] != entry["estimate"]:
            estimate, floor = (" ".join(f"{v:+.2f}" for v in entry[k]) for k in ("estimate", "floor"))
            print(f"    estimated {estimate}, floor {floor} (labels' error, pose spread): not applied within "
                  "deploy.rezero.significance x the noise and floor, shrunk up to twice it")  # fmt: skip
    for log in doc["pose_dependence"]["logs"]:
        for sensor, p in log["sensors"].items():
            if p["depends"]:
                print(f"  {sensor}: depends on the pose ({len(log['poses'])} poses of {log['log']}: spread "
                      f"{p['ratio']:.1f} x the noise)")  # fmt: skip
    print(f"{doc['written']}: offsets of {len(doc['sensors'])} sensor(s)")
    if doc.get("wholebodydynamics"):
        print(f"{doc['wholebodydynamics']}: wholeBodyDynamics configuration with the re-zeroed FT_OFFSET")


def _cmd(args: argparse.Namespace) -> int:
    from pipeline.core.config import load_params

    params = load_params(args.params)
    models = models_dir(args.models)
    doc = run(
        params, args.logs, models, start_s=args.start, duration_s=args.duration, sensors=args.sensors,
        out=args.out, urdf=args.urdf,
    )  # fmt: skip
    _print(doc)
    return 0


def add_cli(subparsers: Any) -> None:
    """Add `ftcal rezero LOG [LOG ...] [--models DIR] [--start S] [--sensors S ...] [--out FILE]`."""
    parser = subparsers.add_parser(
        COMMAND, help="re-zero the exported calibration from a still stretch (no retraining)",
        description=(__doc__ or "").split("\n\n")[0],
    )  # fmt: skip
    parser.add_argument("logs", type=Path, nargs="+", metavar="LOG", help="log(s) with a still stretch")
    add_models_option(parser)
    parser.add_argument(
        "--start", type=float, default=None, metavar="S",
        help="start of the stretch, s of the log's time (default: its first still stretch); "
        "deploy.rezero.duration_s long",
    )  # fmt: skip
    parser.add_argument(
        "--duration", type=float, default=None, metavar="S",
        help="length of the stretch, s (default: deploy.rezero.duration_s)",
    )  # fmt: skip
    parser.add_argument("--sensors", nargs="+", default=None, help="re-zero these sensors only")
    parser.add_argument("--out", type=Path, default=None, help="offsets file (default: DIR/offsets.json)")
    parser.add_argument(
        "--urdf", type=Path, default=None,
        help="the robot model to label the stretch with (models/identified/labels.urdf, as the training "
        "labels), default robot.urdf",
    )  # fmt: skip
    add_params_option(parser)
    parser.set_defaults(func=_cmd)
