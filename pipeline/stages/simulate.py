"""Stage `simulate`: realistic robot logs with known truth, written as ROS 2 MCAP (thesis 4.1).

For every log in ``simulate.logs``: a true motion fitted to the robot of ``robot.urdf`` (its lengths
derived from the URDF unless params override them), the true wrenches of a "true" robot whose links
have mass and COM errors, and what the robot's sensors make of it: distorted, noisy FT wrenches (the
same hidden distortion in every log), a temperature that drifts with activity, FT-board IMUs, quantised
encoders; messages with jittered stamps, a few dropped or duplicated, delayed. The simulator itself is
the :mod:`pipeline.sim` package; this module runs it and writes the outputs.

Outputs in the output directory (replaced as a whole, atomically): one ``<NN>_<type>_<role>.mcap`` per
log (topics as ``params.topics``; metadata record ``experiment``; truth under ``/sim/...``),
``truth.json`` (the hidden distortions and model errors, for evaluation only), ``summary.json`` (the
motion params used, raw and oracle errors against truth per log and sensor), and ``plots/`` (one log per
experiment type). Everything is logged to an MLflow run.
"""

from __future__ import annotations

import argparse
import shutil
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

from pipeline.core.cliargs import add_params_option

# Relative CPU cost of one robot second of a log, in pole-log seconds: the types whose legs are solved by
# inverse kinematics at every sample cost about five times as much; the plots of a log about 150 more.
_TRACKED_TYPES = frozenset({"balancing", "half_foot", "walking", "standing"})
_TRACKED_COST, _PLOT_COST = 5.0, 150.0


def _cost(job: tuple[int, Any, str, bool]) -> float:
    """Estimated relative CPU cost of a job (index, LogSpec, output dir, plot?), for the workers' order."""
    _, spec, _, plot = job
    per_second = _TRACKED_COST if spec.type in _TRACKED_TYPES else 1.0
    return spec.duration_s * per_second + (_PLOT_COST if plot else 0.0)


def _generate(world: Any, jobs: list[tuple], progress: bool | None, section: str) -> list:
    """Run every job (in forked worker processes, or in this one); results sorted by log name. section: the
    params section of the logs (simulate, deploy), which names a failed log.

    The jobs start most expensive first, so that no core idles at the end while another finishes a long
    log. Each log draws from its own random streams: the results do not depend on the order.
    """
    from functools import partial

    from pipeline.core.parallel import forked_map
    from pipeline.core.progress import progress_bar
    from pipeline.sim.experiment import simulate_log

    if any(job[3] for job in jobs):
        import pipeline.sim.plots  # noqa: F401  (matplotlib imported once, before the workers fork)

    tasks = [partial(simulate_log, world, index, spec, Path(out), plot) for index, spec, out, plot in jobs]
    results = []
    with progress_bar(progress) as bar:
        task = bar.add_task("simulate (robot s)", total=sum(job[1].duration_s for job in jobs))
        labels = [f"{section}.logs[{index}] ({spec.name(index)})" for index, spec, _, _ in jobs]
        done = forked_map(tasks, world.sim.workers or None, [_cost(job) for job in jobs], labels)
        for result, job in zip(done, jobs, strict=True):
            results.append(result)
            bar.advance(task, job[1].duration_s)
    return sorted(results, key=lambda r: r.name)


def _write_outputs(world: Any, results: list, wall: float, tmp: Path) -> dict[str, float]:
    """truth.json and summary.json into `tmp`; returns the run's headline metrics."""
    from pipeline.core.io import write_json

    robot_seconds = sum(spec.duration_s for spec in world.sim.logs)
    metrics = {
        "robot_seconds": robot_seconds,
        "wall_seconds": wall,
        "sim_seconds_per_wall_second": robot_seconds / wall,
        "messages": sum(r.messages for r in results),
        "logs": len(results),
    }
    truth = {
        "note": "hidden simulator truth: for evaluation only, never a training input",
        "distortions": {s: d.to_dict() for s, d in world.distortions.items()},
        "model_errors": world.model_errors,
    }
    write_json(tmp / "truth.json", truth)
    # deterministic: the same params give the same bytes (wall-clock times go to MLflow only, so that a
    # re-run of this stage does not make DVC re-run the stages that read its output)
    summary = {
        "robot_seconds": robot_seconds,
        "motion": asdict(world.motions.p),  # the motion params used (URDF-derived where params are null)
        "geometry": asdict(world.motions.geometry),
        "logs": [{k: v for k, v in asdict(r).items() if k != "seconds"} for r in results],
    }
    write_json(tmp / "summary.json", summary)
    return metrics


def _log_mlflow(world: Any, results: list, metrics: dict[str, float], tmp: Path) -> None:
    import mlflow

    mlflow.log_params({f"derived.motion.{k}": v for k, v in asdict(world.motions.p).items()})
    mlflow.log_metrics(metrics)
    for r in results:
        mlflow.log_metric(f"{r.name}.seconds", r.seconds)
        for s, e in r.raw_rmse.items():
            mlflow.log_metrics(
                {
                    f"{r.name}.{s}.raw_rmse_force": e["force"],
                    f"{r.name}.{s}.raw_rmse_torque": e["torque"],
                    f"{r.name}.{s}.oracle_rmse_force": r.oracle_rmse[s]["force"],
                }
            )
    mlflow.log_artifact(str(tmp / "summary.json"))
    mlflow.log_artifact(str(tmp / "truth.json"))
    if (tmp / "plots").is_dir():
        mlflow.log_artifacts(str(tmp / "plots"), artifact_path="plots")


