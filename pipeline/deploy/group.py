"""One sensor group's deployment tests on one day: every test that is per group, and its figures.

A test is a function of the group on the day (`GroupDay`: its sensors, its trained models, its export, the
params) and one of the day's logs, registered in `DAY_TESTS` under the experiment type of the log it runs
on: Test A on a standing-still log, Test B on a walking log, Test C on a pushed pole log. Each returns its
result (JSON-able; empty: nothing of this group to test) and the figures it drew. A new per-group test is
one more entry; the deployment page and verdict (`pipeline.deploy.verdict`) gather the groups' results.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.deploy.prepare import DeployLog
from pipeline.export.offsets import Offsets
from pipeline.logs import schema as S


@dataclass
class GroupDay:
    """One sensor group on one deployment day: what each of its tests reads. Figures go to
    ``figures/<day>_<name>.png``."""

    group: str
    sensors: list[str]
    models: Path  # the group's train output (models/<group>): every trained model, for Test A
    exported: Path  # the group's export directory: the deployed calibration, run causally on the logs
    deployed: str  # the exported model's name
    params: Any
    dp: Any  # DeployParams
    cfg: Any  # EvaluateParams
    robot: Any  # the nominal RobotModel
    day: str
    figures: Path
    excitation: Mapping[str, Any] | None = None  # train's metrics.json ``excitation`` (None: not recorded)
    offsets: Offsets = field(default_factory=Offsets)  # a re-zeroing's (none: the export as delivered)
    variant: str = ""  # "" as delivered, REZEROED: the tests after re-zeroing (Test A: the delivered one's)
    # init=False: `dataclasses.replace` (a day's re-zeroed variant) starts with an empty cache of its own
    _calibrated: dict[str, dict[str, np.ndarray]] = field(default_factory=dict, repr=False, init=False)

    def calibrated(self, log: DeployLog, table: Any) -> dict[str, np.ndarray]:
        """Sensor -> (N, 6) calibrated wrench of the group's sensors at the table's stamps (per log, once)."""
        from pipeline.deploy.models import calibrated_wrenches

        if log.name not in self._calibrated:
            topics = self.params.topics
            wrenches = calibrated_wrenches(self.exported, log.source, table, topics, self.offsets)
            self._calibrated[log.name] = {s: w for s, w in wrenches.items() if s in self.sensors}
        return self._calibrated[log.name]

    def figure(self, name: str) -> Path:
        return self.figures / f"{self.day}_{self.variant + '_' if self.variant else ''}{name}.png"


TestResult = tuple[dict[str, Any], dict[str, str]]  # (result, figure name -> file name)


def a_noise(ctx: GroupDay, log: DeployLog) -> TestResult:
    """Test A: every trained model's output noise standing still, against raw."""
    from pipeline.deploy.checks import standing_noise

    return standing_noise(log, ctx.models, ctx.cfg, ctx.deployed), {}


def b_walking(ctx: GroupDay, log: DeployLog) -> TestResult:
    """Test B: error tables of the calibrated sensors and foot sums while walking; the fz figure of the
    group's leg sensors (else of its sensors)."""
    import pandas as pd

    from pipeline.deploy.checks import walking_errors
    from pipeline.deploy.page import plot_walking

    table = pd.read_parquet(log.labelled)
    calibrated = ctx.calibrated(log, table)
    if not calibrated:
        return {}, {}
    result = walking_errors(log, ctx.robot, ctx.params, calibrated, _affine_fallback(ctx, table))
    truth = pd.read_parquet(log.truth) if log.truth is not None else None
    shown = [s for s in ctx.dp.torque_limbs if s in calibrated] or sorted(calibrated)
    plot_walking(table, truth, calibrated, shown, ctx.figure("walking"))
    return result, {"walking": ctx.figure("walking").name}


def _affine_fallback(ctx: GroupDay, table: Any) -> dict[str, np.ndarray]:
    """Sensor -> (N, 6) the group's affine map (what wholeBodyDynamics runs, `pipeline.export.wbd`) on the
    table's raw inputs less the day's offsets, N and Nm; {} if the group has none."""
    from pipeline.core.errors import DataError
    from pipeline.export.trained import read_group

    try:
        affine = read_group(ctx.models, "affine", ctx.group)
    except DataError:
        return {}
    x = table[affine.input_columns].to_numpy(np.float64, copy=True)
    for s, sensor in enumerate(affine.sensors):
        if sensor in ctx.offsets.values:
            x[:, s * affine.n_inputs : s * affine.n_inputs + 6] -= ctx.offsets.values[sensor]
    y = affine.reference(x)
    return {sensor: y[:, 6 * s : 6 * s + 6] for s, sensor in enumerate(affine.sensors)}


