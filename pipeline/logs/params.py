"""Section `ingest` of params.yaml: alignment tolerances, bad-log policy, the .mat and dataDumper maps."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from pipeline.core.errors import ConfigError
from pipeline.logs.imu_axes import parse_axis_maps


@dataclass(frozen=True)
class IngestParams:
    """Section `ingest` of params.yaml (see the comments there)."""

    source: str  # directory searched recursively for *.mcap and *.mat; dvc.yaml passes it to the command
    max_gap_s: float  # s, wrench/IMU/truth: widest gap between two messages that is interpolated
    max_gap_temperature_s: float  # s, the same for the (slow) temperature stream
    max_reorder_s: float  # s, largest step back of stamps in arrival order that is re-sorted
    max_nonfinite_fraction: float  # fraction of a topic's messages that may hold NaN/inf (dropped)
    skip_bad_logs: bool  # true: a bad log is a warning and is skipped; false: an error
    unstamped_fallback: bool = False  # true: all-zero header stamps -> log time minus the measured delay
    max_frozen_s: float = 0.1  # s: identical FT readings spanning longer than this are a frozen board
    mat: Any = None  # MatParams (section ingest.mat): where .mat logger files keep each quantity
    dumper: Any = None  # DumperParams (section ingest.dumper): the ports and joints of dataDumper runs
    # FT sensor -> its board's IMU axes in the sensor frame (pipeline.logs.imu_axes), mapped at ingest
    imu_axes: Any = None
    # URDF joint -> deg: a joint a lab knows was still at this position where a log does not have it
    fixed_joints: Any = None

    def __post_init__(self) -> None:
        if not isinstance(self.source, str) or not self.source.strip():
            raise ConfigError(f"ingest.source must be a non-empty path, got {self.source!r}")
        for key in ("max_gap_s", "max_gap_temperature_s", "max_reorder_s", "max_frozen_s"):
            value = getattr(self, key)
            if (
                isinstance(value, bool)
                or not isinstance(value, int | float)
                or not math.isfinite(value)
                or value <= 0
            ):
                raise ConfigError(f"ingest.{key} must be a positive number of seconds, got {value!r}")
            object.__setattr__(self, key, float(value))
        f = self.max_nonfinite_fraction
        if isinstance(f, bool) or not isinstance(f, int | float) or not 0 <= f <= 1:
            raise ConfigError(f"ingest.max_nonfinite_fraction must be in [0, 1], got {f!r}")
        object.__setattr__(self, "max_nonfinite_fraction", float(f))
        if not isinstance(self.skip_bad_logs, bool):
            raise ConfigError(f"ingest.skip_bad_logs must be true or false, got {self.skip_bad_logs!r}")
        if not isinstance(self.unstamped_fallback, bool):
            raise ConfigError(
                f"ingest.unstamped_fallback must be true or false, got {self.unstamped_fallback!r}"
            )
        if self.mat is not None:
            from pipeline.core.config import MatParams

            object.__setattr__(self, "mat", MatParams.from_mapping(self.mat))
        if self.dumper is not None:
            object.__setattr__(self, "dumper", DumperParams.from_mapping(self.dumper))
        object.__setattr__(self, "imu_axes", parse_axis_maps(self.imu_axes, "ingest.imu_axes"))
        object.__setattr__(self, "fixed_joints", _fixed_joints(self.fixed_joints))


def _fixed_joints(data: Any) -> dict[str, float]:
    """``ingest.fixed_joints``: joint name -> a finite position in degrees."""
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"ingest.fixed_joints must map joint names to degrees, got {data!r}")
    out = {}
    for name, value in data.items():
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise ConfigError(f"ingest.fixed_joints.{name} must be a position in degrees, got {value!r}")
        out[_name(name, "ingest.fixed_joints key")] = float(value)
    return out


def _name(value: Any, key: str) -> str:
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(f"{key} must be a non-empty string, got {value!r}")
    return value


@dataclass(frozen=True)
class DumperParams:
    """Section `ingest.dumper`: how a YARP dataDumper run's ports map to the contract's streams.

    A run is a folder of port folders (``data.log``, ``info.log``), each port named by its info.log
    (``/icub/right_leg/analog:o``: robot prefix, part, port; `pipeline.logs.dumper`). `ft_ports` maps an
    FT part to its URDF sensor (its `ft_port` carries the wrench); `joints` maps a control-board part to
    the URDF joints of its axes in the board's order (null: an axis the URDF does not have; axes past the
    list are ignored), read from the first of its `joint_ports` the run has (``stateExt:o``: positions,
    velocities, torques; ``state:o``: positions only). The first part of `time_base` present in a run is
    the time base. `ignore`: parts, ``part/port`` names or folders (relative to the run) skipped on
    purpose (any other port is an error).
    """

    ft_port: str  # port of an FT part's wrench, e.g. "analog:o"
    joint_ports: tuple[str, ...]  # ports of a control board's joint states, by preference, e.g. stateExt:o
    ft_ports: Mapping[str, str]  # part -> URDF FT sensor
    joints: Mapping[str, tuple[str | None, ...]]  # part -> URDF joint per axis (None: not in the URDF)
    time_base: tuple[str, ...]  # parts of `joints`, in order of preference as the run's time base
    ignore: tuple[str, ...] = ()  # "part" or "part/port" folders not read
    sidecar_suffix: str = ".yaml"  # experiment metadata: <run><suffix> beside the run folder

    def __post_init__(self) -> None:
        from pipeline.core.config import check_suffix

        key = "ingest.dumper"
        _name(self.ft_port, f"{key}.ft_port")
        ports = self.joint_ports
        if not isinstance(ports, list | tuple) or not ports:
            raise ConfigError(f"{key}.joint_ports must be a non-empty list of port names, got {ports!r}")
        for k, port in enumerate(ports):
            _name(port, f"{key}.joint_ports[{k}]")
        if self.ft_port in ports:
            raise ConfigError(f"{key}.joint_ports: {self.ft_port!r} is also the ft_port")
        object.__setattr__(self, "joint_ports", tuple(ports))
        if not isinstance(self.ft_ports, Mapping) or not self.ft_ports:
            raise ConfigError(f"{key}.ft_ports must be a mapping part -> FT sensor, got {self.ft_ports!r}")
        for part, sensor in self.ft_ports.items():
            _name(part, f"{key}.ft_ports key")
            _name(sensor, f"{key}.ft_ports.{part}")
        if len(set(self.ft_ports.values())) != len(self.ft_ports):
            raise ConfigError(f"{key}.ft_ports maps two parts to the same sensor")
        if not isinstance(self.joints, Mapping) or not self.joints:
            raise ConfigError(f"{key}.joints must be a mapping part -> [joint per axis], got {self.joints!r}")
        seen: dict[str, str] = {}
        joints = {}
        for part, axes in self.joints.items():
            _name(part, f"{key}.joints key")
            if not isinstance(axes, list | tuple) or not axes:
                raise ConfigError(
                    f"{key}.joints.{part} must be a non-empty list of joint names, got {axes!r}"
                )
            for k, joint in enumerate(axes):
                if joint is None:
                    continue
                _name(joint, f"{key}.joints.{part}[{k}]")
                if joint in seen:
                    raise ConfigError(
                        f"{key}.joints.{part}[{k}]: {joint!r} is also in {key}.joints.{seen[joint]}"
                    )
                seen[joint] = part
            joints[part] = tuple(axes)
        object.__setattr__(self, "joints", joints)
        base = self.time_base
        if not isinstance(base, list | tuple) or not base or any(b not in joints for b in base):
            raise ConfigError(
                f"{key}.time_base must be a non-empty list of parts of {key}.joints, got {base!r}"
            )
        object.__setattr__(self, "time_base", tuple(base))
        object.__setattr__(self, "ft_ports", dict(self.ft_ports))
        ignore = self.ignore if self.ignore is not None else ()
        if not isinstance(ignore, list | tuple):
            raise ConfigError(
                f"{key}.ignore must be a list of part or part/port folder names, got {ignore!r}"
            )
        for k, item in enumerate(ignore):
            _name(item, f"{key}.ignore[{k}]")
        object.__setattr__(self, "ignore", tuple(ignore))
        check_suffix(self.sidecar_suffix, f"{key}.sidecar_suffix")

    @classmethod
    def from_mapping(cls, data: Any) -> DumperParams:
        """Build from the parsed `ingest.dumper` mapping (exactly the dataclass's keys)."""
        from pipeline.core.config import _mapping, _section

        if isinstance(data, cls):
            return data
        data = _mapping(data, "ingest.dumper")
        _section(data, "ingest.dumper", set(cls.__dataclass_fields__))
        return cls(**data)
