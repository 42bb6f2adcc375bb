"""Section ``deploy`` of params.yaml: the deployment logs (a later day of the robot) and the tests' settings.

Light imports only (the stage's CLI validates params with it). Every error names the dotted key.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from pipeline.core.config import Params
from pipeline.core.errors import ConfigError
from pipeline.sim.interaction import InteractionParams
from pipeline.sim.params import DeploymentShift, LogSpec, PushParams, simulate_params

VARIANTS = ("later", "drifted")  # the default deployment logs and the drift check's


@dataclass(frozen=True)
class Drift:
    """How far a deployment day is from training (``deploy.later``, ``deploy.drifted``)."""

    temperature_c: float  # sensors' idle temperature above training's, deg C
    offset_force: float  # offset drift per force axis, uniform +-, N
    offset_torque: float  # offset drift per torque axis, uniform +-, Nm


@dataclass(frozen=True)
class ScaleParams:
    """Test D from the noise level up (``deploy.scales``, `pipeline.deploy.scales`): virtual pushes of every
    scale added through each sensor's own distortion on every simulated log of a day."""

    force_n: tuple[float, ...]  # force pushes, N (the verdict reads every one)
    moment_nm: tuple[float, ...]  # pure moments, Nm
    load_kg: tuple[float, ...]  # loads held at the sensor's site, kg
    levers: tuple[float, ...]  # scales of the site's lever (its point in the sensor frame)
    pulse_s: float  # length of a push (half-sine), s
    load_s: float  # a held load's plateau, s
    pulses: int  # pushes per log, sensor and magnitude at most (seeded slots; loads: a sixth)


@dataclass(frozen=True)
class RezeroParams:
    """``deploy.rezero``: re-zeroing a calibration from a still stretch (`ftcal rezero`, and every
    deployment day after its first still seconds)."""

    duration_s: float  # s of a still stretch used: its first ones
    min_s: float  # the shortest still stretch, s
    still_joint_rad_s: float  # still: every joint slower than this, rad/s (smoothed velocities) ...
    still_gyro_rad_s: float  # ... and every FT board slower than this, rad/s (low-passed gyroscope norm)
    prior_force_n: float  # expected offset change per force axis (1 sigma), N: what the labels leave open
    prior_torque_nm: float  # per torque axis, Nm
    label_mass_rel: float  # the labels' model error (1 sigma): the URDF's masses, relative, ...
    label_com_m: float  # ... and centres of mass, m per axis (`pipeline.deploy.shrink`)
    significance: float  # an estimated change within this x (noise + label error) is not applied; beyond
    # twice it in full, shrunk continuously between
    pose_limit: (
        float  # offsets' spread over a log's still poses above this x the reading's noise: pose-dependent
    )


@dataclass(frozen=True)
class DeployParams:
    """Section ``deploy``."""

    seed: int
    real_logs: str
    logs: tuple[LogSpec, ...]
    push: PushParams
    later: Drift
    drifted: Drift
    torque_limbs: dict[str, str]  # leg FT sensor -> limb end link (its joints are estimated)
    figure_joint: str  # suffix of the joint drawn in the Test C figure (e.g. hip_pitch)
    torque_target: float  # Test C passes when raw RMSE / calibrated RMSE of the joint torque is >= this
    interaction: InteractionParams  # interaction log: pushes and a carried load at every sensor's site
    slope_tolerance: float  # Test D: per-axis slope error (vs 1) at most the oracle's + this
    push_rmse_target: float  # Test D: error of the pushes' reported change at most this x the oracle's
    scales: ScaleParams  # Test D from the noise level up
    rezero: RezeroParams  # re-zeroing: every day is judged as delivered and after re-zeroing


def _num(value: Any, key: str, lo: float, hi: float) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not (lo <= value <= hi):
        raise ConfigError(f"deploy.{key} must be a number in [{lo:g}, {hi:g}], got {value!r}")
    return float(value)


