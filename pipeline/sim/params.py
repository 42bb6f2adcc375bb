"""Parameters of the simulator (section ``simulate`` of params.yaml), validated on construction.

Every dataclass below is one subsection; its ``__post_init__`` raises `ConfigError` naming the dotted key.
Motion lengths left ``null`` in params.yaml are derived from the robot's URDF (:mod:`pipeline.sim.derive`),
so changing ``robot.urdf`` alone gives motions fitted to the robot. Light imports (no numpy): the CLI loads
this module to validate params.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from pipeline.core.config import Params, stage_section
from pipeline.core.errors import ConfigError
from pipeline.logs.imu_axes import parse_axis_maps

EXPERIMENT_TYPES = ("pole", "balancing", "half_foot", "walking", "standing", "known_load", "interaction",
                    "poses")  # fmt: skip


def check_number(
    obj: Any, name: str, lo: float, hi: float, *, lo_open: bool = False, hi_open: bool = True
) -> None:
    """Check field `name` of the params dataclass `obj` is a real number in the given interval; converts
    ints to float in place (the dataclasses are frozen) and raises ConfigError naming ``<obj.SECTION>.<name>``
    otherwise."""
    value = getattr(obj, name)
    left, right = "(" if lo_open else "[", ")" if hi_open else "]"
    key = f"{obj.SECTION}.{name}"
    interval = f"{left}{lo:g}, {'inf' if hi == math.inf else f'{hi:g}'}{right}"
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ConfigError(f"{key} must be a number in {interval}, got {value!r}")
    too_low = value <= lo if lo_open else value < lo
    too_high = value >= hi if hi_open else value > hi
    if too_low or too_high:
        raise ConfigError(f"{key} must be in {interval}, got {value!r}")
    object.__setattr__(obj, name, float(value))


def check_order(obj: Any, low: str, high: str) -> None:
    if getattr(obj, low) > getattr(obj, high):
        raise ConfigError(
            f"{obj.SECTION}.{low} must not exceed {obj.SECTION}.{high}, "
            f"got {getattr(obj, low)!r} > {getattr(obj, high)!r}"
        )


@dataclass(frozen=True)
class DistortionRanges:
    """Ranges from which each FT sensor's hidden distortion is drawn (section ``simulate.sensors``).

    Defaults give raw-vs-truth errors like the thesis's raw columns for loads of a few hundred N: ~25-50 N
    RMSE on force axes, ~1.5-6 Nm on torque axes, mostly offsets. "uniform +-x": U(-x, x) per sensor, axis.
    """

    coupling: float = 0.02  # off-diagonal cross-talk of C, uniform +-: dimensionless in the force<-force
    #                         and torque<-torque blocks, 1/m in force<-torque (torque<-force is the lever)
    lever_m: float = 0.008  # force->torque lever, m: torque rows get r x f, r uniform +- per component
    gain: float = 0.03  # diagonal gain error of C, uniform +-, dimensionless
    temperature_gain: float = 5e-4  # g_T, gain change per deg C, uniform +-, 1/degC (0.05 %/degC)
    temperature_ref: float = 25.0  # T_ref, deg C: temperature of the primary calibration (zero drift)
    offset_force_min: float = 20.0  # |offset| of each force axis, N, uniform in [min, max], random sign
    offset_force_max: float = 45.0
    offset_torque_min: float = 1.0  # |offset| of each torque axis, Nm, uniform in [min, max], random sign
    offset_torque_max: float = 4.0
    offset_drift_force: float = 0.5  # o_T of force axes, N/degC, uniform +-
    offset_drift_torque: float = 0.02  # o_T of torque axes, Nm/degC, uniform +-
    nonlinearity: float = 0.01  # k, uniform +-: k * v|v|/s is k of full scale at full scale (1% rule)
    full_scale_force: float = 1500.0  # s of force axes, N
    full_scale_torque: float = 100.0  # s of torque axes, Nm
    hysteresis: float = 0.003  # h, uniform in [0, hysteresis] x full scale, per axis (0.3% of FS)
    hysteresis_width_min: float = 0.005  # the play operators' widths, log-uniform in [min, max] x full scale
    hysteresis_width_max: float = 0.05  # per operator and axis; a reversal of 2x a width saturates it
    hysteresis_operators: int = 3  # play operators per axis, the amplitude split equally among them
    creep: float = 0.003  # c, uniform in [0, creep] per axis: a load step reads -c of itself, then recovers
    creep_tau_min_s: float = 20.0  # creep's time constant, log-uniform in [min, max], s, per axis
    creep_tau_max_s: float = 200.0
    thermal_lag_s: float = 60.0  # the gauges' temperature lags the board thermometer's by this, s (0: none)
    noise_force: float = 0.6  # white noise std of force axes, N
    noise_torque: float = 0.03  # white noise std of torque axes, Nm

    SECTION = "simulate.sensors"  # dotted params key, for error messages (a class attribute, not a field)

    def __post_init__(self) -> None:
        check_number(self, "coupling", 0.0, 0.5)
        check_number(self, "lever_m", 0.0, 0.1)
        check_number(self, "gain", 0.0, 0.5)
        check_number(self, "temperature_gain", 0.0, 0.005)  # keeps G(T) > 0.5 within 100 degC of T_ref
        check_number(self, "temperature_ref", -50.0, 150.0, hi_open=False)
        nonnegative = ("offset_force_min", "offset_force_max", "offset_torque_min", "offset_torque_max",
                       "offset_drift_force", "offset_drift_torque", "noise_force", "noise_torque",
                       "thermal_lag_s")  # fmt: skip
        for name in nonnegative:
            check_number(self, name, 0.0, math.inf)
        for name in ("full_scale_force", "full_scale_torque", "creep_tau_min_s", "creep_tau_max_s"):
            check_number(self, name, 0.0, math.inf, lo_open=True)
        for name in ("hysteresis_width_min", "hysteresis_width_max"):
            check_number(self, name, 0.0, 1.0, lo_open=True, hi_open=False)
        for low in ("offset_force_min", "offset_torque_min", "hysteresis_width_min", "creep_tau_min_s"):
            check_order(self, low, low.replace("min", "max"))
        check_number(self, "nonlinearity", 0.0, 0.2)  # keeps the static map monotonic far beyond full scale
        check_number(self, "hysteresis", 0.0, 0.1)
        check_number(self, "creep", 0.0, 0.1, hi_open=False)
        if not isinstance(self.hysteresis_operators, int) or not 1 <= self.hysteresis_operators <= 10:
            got = repr(self.hysteresis_operators)
            raise ConfigError(f"{self.SECTION}.hysteresis_operators must be an integer in [1, 10], got {got}")


@dataclass(frozen=True)
class ThermalParams:
    """First-order thermal model of an FT sensor (section ``simulate.thermal``).

    The sensor relaxes with time constant `tau_s` towards ``baseline + heat_gain * activity``, where
    the baseline (idle temperature) is drawn per log; a 2-3 minute log drifts a few degrees, a long
    active one approaches baseline + heat_gain (~45 degC by default).
    """

    baseline: float = 30.0  # idle sensor temperature, deg C (the log starts here unless `initial` is given)
    baseline_spread: float = 1.0  # baseline drawn uniform +- this, deg C, per log
    heat_gain: float = 15.0  # temperature rise at activity 1 in steady state, deg C
    tau_s: float = 300.0  # thermal time constant, s
    t_min: float = 15.0  # clip of the temperature, deg C
    t_max: float = 60.0
    noise: float = 0.05  # white measurement noise std, deg C
    resolution: float = 0.1  # quantisation step of the published temperature, deg C (0: none)
    warmup_max: float = 0.0  # a log starts up to this much above its baseline (robot busy before), deg C

    SECTION = "simulate.thermal"  # dotted params key, for error messages (a class attribute, not a field)

    def __post_init__(self) -> None:
        for name in ("baseline", "t_min", "t_max"):
            check_number(self, name, -50.0, 150.0, hi_open=False)
        for name, high in (("baseline_spread", 50), ("heat_gain", 100), ("noise", 10), ("resolution", 10)):
            check_number(self, name, 0.0, high)
        check_number(self, "warmup_max", 0.0, 50.0)
        check_number(self, "tau_s", 0.0, math.inf, lo_open=True)
        check_order(self, "t_min", "t_max")


@dataclass(frozen=True)
class ImuNoiseParams:
    """Accelerometer and gyroscope imperfections of an FT board IMU (section ``simulate.imu``).

    Biases are constant over a log; vibration bursts (e.g. foot impacts, motor cogging) arrive as a
    Poisson process and are a Hann-windowed sinusoid along a random direction.
    """

    acc_bias: float = 0.2  # accelerometer bias per axis, uniform +-, m/s^2
    gyro_bias: float = 0.01  # gyroscope bias per axis, uniform +-, rad/s
    acc_noise: float = 0.05  # accelerometer white noise std, m/s^2
    gyro_noise: float = 0.005  # gyroscope white noise std, rad/s
    burst_rate: float = 0.1  # vibration bursts per second (Poisson)
    burst_duration_min: float = 0.1  # burst length, s, uniform in [min, max]
    burst_duration_max: float = 0.5
    burst_freq_min: float = 20.0  # burst oscillation frequency, Hz, uniform in [min, max]
    burst_freq_max: float = 40.0  # (aliased if above the Nyquist frequency, as an unfiltered sensor would)
    burst_acc: float = 2.0  # peak burst amplitude on the accelerometer, uniform in [0, this], m/s^2
    burst_gyro: float = 0.05  # peak burst amplitude on the gyroscope at the same relative level, rad/s
    axes: Any = None  # FT sensor -> its board's IMU axes in the sensor frame (a faulty board; none: none)

    SECTION = "simulate.imu"  # dotted params key, for error messages (a class attribute, not a field)

    def __post_init__(self) -> None:
        for name in (
            "acc_bias",
            "gyro_bias",
            "acc_noise",
            "gyro_noise",
            "burst_rate",
            "burst_acc",
            "burst_gyro",
        ):
            check_number(self, name, 0.0, math.inf)
        check_number(self, "burst_duration_min", 0.0, math.inf, lo_open=True)
        check_number(self, "burst_duration_max", 0.0, math.inf, lo_open=True)
        check_order(self, "burst_duration_min", "burst_duration_max")
        check_number(self, "burst_freq_min", 0.0, math.inf)
        check_number(self, "burst_freq_max", 0.0, math.inf)
        check_order(self, "burst_freq_min", "burst_freq_max")
        object.__setattr__(self, "axes", parse_axis_maps(self.axes, "simulate.imu.axes"))


@dataclass(frozen=True)
class MotionParams:
    """Shape of the simulated motions (section ``simulate.motion``).

    Fields that default to None are robot-dependent lengths and angles: None means "derived from the
    URDF" (:func:`pipeline.sim.derive.derive_motion` says how), a number overrides the derivation.
    """

    limit_margin: float = 0.03  # rad (m for prismatic) kept free at both ends of every joint range
    f_min_hz: float = 0.05  # lowest frequency of the free joints' multi-sines, Hz
    f_max_hz: float = 0.5  # highest, Hz
    pole_amplitude: float = 0.35  # free-joint swing on the pole, fraction of the joint range
    upper_body_amplitude: float = 0.2  # arms, torso, head while balancing/walking, fraction of range
    still_mass_fraction: float = 0.003  # joints moving less than this share of the robot mass are held
    root_height_m: float | None = None  # root_link height above the soles while standing (legs bent), m
    stance_lean_rad: float | None = None  # pelvis roll towards the supporting foot, rad
    swing_lift_m: float | None = None  # balancing: how high the free foot is held, m
    swing_forward_m: float | None = None  # balancing: how far forward the free foot is held, m
    swing_motion_m: float | None = None  # balancing: free-foot wander, m
    com_margin_m: float | None = None  # CoM kept this far inside the edge of a supporting foot part, m
    step_length_m: float | None = None  # walking: step length, m
    step_lift_m: float | None = None  # walking: swing-foot clearance, m
    single_support_s: float = 0.8  # walking: single-support duration, s
    double_support_s: float = 0.4  # walking: double-support duration, s
    steps_per_direction: int = 8  # walking: steps forward, then as many backward
    com_rate_hz: float = 10.0  # rate of the centre-of-mass correction (spline in between), Hz
    pose_hold_s: float = 8.0  # poses (on the pole, still): each pose held this long, s
    pose_move_s: float = 2.0  # poses: the move from one pose to the next, s

    SECTION = "simulate.motion"  # dotted params key, for error messages (a class attribute, not a field)
    DERIVED = (  # the fields None derives from the URDF
        "root_height_m",
        "stance_lean_rad",
        "swing_lift_m",
        "swing_forward_m",
        "swing_motion_m",
        "com_margin_m",
        "step_length_m",
        "step_lift_m",
    )

    def __post_init__(self) -> None:
        check_number(self, "limit_margin", 0.0, 0.5)
        check_number(self, "f_min_hz", 0.0, 50.0, lo_open=True)
        check_number(self, "f_max_hz", 0.0, 50.0, lo_open=True)
        check_order(self, "f_min_hz", "f_max_hz")
        check_number(self, "pole_amplitude", 0.0, 0.5, hi_open=False)
        check_number(self, "upper_body_amplitude", 0.0, 0.5, hi_open=False)
        check_number(self, "still_mass_fraction", 0.0, 0.1)
        bounds = {"root_height_m": (0.0, 5.0), "stance_lean_rad": (-0.5, 0.5)}
        for name in self.DERIVED:
            if getattr(self, name) is not None:
                lo, hi = bounds.get(name, (0.0, 1.0))
                check_number(self, name, lo, hi, lo_open=name == "root_height_m")
        check_number(self, "single_support_s", 0.1, 10.0)
        check_number(self, "double_support_s", 0.05, 10.0)
        check_number(self, "com_rate_hz", 0.5, 1000.0)
        check_number(self, "pose_hold_s", 0.5, 600.0)
        check_number(self, "pose_move_s", 0.1, 60.0)
        steps = self.steps_per_direction
        if isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= 100:
            raise ConfigError(
                f"{self.SECTION}.steps_per_direction must be an integer in [1, 100], got {steps!r}"
            )


@dataclass(frozen=True)
class TimingParams:
    """How messages arrive (section ``simulate.timing``)."""

    jitter_s: float = 0.0005  # std of stamp jitter around the nominal period, s
    ft_offset_s: float = 0.002  # FT board clock lag behind the joint-state stamps, s
    temperature_rate_hz: float = 10.0  # temperature messages per second
    drop_rate: float = 0.001  # fraction of FT, IMU and joint-state messages lost
    duplicate_rate: float = 0.0005  # fraction of messages recorded twice
    delay_s: float = 0.003  # mean of the exponential transport delay (log time - stamp), s

    SECTION = "simulate.timing"

    def __post_init__(self) -> None:
        for name in ("jitter_s", "ft_offset_s", "delay_s"):
            check_number(self, name, 0.0, 0.1, hi_open=False)
        for name in ("drop_rate", "duplicate_rate"):
            check_number(self, name, 0.0, 0.5)
        check_number(self, "temperature_rate_hz", 0.1, 1000.0, hi_open=False)


def three_numbers(value: Any, key: str) -> tuple[float, float, float]:
    """Three finite numbers (a point or a direction), else ConfigError naming `key`."""
    if (
        not isinstance(value, list | tuple)
        or len(value) != 3
        or not all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in value)
    ):
        raise ConfigError(f"{key} must be 3 numbers, got {value!r}")
    return tuple(float(v) for v in value)  # type: ignore[return-value]


@dataclass(frozen=True)
class LoadSpec:
    """A known mass rigidly attached to a link (known-load experiments): a point mass at `point`."""

    link: (
        str  # a URDF link, or a site: 'hands' / 'feet' (every arm's / foot sensor's site, pipeline.sim.sites)
    )
    mass_kg: float
    point: tuple[float, float, float] = (0.0, 0.0, 0.0)  # in the link frame, m

    def check(self, key: str) -> None:
        if not isinstance(self.link, str) or not self.link.strip():
            raise ConfigError(f"{key}.link must be a link name, 'hands' or 'feet', got {self.link!r}")
        m = self.mass_kg
        if isinstance(m, bool) or not isinstance(m, int | float) or not 0.0 < m <= 100.0:
            raise ConfigError(f"{key}.mass_kg must be a number in (0, 100] kg, got {m!r}")
        object.__setattr__(self, "mass_kg", float(m))
        object.__setattr__(self, "point", three_numbers(self.point, f"{key}.point"))


@dataclass(frozen=True)
class LogSpec:
    """One simulated log (an entry of ``simulate.logs``)."""

    type: str  # pole | balancing | half_foot | walking | standing | known_load | interaction | poses
    duration_s: float  # robot time, s
    role: str  # train | test (written into the log's metadata)
    foot: str = ""  # balancing / half_foot: the supporting foot (l_foot...: pipeline.physics.feet)
    part: str = ""  # half_foot: 'front' or 'rear'
    # known_load: the masses attached for the whole log (on the pole); the labels include them
    loads: tuple[LoadSpec, ...] = ()

    def check(self, key: str, feet: tuple[str, ...] | None) -> None:
        """Raise ConfigError naming `key` for a bad entry; `feet`: the robot's foot names (None: unknown
        until the URDF is loaded, `pipeline.sim.world.check_feet`)."""
        if self.type not in EXPERIMENT_TYPES:
            raise ConfigError(f"{key}.type must be one of {', '.join(EXPERIMENT_TYPES)}, got {self.type!r}")
        loads = self.loads
        if not isinstance(loads, list | tuple) or (self.type == "known_load") != bool(loads):
            raise ConfigError(f"{key}.loads: a known_load log needs a list of loads, no other log has any")
        specs = []
        for i, entry in enumerate(loads):
            if not isinstance(entry, dict | LoadSpec):
                raise ConfigError(
                    f"{key}.loads[{i}] must be a mapping {{link, mass_kg, point}}, got {entry!r}"
                )
            try:
                spec = entry if isinstance(entry, LoadSpec) else LoadSpec(**entry)
            except TypeError as exc:
                raise ConfigError(f"{key}.loads[{i}]: {exc}") from None
            spec.check(f"{key}.loads[{i}]")
            specs.append(spec)
        object.__setattr__(self, "loads", tuple(specs))
        if not (isinstance(self.duration_s, int | float) and 1.0 <= self.duration_s <= 7200.0):
            raise ConfigError(f"{key}.duration_s must be in [1, 7200] s, got {self.duration_s!r}")
        if self.role not in ("train", "test"):
            raise ConfigError(f"{key}.role must be train or test, got {self.role!r}")
        if self.type in ("balancing", "half_foot") and feet is not None and self.foot not in feet:
            raise ConfigError(f"{key}.foot must be one of {', '.join(feet)}, got {self.foot!r}")
        if self.type == "half_foot" and self.part not in ("front", "rear"):
            raise ConfigError(f"{key}.part must be front or rear, got {self.part!r}")

    def name(self, index: int) -> str:
        """File stem of the log: ``<NN>_<type>[_<foot>][_<part>]_<role>``."""
        extra = f"_{self.foot}" if self.foot else ""
        extra += f"_{self.part}" if self.part else ""
        return f"{index:02d}_{self.type}{extra}_{self.role}"


@dataclass(frozen=True)
class PushParams:
    """External pushes on the legs in pole logs (deployment logs, ``deploy.push``): a hand pushing one foot.

    Each push is a half-sine force profile along `direction` (world frame: the root_link frame on the
    pole), applied at the origin of the sole frame of one foot; feet take turns. The motion is unchanged
    (the joints track their trajectories, as under stiff position control): the push shows in the wrenches
    of the sensors between it and the root and in the joint torques.
    """

    force_n: float  # peak force of a push, N
    duration_s: float  # length of a push, s
    period_s: float  # a push starts every this many seconds (the first after half a period), s
    direction: tuple[float, float, float]  # force direction in the world frame (normalised), 1

    SECTION = "deploy.push"

    def __post_init__(self) -> None:
        check_number(self, "force_n", 0.0, 2000.0)
        check_number(self, "duration_s", 0.0, 60.0, lo_open=True)
        check_number(self, "period_s", 0.0, 600.0, lo_open=True)
        check_order(self, "duration_s", "period_s")
        d = self.direction
        if (
            not isinstance(d, list | tuple)
            or len(d) != 3
            or not all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in d)
            or math.hypot(*d) == 0.0
        ):
            raise ConfigError(f"{self.SECTION}.direction must be 3 numbers, not all zero, got {d!r}")
        norm = math.hypot(*d)
        object.__setattr__(self, "direction", tuple(float(v) / norm for v in d))


@dataclass(frozen=True)
class DeploymentShift:
    """What sets deployment logs apart from the training logs of the same robot (a later day).

    The hidden distortions are those of training (drawn from the top-level seed); motions and noise come
    from `seed`, and every sensor's offset has drifted by a draw uniform +- `offset_force` (N, force axes)
    and +- `offset_torque` (Nm, torque axes) from `seed`.
    """

    seed: int  # seed of the deployment logs' motions, noise and offset drift
    offset_force: float  # N, offset drift bound per force axis
    offset_torque: float  # Nm, offset drift bound per torque axis


@dataclass(frozen=True)
class SimulateParams:
    """Section ``simulate`` of params.yaml."""

    rate_hz: float  # joint-state and FT rate, Hz
    mass_error: float  # true link mass = URDF mass x (1 + uniform +- this)
    com_error_m: float  # true link COM = URDF COM + uniform +- this per axis, m
    encoder_resolution_rad: float  # encoder quantum, rad (0: none)
    encoder_noise_rad: float  # encoder white noise std before quantisation, rad
    activity_scale: float  # |joint velocity| (rad/s, norm over the limb) that counts as activity 1
    workers: int  # processes generating logs in parallel (0: one per core)
    plots: bool  # write the per-experiment-type plots
    logs: tuple[LogSpec, ...]
    motion: MotionParams = field(default_factory=MotionParams)
    sensors: DistortionRanges = field(default_factory=DistortionRanges)
    thermal: ThermalParams = field(default_factory=ThermalParams)
    imu: ImuNoiseParams = field(default_factory=ImuNoiseParams)
    timing: TimingParams = field(default_factory=TimingParams)
    push: PushParams | None = None  # external pushes in pole logs (deployment logs only)
    # pushes and loads of interaction logs (deployment only): a pipeline.sim.interaction.InteractionParams
    interaction: Any = None
    shift: DeploymentShift | None = None  # deployment logs: their own seed and drifted offsets

    SECTION = "simulate"

    def __post_init__(self) -> None:
        check_number(self, "rate_hz", 10.0, 2000.0, hi_open=False)
        check_number(self, "mass_error", 0.0, 0.5)
        check_number(self, "com_error_m", 0.0, 0.1)
        check_number(self, "encoder_resolution_rad", 0.0, 0.1)
        check_number(self, "encoder_noise_rad", 0.0, 0.1)
        check_number(self, "activity_scale", 0.0, math.inf, lo_open=True)
        if isinstance(self.workers, bool) or not isinstance(self.workers, int) or self.workers < 0:
            raise ConfigError(f"simulate.workers must be an integer >= 0, got {self.workers!r}")
        if not self.logs:
            raise ConfigError("simulate.logs must list at least one log")


_NESTED = {
    "motion": MotionParams,
    "sensors": DistortionRanges,
    "thermal": ThermalParams,
    "imu": ImuNoiseParams,
    "timing": TimingParams,
}


def _sub(cls: type, data: Any, key: str) -> Any:
    """`cls` built from the mapping `data` at dotted `key` (unknown keys and bad types name the key)."""
    if not isinstance(data, dict):
        raise ConfigError(f"{key} must be a mapping, got {data!r}")
    names = set(cls.__dataclass_fields__)
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"unknown key {key}.{unknown[0]} (allowed: {', '.join(sorted(names))})")
    try:
        return cls(**data)
    except TypeError as exc:
        raise ConfigError(f"{key}: {exc}") from None


def simulate_params(params: Params) -> SimulateParams:
    """Load and validate the ``simulate`` section (errors start with the params file, name the dotted key)."""
    where = params.raw.get("__file__", "params.yaml")
    raw = params.raw.get("simulate")
    try:
        if not isinstance(raw, dict):
            raise ConfigError("missing section simulate")
        raw = dict(raw)
        for key in (
            "push",
            "shift",
            "interaction",
        ):  # set by the deploy section only (pipeline.deploy.params)
            if key in raw:
                raise ConfigError(
                    f"unknown key simulate.{key} (pushes and drift belong to the deploy section)"
                )
            raw[key] = None
        for key, cls in _NESTED.items():
            if key in raw:
                raw[key] = _sub(cls, raw[key], f"simulate.{key}")
        if not isinstance(raw.get("logs"), list):
            raise ConfigError("simulate.logs must be a list of logs")
        # the feet: params' foot pairs; derived from the URDF (None), they are checked when it is loaded
        feet = None if params.robot.foot_pairs is None else tuple(p.name for p in params.robot.foot_pairs)
        logs = []
        for i, entry in enumerate(raw["logs"]):
            spec = _sub(LogSpec, entry, f"simulate.logs[{i}]")
            spec.check(f"simulate.logs[{i}]", feet)
            if spec.type == "interaction":
                raise ConfigError(
                    f"simulate.logs[{i}].type: interaction logs belong to deploy.logs (deploy.interaction)"
                )
            logs.append(spec)
        raw["logs"] = tuple(logs)
        fake = Params(seed=params.seed, robot=params.robot, topics=params.topics, raw={"simulate": raw})
        return stage_section(fake, "simulate", SimulateParams)
    except ConfigError as exc:
        message = str(exc)
        raise ConfigError(message if message.startswith(where) else f"{where}: {message}") from None
