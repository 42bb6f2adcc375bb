"""params.yaml, loaded once into frozen, validated dataclasses.

Only the shared sections (`seed`, `robot`) are typed here; each stage adds its own section and
dataclass when it arrives. `Params.raw` keeps the whole parsed file for the sections not typed yet.

Every problem is a `ConfigError` whose message names the file and the dotted key, e.g.
``params.yaml: robot.gravity must be a positive number, got -1``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from pipeline.core.defaults import read_yaml_file, resolve
from pipeline.core.errors import ConfigError

PARAMS_FILE = "params.yaml"
PIPELINE_FILE = "dvc.yaml"  # marks the repo root

T = TypeVar("T")

_MAX_SEED = 2**32  # numpy and torch accept seeds in [0, 2**32)


def repo_root() -> Path:
    """The project root: the nearest directory holding dvc.yaml, walking up from the working directory.

    Falls back to the parent of the installed `pipeline` package if it holds dvc.yaml (an editable
    install run from elsewhere), and finally to the working directory.
    """
    cwd = Path.cwd().resolve()
    for directory in (cwd, *cwd.parents):
        if (directory / PIPELINE_FILE).is_file():
            return directory
    package_parent = Path(__file__).resolve().parents[2]
    if (package_parent / PIPELINE_FILE).is_file():
        return package_parent
    return cwd


def resolve_urdf(urdf: str, root: Path) -> str:
    """Resolve `robot.urdf` from params: a model name stays as is, a relative path is taken from `root`.

    A value is a path if it ends in ``.urdf`` or contains a path separator; otherwise it is a robot
    name of the icub-models package (e.g. ``iCubGenova09``).
    """
    if not (urdf.endswith(".urdf") or "/" in urdf or "\\" in urdf):
        return urdf
    path = Path(urdf).expanduser()
    return str(path if path.is_absolute() else (root / path))


def _check_name(value: object, key: str) -> None:
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(f"{key} must be a non-empty string, got {value!r}")


def check_suffix(value: object, key: str) -> None:
    """A file suffix such as '.yaml' (a sidecar's), else ConfigError naming `key`."""
    if not isinstance(value, str) or not value.startswith(".") or len(value) < 2:
        raise ConfigError(f"{key} must be a file suffix like '.yaml', got {value!r}")


@dataclass(frozen=True)
class FootPairParams:
    """The front and rear FT sensors of one foot, whose sum is compared in the sole frame.

    `name` is the sensor group name (the key under `robot.foot_pairs`); `front` and `rear` are
    FT sensor names and `sole` a link/frame name, all as written in the URDF.
    """

    name: str
    front: str
    rear: str
    sole: str

    def __post_init__(self) -> None:
        _check_name(self.name, "robot.foot_pairs key")
        prefix = f"robot.foot_pairs.{self.name}"
        for attr in ("front", "rear", "sole"):
            _check_name(getattr(self, attr), f"{prefix}.{attr}")
        if self.front == self.rear:
            raise ConfigError(f"{prefix}.rear must differ from {prefix}.front, both are {self.front!r}")

    @property
    def sensors(self) -> tuple[str, str]:
        """(front, rear) sensor names."""
        return (self.front, self.rear)


@dataclass(frozen=True)
class RobotParams:
    """The robot model and the physical constants shared by every stage (section `robot`)."""

    urdf: str  # icub-models robot name or URDF path (relative paths: from the repo root)
    gravity: float  # m/s^2, magnitude; world z is up, so gravity is (0, 0, -gravity)
    # the foot pairs as params name them; None: the feet derived from the URDF (pipeline.physics.feet)
    foot_pairs: tuple[FootPairParams, ...] | None = None
    # FT sensor -> serial number of its board, where the logs do not record it (pipeline.export.identity)
    serials: dict[str, str] | None = None

    def __post_init__(self) -> None:
        _check_name(self.urdf, "robot.urdf")
        serials = _mapping(self.serials or {}, "robot.serials")
        if any(type(v) not in (str, int) or not str(v).strip() for v in serials.values()):
            raise ConfigError(f"robot.serials must map FT sensors to serial numbers, got {self.serials!r}")
        object.__setattr__(self, "serials", {str(k): str(v).strip() for k, v in serials.items()} or None)
        g = self.gravity
        if isinstance(g, bool) or not isinstance(g, int | float) or not math.isfinite(g) or g <= 0:
            raise ConfigError(f"robot.gravity must be a positive number, got {g!r}")
        object.__setattr__(self, "gravity", float(g))
        seen_names: set[str] = set()
        used_by: dict[str, str] = {}
        for pair in self.foot_pairs or ():
            if not isinstance(pair, FootPairParams):
                raise ConfigError(f"robot.foot_pairs must hold foot pairs, got {pair!r}")
            if pair.name in seen_names:
                raise ConfigError(f"robot.foot_pairs.{pair.name} is defined twice")
            seen_names.add(pair.name)
            for sensor in pair.sensors:
                if sensor in used_by:
                    raise ConfigError(
                        f"robot.foot_pairs.{pair.name}: sensor {sensor!r} is already in "
                        f"robot.foot_pairs.{used_by[sensor]}"
                    )
                used_by[sensor] = pair.name


@dataclass(frozen=True)
class TopicParams:
    """MCAP topic names (section `topics`), shared by the simulator and ingest.

    Per-sensor names are templates in which ``{sensor}`` stands for the FT sensor name of the URDF.
    The ``sim_*`` topics carry simulated truth: evaluation only, never a training input.
    """

    joint_states: str  # sensor_msgs/msg/JointState: encoder positions (rad), velocities (rad/s)
    ft_wrench: str  # geometry_msgs/msg/WrenchStamped: raw wrench, N and Nm, sensor frame
    ft_imu: str  # sensor_msgs/msg/Imu: FT board accelerometer (m/s^2, proper) and gyroscope (rad/s)
    ft_temperature: str  # sensor_msgs/msg/Temperature: deg C
    sim_wrench_true: str  # WrenchStamped: the true wrench through the sensor
    sim_wrench_distorted: str  # WrenchStamped: the sensor's noise-free distorted reading
    sim_wrench_oracle: str  # WrenchStamped: the oracle calibration of the raw reading (noise floor)
    sim_contacts: str  # std_msgs/msg/String: comma-separated links touching the environment
    sim_joint_torques: str = "/sim/joint_torques"  # JointState: true joint torques (effort, Nm), pushed logs
    # WrenchStamped: the part of the true wrench due to external pushes and loads (logs with some)
    sim_wrench_external: str = "/sim/ft/{sensor}/wrench_external"

    PER_SENSOR = (
        "ft_wrench",
        "ft_imu",
        "ft_temperature",
        "sim_wrench_true",
        "sim_wrench_distorted",
        "sim_wrench_oracle",
        "sim_wrench_external",
    )

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            _check_name(value, f"topics.{name}")
            if not value.startswith("/"):
                raise ConfigError(f"topics.{name} must start with '/', got {value!r}")
            if (name in self.PER_SENSOR) != ("{sensor}" in value):
                need = "must" if name in self.PER_SENSOR else "must not"
                raise ConfigError(f"topics.{name} {need} contain {{sensor}}, got {value!r}")

    def sensor_topic(self, kind: str, sensor: str) -> str:
        """The topic of `kind` (a per-sensor field name, e.g. 'ft_wrench') for FT sensor `sensor`."""
        return getattr(self, kind).replace("{sensor}", sensor)


_MAT_TEMPLATE_KEYS = ("ft", "temperature", "accelerometer", "gyroscope")
_MAT_PATH_KEYS = ("joint_positions", "joint_velocities", "joint_torques")


@dataclass(frozen=True)
class MatParams:
    """Section `ingest.mat`: where ingest finds each quantity in a YarpRobotLoggerDevice .mat file.

    Paths are channel names with ``/`` between struct levels (the logger's ``::``), below the file's
    top-level struct. Per-sensor entries are lists of templates tried in order (the first channel that
    exists wins), in which ``{sensor}`` stands for the logger's name of a URDF FT sensor: the URDF
    name itself, or its entry in `sensor_names`.
    """

    joint_positions: str  # rad, the time base (joint order from the file's description_list)
    joint_velocities: str  # rad/s, the logger's own (-> dq_enc)
    joint_torques: str  # Nm (-> tau_enc)
    ft: tuple[str, ...]  # 6 values: fx fy fz (N), mx my mz (Nm), by position
    temperature: tuple[str, ...]  # 1 value, deg C
    accelerometer: tuple[str, ...]  # 3 values, m/s^2
    gyroscope: tuple[str, ...]  # 3 values, rad/s
    sensor_names: Mapping[str, str] = field(default_factory=dict)  # URDF sensor -> logger name
    sidecar_suffix: str = ".yaml"  # experiment metadata file: <log stem><suffix> beside the .mat

    def __post_init__(self) -> None:
        for key in _MAT_PATH_KEYS:
            _check_name(getattr(self, key), f"ingest.mat.{key}")
        for key in _MAT_TEMPLATE_KEYS:
            value = getattr(self, key)
            if isinstance(value, str):
                value = (value,)
            if not isinstance(value, list | tuple) or not value:
                raise ConfigError(
                    f"ingest.mat.{key} must be a non-empty list of channel templates, got {value!r}"
                )
            for k, template in enumerate(value):
                _check_name(template, f"ingest.mat.{key}[{k}]")
                if "{sensor}" not in template:
                    raise ConfigError(f"ingest.mat.{key}[{k}] must contain {{sensor}}, got {template!r}")
            object.__setattr__(self, key, tuple(value))
        names = self.sensor_names if self.sensor_names is not None else {}
        if not isinstance(names, Mapping):
            raise ConfigError(f"ingest.mat.sensor_names must be a mapping, got {names!r}")
        for urdf_name, logger_name in names.items():
            _check_name(urdf_name, "ingest.mat.sensor_names key")
            _check_name(logger_name, f"ingest.mat.sensor_names.{urdf_name}")
        object.__setattr__(self, "sensor_names", dict(names))
        check_suffix(self.sidecar_suffix, "ingest.mat.sidecar_suffix")

    @classmethod
    def from_mapping(cls, data: Any) -> MatParams:
        """Build from the parsed `ingest.mat` mapping (exactly the dataclass's keys)."""
        if isinstance(data, cls):
            return data
        data = _mapping(data, "ingest.mat")
        _section(data, "ingest.mat", set(cls.__dataclass_fields__))
        return cls(**data)

    def channels(self, key: str, sensor: str) -> tuple[str, ...]:
        """The candidate channels of per-sensor quantity `key` (e.g. 'ft') for URDF FT sensor `sensor`."""
        name = self.sensor_names.get(sensor, sensor)
        return tuple(t.replace("{sensor}", name) for t in getattr(self, key))


def mat_section(params: Params) -> MatParams:
    """`ingest.mat` of params.yaml, validated (errors prefixed with the params file)."""
    where = params.raw.get("__file__", PARAMS_FILE)
    try:
        ingest = _mapping(params.raw.get("ingest"), "ingest")
        if "mat" not in ingest:
            raise ConfigError("missing key ingest.mat")
        return MatParams.from_mapping(ingest["mat"])
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None


@dataclass(frozen=True)
class Params:
    """The whole of params.yaml: typed shared sections plus the raw dict for the stage sections."""

    seed: int  # master seed, in [0, 2**32)
    robot: RobotParams
    topics: TopicParams
    raw: Mapping[str, Any] = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        s = self.seed
        if isinstance(s, bool) or not isinstance(s, int) or not 0 <= s < _MAX_SEED:
            raise ConfigError(f"seed must be an integer in [0, 2**32), got {s!r}")


@dataclass(frozen=True)
class LabelParams:
    """Section `label` of params.yaml (stage `label`; see the comments there). Thresholds are in robot-weight
    units (fractions of the URDF's total mass times gravity), so the same values hold for any robot."""

    contact_on: float  # fraction of robot weight: a foot's normal force above this -> touching
    contact_off: float  # fraction of robot weight: below this -> not touching
    guard_s: float  # s: half-width of the guard band around every contact change
    zero_quantile: float  # the foot's zero level is the median of its readings below this quantile
    cut_max_sensors: int  # cut sets (summed labels) of 2 to this many FT sensors; 1 = none
    imu_check: Any  # label.imu_check: pipeline.labels.imu_params.ImuCheckParams (built there)
    inertials: str  # the labels' inertial parameters: urdf or identified (checked in imu_params)
    identify: Any  # label.identify: pipeline.labels.imu_params.IdentifyParams (built there)

    def __post_init__(self) -> None:
        for name in ("contact_on", "contact_off", "guard_s", "zero_quantile"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ConfigError(f"label.{name} must be a number, got {v!r}")
            object.__setattr__(self, name, float(v))
        if not 0.0 < self.contact_off < self.contact_on < 1.0:
            raise ConfigError(
                f"label.contact_off and label.contact_on must satisfy 0 < contact_off < contact_on < 1 "
                f"(fractions of the robot weight), got {self.contact_off} and {self.contact_on}"
            )
        if not 0.0 <= self.guard_s <= 1.0:
            raise ConfigError(f"label.guard_s must be in [0, 1] s, got {self.guard_s}")
        if not 0.01 <= self.zero_quantile <= 0.5:
            raise ConfigError(f"label.zero_quantile must be in [0.01, 0.5], got {self.zero_quantile}")
        m = self.cut_max_sensors
        if isinstance(m, bool) or not isinstance(m, int) or not 1 <= m <= 6:
            raise ConfigError(f"label.cut_max_sensors must be an integer in [1, 6], got {m!r}")


@dataclass(frozen=True)
class ExportParams:
    """Section `export` of params.yaml: which model of each group is exported, and the export's checks."""

    models: Mapping[str, str]  # group -> model exported instead of the recommended one (nn7, poly2, ...)
    tolerance_float32_ulps: float  # float32 steps at each sensor's largest |output|: max |float32 graph -
    #                                the project's float32 prediction| (relative: a heavier robot's wrench
    #                                has coarser float32 steps)
    tolerance_float64: float  # N and Nm: max |float64 graph - the project's float64 model|

    def __post_init__(self) -> None:
        models = self.models if self.models is not None else {}
        if not isinstance(models, Mapping):
            raise ConfigError(f"export.models must be a mapping group -> model name, got {models!r}")
        for group, name in models.items():
            _check_name(name, f"export.models.{group}")
        object.__setattr__(self, "models", dict(models))
        for key, unit in (("tolerance_float32_ulps", "float32 steps"), ("tolerance_float64", "N, Nm")):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value < math.inf:
                raise ConfigError(f"export.{key} must be a positive number ({unit}), got {value!r}")
            object.__setattr__(self, key, float(value))


# --- loading -----------------------------------------------------------------------------------


def display_path(path: Path) -> str:
    """The path as the user would write it: relative to the working directory when under it."""
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def _section(data: Mapping[str, Any], key: str, expected: set[str]) -> None:
    """Check that mapping `data` (at dotted `key`) has exactly the expected keys."""
    unknown = sorted(str(k) for k in data if k not in expected)
    if unknown:
        allowed = ", ".join(sorted(expected))
        raise ConfigError(f"unknown key {key}.{unknown[0]} (allowed: {allowed})")
    missing = sorted(expected - set(data))
    if missing:
        raise ConfigError(f"missing key {key}.{missing[0]}")


def _mapping(value: Any, key: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise ConfigError(f"{key} must be a mapping, got {value!r}")
    return value


def _parse(data: Any) -> Params:
    if data is None:
        raise ConfigError("the file is empty")
    data = _mapping(data, "the top level")
    for key in ("seed", "robot"):
        if key not in data:
            raise ConfigError(f"missing key {key}")
    robot = _mapping(data["robot"], "robot")
    # foot_pairs is optional: absent (or null), the feet are derived from the URDF; a robot without foot
    # pairs may also say `foot_pairs: {}`.
    _section({"foot_pairs": None, "serials": None, **robot}, "robot", set(RobotParams.__dataclass_fields__))
    pairs = None
    if robot.get("foot_pairs") is not None:
        pairs = []
        for name, pair in _mapping(robot["foot_pairs"], "robot.foot_pairs").items():
            key = f"robot.foot_pairs.{name}"
            pair = _mapping(pair, key)
            _section(pair, key, {"front", "rear", "sole"})
            pairs.append(FootPairParams(name=name, front=pair["front"], rear=pair["rear"], sole=pair["sole"]))
    robot_params = RobotParams(
        robot["urdf"], robot["gravity"], None if pairs is None else tuple(pairs), robot.get("serials")
    )
    if "topics" not in data:
        raise ConfigError("missing key topics")
    topics = _mapping(data["topics"], "topics")
    _section(topics, "topics", set(TopicParams.__dataclass_fields__))
    return Params(seed=data["seed"], robot=robot_params, topics=TopicParams(**topics), raw=dict(data))


def stage_section(params: Params, key: str, cls: type[T]) -> T:
    """Build a stage's frozen params dataclass `cls` from section `key` of params.yaml.

    Every field of `cls` must be present and no other key; the dataclass's ``__post_init__`` checks the
    values (raising ConfigError naming ``<key>.<field>``). Errors are prefixed with the params file.
    """
    where = params.raw.get("__file__", PARAMS_FILE)
    try:
        if key not in params.raw:
            raise ConfigError(f"missing section {key}")
        data = _mapping(params.raw[key], key)
        _section(data, key, set(cls.__dataclass_fields__))
        return cls(**data)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    except TypeError as exc:  # a value of the wrong type that __post_init__ did not catch
        raise ConfigError(f"{where}: {key}: {exc}") from None


# Every stage section of params.yaml and the validator that builds it: called when params.yaml is
# loaded, whichever stage runs, so a typo anywhere is reported at once with its dotted key. A validator
# is "module:function(params)" or "module:Class" (built with `stage_section`).
SECTIONS: dict[str, str] = {
    "simulate": "pipeline.sim.params:simulate_params",
    "ingest": "pipeline.logs.params:IngestParams",
    "smooth": "pipeline.logs.smoothing:SmoothParams",
    "label": "pipeline.labels.imu_params:label_params",
    "train": "pipeline.calib.params:TrainParams",
    "evaluate": "pipeline.evaluation.params:EvaluateParams",
    "export": "pipeline.core.config:ExportParams",
    "deploy": "pipeline.deploy.params:deploy_params",
}
SHARED_KEYS = ("seed", "robot", "topics")


def validate_sections(params: Params) -> None:
    """Build every stage section of `params` (ConfigError naming the dotted key if one is invalid).

    A section may be absent (a params file for some stages only); an unknown top-level key is an error.
    """
    import importlib

    unknown = sorted(
        str(k) for k in params.raw if k not in SECTIONS and k not in SHARED_KEYS and k != "__file__"
    )
    if unknown:
        raise ConfigError(f"unknown key {unknown[0]} (allowed: {', '.join([*SHARED_KEYS, *SECTIONS])})")
    for key, ref in SECTIONS.items():
        if key not in params.raw:
            continue
        module, name = ref.split(":")
        validator = getattr(importlib.import_module(module), name)
        if isinstance(validator, type):
            stage_section(params, key, validator)
        else:
            validator(params)


def load_params(path: str | Path | None = None) -> Params:
    """Load and validate params.yaml (default: ``<repo_root()>/params.yaml``) over the defaults
    (`pipeline.core.defaults`: every key the file does not set takes its default).

    Raises:
        ConfigError: the file is missing or unreadable, is not valid YAML, or has a missing, unknown
            or invalid key; the message starts with the file name and names the dotted key.
    """
    path = Path(path) if path is not None else repo_root() / PARAMS_FILE
    try:
        lab = read_yaml_file(path)
        if lab is None:
            raise ConfigError("the file is empty")
        params = _parse(resolve(_mapping(lab, "the top level"))[0])
        params.raw["__file__"] = display_path(path)  # type: ignore[index]
    except ConfigError as exc:
        raise ConfigError(f"{display_path(path)}: {exc}") from None
    try:
        validate_sections(params)
    except ConfigError as exc:  # stage_section already names the file
        message, where = str(exc), display_path(path)
        raise ConfigError(message if message.startswith(where) else f"{where}: {message}") from None
    return params