def _mapping(raw: Any, key: str, names: tuple[str, ...]) -> dict[str, Any]:
    if not isinstance(raw, dict):
        raise ConfigError(f"deploy.{key} must be a mapping, got {raw!r}")
    unknown = sorted(set(raw) - set(names))
    missing = sorted(set(names) - set(raw))
    if unknown or missing:
        prefix = f"deploy.{key}." if key else "deploy."
        what = f"unknown key {prefix}{unknown[0]}" if unknown else f"missing key {prefix}{missing[0]}"
        raise ConfigError(what)
    return raw


def _drift(raw: Any, key: str) -> Drift:
    raw = _mapping(raw, key, ("temperature_c", "offset_force", "offset_torque"))
    return Drift(
        _num(raw["temperature_c"], f"{key}.temperature_c", -30.0, 60.0),
        _num(raw["offset_force"], f"{key}.offset_force", 0.0, 500.0),
        _num(raw["offset_torque"], f"{key}.offset_torque", 0.0, 50.0),
    )


def _logs(raw: Any, feet: tuple[str, ...] | None) -> tuple[LogSpec, ...]:
    if not isinstance(raw, list) or not raw:
        raise ConfigError("deploy.logs must be a non-empty list of logs")
    out = []
    for i, entry in enumerate(raw):
        if not isinstance(entry, dict):
            raise ConfigError(f"deploy.logs[{i}] must be a mapping, got {entry!r}")
        try:
            spec = LogSpec(**{"role": "test", **entry})
        except TypeError as exc:
            raise ConfigError(f"deploy.logs[{i}]: {exc}") from None
        spec.check(f"deploy.logs[{i}]", feet)
        out.append(spec)
    types = {s.type for s in out}
    for need in ("standing", "walking", "pole", "interaction"):
        if need not in types:
            raise ConfigError(f"deploy.logs must hold a {need} log (tests A, B, C, D need one each)")
    return tuple(out)


def deploy_params(params: Params) -> DeployParams:
    """Load and validate the ``deploy`` section."""
    names = tuple(f.name for f in dataclasses.fields(DeployParams))
    raw = _mapping(params.raw.get("deploy"), "", names) if "deploy" in params.raw else None
    if raw is None:
        raise ConfigError("missing section deploy")
    seed = raw["seed"]
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**32:
        raise ConfigError(f"deploy.seed must be an integer in [0, 2**32), got {seed!r}")
    if not isinstance(raw["real_logs"], str) or not raw["real_logs"]:
        raise ConfigError(f"deploy.real_logs must be a folder path, got {raw['real_logs']!r}")
    push = _mapping(raw["push"], "push", ("force_n", "duration_s", "period_s", "direction"))
    limbs = raw["torque_limbs"]
    if not isinstance(limbs, dict) or not limbs or not all(isinstance(v, str) for v in limbs.values()):
        raise ConfigError(f"deploy.torque_limbs must map FT sensors to limb end links, got {limbs!r}")
    if not isinstance(raw["figure_joint"], str) or not raw["figure_joint"]:
        raise ConfigError(f"deploy.figure_joint must be a joint name suffix, got {raw['figure_joint']!r}")
    pairs = params.robot.foot_pairs  # None: feet from the URDF, checked when it is loaded
    feet = None if pairs is None else tuple(p.name for p in pairs)
    return DeployParams(
        seed=seed,
        real_logs=raw["real_logs"],
        logs=_logs(raw["logs"], feet),
        push=PushParams(
            **{k: tuple(v) if k == "direction" and isinstance(v, list) else v for k, v in push.items()}
        ),
        later=_drift(raw["later"], "later"),
        drifted=_drift(raw["drifted"], "drifted"),
        torque_limbs=dict(limbs),
        figure_joint=raw["figure_joint"],
        torque_target=_num(raw["torque_target"], "torque_target", 0.0, math.inf),
        interaction=_interaction(raw["interaction"]),
        slope_tolerance=_num(raw["slope_tolerance"], "slope_tolerance", 0.0, 1.0),
        push_rmse_target=_num(raw["push_rmse_target"], "push_rmse_target", 1.0, math.inf),
        scales=_scales(raw["scales"]),
        rezero=_rezero(raw["rezero"]),
    )