def c_torques(ctx: GroupDay, log: DeployLog) -> TestResult:
    """Test C: leg joint torques from the group's leg sensors, raw and calibrated, during the pushes."""
    import pandas as pd

    from pipeline.deploy.checks import push_torques
    from pipeline.deploy.page import plot_torques

    calibrated = ctx.calibrated(log, pd.read_parquet(log.labelled))
    if not any(s in calibrated for s in ctx.dp.torque_limbs):
        return {}, {}
    result, series = push_torques(log, ctx.robot, ctx.params, ctx.dp, calibrated)
    if not result:
        return {}, {}
    name = ctx.dp.figure_joint
    plot_torques(series, name, ctx.figure(name))
    return result, {"torques": ctx.figure(name).name}


def d_interaction(ctx: GroupDay, log: DeployLog) -> TestResult:
    """Test D: how the deployed calibration reports the pushes and loads at its sensors' sites (simulated
    logs: it needs their true share of each wrench); how far the log lies outside the training excitation."""
    import pandas as pd

    from pipeline.deploy.interaction import interaction_test, load_mask, outside_during, plot_interaction

    if log.truth is None:
        return {}, {}
    table = pd.read_parquet(log.labelled)
    truth = table[[S.STAMP]].merge(pd.read_parquet(log.truth), on=S.STAMP, how="left")
    calibrated = ctx.calibrated(log, table)
    loads = load_mask(table[S.TIME].to_numpy(np.float64), ctx.robot, ctx.params, ctx.dp)
    result = interaction_test(table, truth, calibrated, loads, ctx.dp)
    if not result:
        return {}, {}
    outside_during(result, ctx.excitation, truth, calibrated)
    drawn = plot_interaction(table, truth, calibrated, ctx.figure("interaction"))
    return result, {"interaction": ctx.figure("interaction").name} if drawn else {}


def d_scales(ctx: GroupDay, log: DeployLog) -> TestResult:
    """Test D from the noise level up (`pipeline.deploy.scales`): pushes of 1-40 N, moments and held loads
    added through each sensor's own distortion on every simulated log of the day (`log`'s day), the
    deployed export beside the oracle and raw; its figures: the slope against the magnitude, the held
    loads' step responses (`pipeline.deploy.steps`)."""
    from pipeline.deploy.page import plot_scales
    from pipeline.deploy.prepare import read_day
    from pipeline.deploy.scales import day_scales
    from pipeline.deploy.steps import plot_steps

    result = day_scales(ctx, read_day(log.labelled.parent.parent))
    figures = {}
    if result and plot_scales(result, ctx.figure("scales")):
        figures["scales"] = ctx.figure("scales").name
    if result and plot_steps(result, ctx.figure("steps")):
        figures["step responses"] = ctx.figure("steps").name
    return result, figures


# test name -> (the experiment type of the log it runs on, the test), in the order of a day's result
DAY_TESTS: dict[str, tuple[str, Callable[[GroupDay, DeployLog], TestResult]]] = {
    "test_a": ("standing", a_noise),
    "test_b": ("walking", b_walking),
    "test_c": ("pole", c_torques),
    "test_d": ("interaction", d_interaction),
    "test_d_scales": ("interaction", d_scales),  # reads every simulated log of the day
}
# the tests' relative costs (Test C: a rigid-body pass per sample and per wrench): forked workers take the
# costliest first, so that they end together
_COST = {"test_c": 4.0, "test_a": 3.0, "test_d": 2.0, "test_d_scales": 2.0, "test_b": 1.0}


def run_days(days: list[tuple[GroupDay, list[DeployLog]]]) -> list[TestResult]:
    """`run_day` of each (day, its logs), every test of every day in its own forked job (the tests are
    independent: each reads its own log); the same results, in the order of `days`."""
    from pipeline.core.parallel import forked_map

    jobs: list[tuple[int, str, GroupDay, DeployLog]] = []
    for d, (ctx, logs) in enumerate(days):
        for name, (kind, _) in DAY_TESTS.items():
            log = next((g for g in logs if g.experiment.get("type", "") == kind), None)
            if log is not None and not (ctx.variant and name == "test_a"):  # offsets change no noise
                jobs.append((d, name, ctx, log))
    if len(jobs) > 1:
        from pipeline.evaluation.figures import pyplot

        pyplot()  # matplotlib imported once, before the workers fork
    calls = [lambda t=DAY_TESTS[name][1], c=ctx, g=log: t(c, g) for _, name, ctx, log in jobs]
    labels = [f"{log.source} ({ctx.group} {name}, day {ctx.day})" for _, name, ctx, log in jobs]
    outs = forked_map(calls, costs=[_COST.get(name, 1.0) for _, name, _, _ in jobs], labels=labels)
    done = {(d, name): out for (d, name, _, _), out in zip(jobs, outs, strict=True)}
    results: list[TestResult] = []
    for d, (_, logs) in enumerate(days):
        result: dict[str, Any] = {"logs": [log.name for log in logs]}
        figures: dict[str, str] = {}
        for name in DAY_TESTS:
            out, drawn = done.get((d, name), ({}, {}))
            if out:
                result[name] = out
                figures.update(drawn)
        results.append((result, figures))
    return results


def run_day(ctx: GroupDay, logs: list[DeployLog]) -> TestResult:
    """Every test of `DAY_TESTS` on the first log of its type (a day without one skips the test)."""
    return run_days([(ctx, logs)])[0]