def _swap_in(tmp: Path, out_dir: Path) -> None:
    """Replace `out_dir` by the complete `tmp` (the old outputs stay until the new ones are whole)."""
    if out_dir.exists():
        old = out_dir.with_name(out_dir.name + ".old")
        shutil.rmtree(old, ignore_errors=True)
        out_dir.rename(old)
        tmp.rename(out_dir)
        shutil.rmtree(old, ignore_errors=True)
    else:
        tmp.rename(out_dir)


def recorded_source(params: Any, sim_dir: str | Path) -> str | None:
    """``ingest.source`` when it is not `sim_dir` (the simulated default data's folder): the pipeline then
    reads recorded logs only and nothing is simulated. None when ingest reads `sim_dir`.

    ingest.source is taken from the repo root (where DVC runs the stages), `sim_dir` from the working
    directory (a command-line path)."""
    from pipeline.core.config import repo_root, stage_section
    from pipeline.logs.params import IngestParams

    source = stage_section(params, "ingest", IngestParams).source
    path = Path(source).expanduser()
    path = path if path.is_absolute() else repo_root() / path
    return None if path.resolve() == Path(sim_dir).expanduser().resolve() else source


def leave_unsimulated(out_dir: Path, source: str, sim_dir: str | Path, deploy: str | None) -> str:
    """Replace `out_dir` by an empty folder holding only the note `NOT_SIMULATED` (why nothing is simulated:
    ingest reads `source`, recorded logs, not `sim_dir`); log the step to MLflow; return the note's line.
    Neither the URDF nor the simulator is loaded."""
    import mlflow

    from pipeline.core.io import atomic_dir
    from pipeline.core.tracking import stage_run
    from pipeline.logs.schema import NOT_SIMULATED

    note = f"nothing simulated: ingest.source is {source}, not {sim_dir} (recorded logs only)"
    logged = {"ingest": {"source": source}, "simulated_data": str(sim_dir), "variant": deploy or "default"}
    with stage_run("simulate", logged):
        with atomic_dir(out_dir) as tmp:
            (tmp / NOT_SIMULATED).write_text(
                f"{note}\nSet ingest.source: {sim_dir} in params.yaml to simulate the default data.\n",
                encoding="utf-8",
            )
        mlflow.set_tag("nothing_simulated", note)
        mlflow.log_metric("logs", 0)
    return note


def run(params: Any, out_dir: Path, progress: bool | None = None, deploy: str | None = None) -> list:
    """Simulate every configured log into `out_dir` (replaced atomically as a whole) and log to MLflow.

    params: the loaded :class:`pipeline.core.config.Params`. deploy: None for the logs of ``simulate``, or
    ``later`` / ``drifted`` for the deployment logs of section ``deploy``. Returns the per-log
    :class:`pipeline.sim.experiment.LogResult` list, sorted by log name.
    """
    from pipeline.core.tracking import stage_run
    from pipeline.sim.params import simulate_params
    from pipeline.sim.world import build_world

    if deploy is None:
        sim = simulate_params(params)
    else:
        from pipeline.deploy.params import deployment_simulation

        sim = deployment_simulation(params, deploy)
    world = build_world(params, sim)  # validates robot, foot pairs and motion params before any work
    out_dir = Path(out_dir)
    tmp = out_dir.with_name(out_dir.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    seen: set[str] = set()
    jobs = []
    for i, spec in enumerate(sim.logs):
        jobs.append((i, spec, str(tmp), sim.plots and spec.type not in seen))
        seen.add(spec.type)
    logged = {"seed": params.seed, "robot": asdict(params.robot), "simulate": params.raw["simulate"]}
    if deploy is not None:
        logged.update(deploy=params.raw["deploy"], variant=deploy)
    with stage_run("simulate", logged):
        start = time.perf_counter()
        results = _generate(world, jobs, progress, "simulate" if deploy is None else "deploy")
        metrics = _write_outputs(world, results, time.perf_counter() - start, tmp)
        _log_mlflow(world, results, metrics, tmp)
    _swap_in(tmp, out_dir)
    return results


def _cmd(args: argparse.Namespace) -> int:
    from pipeline.core.config import load_params

    params = load_params(args.params)
    source = recorded_source(params, args.if_ingested) if args.if_ingested is not None else None
    if source is not None:
        note = leave_unsimulated(Path(args.out_dir), source, args.if_ingested, args.deploy)
        print(f"simulate: {args.out_dir}: {note}")
        return 0
    progress = False if args.quiet else None
    results = run(params, Path(args.out_dir), progress=progress, deploy=args.deploy)
    total = sum(r.samples for r in results)
    print(f"simulate: {len(results)} logs, {total} samples -> {args.out_dir}")
    return 0


def add_cli(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate", help="generate simulated MCAP logs with known truth", description=__doc__.splitlines()[0]
    )
    p.add_argument("out_dir", help="output directory (e.g. data/sim)")
    add_params_option(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--deploy",
        choices=("later", "drifted"),
        default=None,
        help="simulate the deployment logs of params section deploy (a later day, or the drift check's)",
    )
    p.add_argument(
        "--if-ingested",
        default=None,
        metavar="SIM_DIR",
        help="simulate only if ingest.source is SIM_DIR (the simulated default data, e.g. data/sim); with "
        "recorded logs (any other ingest.source) leave OUT an empty folder with a note and simulate nothing",
    )
    p.set_defaults(func=_cmd)


__all__ = ["leave_unsimulated", "recorded_source", "run"]