def _numbers(value: Any, key: str, lo: float, hi: float) -> tuple[float, ...]:
    if not isinstance(value, list) or not value:
        raise ConfigError(f"deploy.scales.{key} must be a non-empty list of numbers, got {value!r}")
    return tuple(_num(v, f"scales.{key}", lo, hi) for v in value)


def _scales(raw: Any) -> ScaleParams:
    names = tuple(f.name for f in dataclasses.fields(ScaleParams))
    raw = _mapping(raw, "scales", names)
    pulses = raw["pulses"]
    if isinstance(pulses, bool) or not isinstance(pulses, int) or not 1 <= pulses <= 1000:
        raise ConfigError(f"deploy.scales.pulses must be an integer in [1, 1000], got {pulses!r}")
    return ScaleParams(
        force_n=_numbers(raw["force_n"], "force_n", 1e-3, 2000.0),
        moment_nm=_numbers(raw["moment_nm"], "moment_nm", 1e-4, 200.0),
        load_kg=_numbers(raw["load_kg"], "load_kg", 1e-3, 100.0),
        levers=_numbers(raw["levers"], "levers", 0.0, 10.0),
        pulse_s=_num(raw["pulse_s"], "scales.pulse_s", 0.05, 10.0),
        load_s=_num(raw["load_s"], "scales.load_s", 0.1, 60.0),
        pulses=pulses,
    )


def _rezero(raw: Any) -> RezeroParams:
    names = tuple(f.name for f in dataclasses.fields(RezeroParams))
    raw = _mapping(raw, "rezero", names)
    bounds = {
        "duration_s": (0.1, 3600.0), "min_s": (0.1, 600.0), "still_joint_rad_s": (1e-6, 10.0),
        "still_gyro_rad_s": (1e-6, 10.0), "prior_force_n": (1e-3, 1e4), "prior_torque_nm": (1e-4, 1e3),
        "pose_limit": (0.0, 1e3), "label_mass_rel": (0.0, 1.0), "label_com_m": (0.0, 1.0),
        "significance": (0.0, 100.0),
    }  # fmt: skip
    values = {k: _num(raw[k], f"rezero.{k}", *bounds[k]) for k in names}
    if values["min_s"] > values["duration_s"]:
        raise ConfigError(f"deploy.rezero.min_s ({values['min_s']:g}) must not exceed duration_s")
    return RezeroParams(**values)


def _interaction(raw: Any) -> InteractionParams:
    names = tuple(f.name for f in dataclasses.fields(InteractionParams))
    raw = _mapping(raw, "interaction", names)
    values = {
        k: tuple(v) if k in ("force_n", "directions") and isinstance(v, list) else v for k, v in raw.items()
    }
    return InteractionParams(**values)


def deployment_simulation(params: Params, variant: str) -> Any:
    """The `SimulateParams` of the deployment logs of `variant` (later or drifted): the training
    simulation's robot and hidden distortions, the deploy section's logs, seed, pushes, warmth and drift."""
    if variant not in VARIANTS:
        raise ConfigError(f"deployment variant must be one of {', '.join(VARIANTS)}, got {variant!r}")
    dp = deploy_params(params)
    sim = simulate_params(params)
    drift: Drift = getattr(dp, variant)
    thermal = dataclasses.replace(sim.thermal, baseline=sim.thermal.baseline + drift.temperature_c)
    seed = (dp.seed + VARIANTS.index(variant)) % 2**32  # each day its own motions and noise
    return dataclasses.replace(
        sim,
        logs=dp.logs,
        plots=False,
        thermal=thermal,
        push=dp.push,
        interaction=dp.interaction,
        shift=DeploymentShift(seed, drift.offset_force, drift.offset_torque),
    )
