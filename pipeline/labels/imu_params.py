"""Sections ``label.imu_check`` and ``label.identify`` of params.yaml: the thresholds of the FT boards' IMU
check, and the identification of the robot's inertial parameters.

The check and the reasons for its defaults: `pipeline.labels.imu_check`; the identification:
`pipeline.labels.inertials`, `pipeline.labels.identify`. Light imports only (no numpy): params are validated
when they are loaded, whichever stage runs (`pipeline.core.config.SECTIONS`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

from pipeline.core.config import LabelParams, Params, stage_section
from pipeline.core.errors import ConfigError
from pipeline.core.play import checked_widths, width_rows

KEY = "label.imu_check"


def _from_mapping(cls: Any, key: str, data: Any) -> Any:
    """`cls` (a params dataclass of section `key`) from its parsed mapping, exactly its fields, or itself."""
    if isinstance(data, cls):
        return data
    if not isinstance(data, dict):
        raise ConfigError(f"{key} must be a mapping, got {data!r}")
    for name in sorted(set(data) ^ {f.name for f in fields(cls)}):
        raise ConfigError(f"{'unknown' if name in data else 'missing'} key {key}.{name}")
    return cls(**data)


@dataclass(frozen=True)
class ImuCheckParams:
    """Section ``label.imu_check`` of params.yaml (the comments there; `pipeline.labels.imu_check`)."""

    still_gyro_rad_s: float  # quasi-static: the board turns slower than this (kinematics and gyroscope)
    still_acc_m_s2: float  # ... its frame accelerates less than this (without gravity)
    still_min_s: float  # ... for at least this long
    min_spread_deg: float  # gravity (or the rotation axis) seen along directions at least this far apart
    max_rms_m_s2: float  # a map fits within this residual RMS per axis; every other must leave twice it
    gyro_min_rad_s: float  # the gyroscope is compared where the board turns faster than this
    gyro_max_rms_rad_s: float  # the gyroscope's map fits within this; every other must leave twice it

    def __post_init__(self) -> None:
        for name in (f.name for f in fields(self)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not 0 < v < math.inf:
                raise ConfigError(f"{KEY}.{name} must be a positive number, got {v!r}")
            object.__setattr__(self, name, float(v))
        if self.min_spread_deg > 90:
            raise ConfigError(f"{KEY}.min_spread_deg must be at most 90, got {self.min_spread_deg:g}")

    @classmethod
    def from_mapping(cls, data: Any) -> ImuCheckParams:
        """From the parsed mapping (exactly the dataclass's keys), or itself."""
        return _from_mapping(cls, KEY, data)


IDENTIFY_KEY = "label.identify"


@dataclass(frozen=True)
class IdentifyParams:
    """Section ``label.identify`` of params.yaml (the comments there; `pipeline.labels.identify`)."""

    step: int  # every step-th exact sample of each training log
    weight: float  # each sample's weight in the posterior (the samples of a log are strongly correlated)
    shrink: float  # a part is identified where the data shrink its mass's sd to at most this x the prior's
    reject_p: float  # ... and re-estimated where its change rejects the URDF's values at this significance
    play_widths_n: tuple[float, ...]  # the sensor model's play operators (hysteresis) on force axes, N ...
    play_widths_nm: tuple[float, ...]  # ... and torque axes, Nm (as many)

    def __post_init__(self) -> None:
        if isinstance(self.step, bool) or not isinstance(self.step, int) or self.step < 1:
            raise ConfigError(f"{IDENTIFY_KEY}.step must be a positive integer, got {self.step!r}")
        for name in ("weight", "shrink", "reject_p"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not 0 < v < math.inf:
                raise ConfigError(f"{IDENTIFY_KEY}.{name} must be a positive number, got {v!r}")
            object.__setattr__(self, name, float(v))
        for name in ("shrink", "reject_p"):
            if getattr(self, name) >= 1:
                raise ConfigError(f"{IDENTIFY_KEY}.{name} must be below 1, got {getattr(self, name)!r}")
        widths = checked_widths(IDENTIFY_KEY, self.play_widths_n, self.play_widths_nm)
        object.__setattr__(self, "play_widths_n", widths[0])
        object.__setattr__(self, "play_widths_nm", widths[1])

    def widths(self) -> tuple[tuple[float, ...], ...]:
        """The play operators' widths, one row per operator (K, 6: force axes N, torque axes Nm)."""
        return width_rows(self.play_widths_n, self.play_widths_nm)

    @classmethod
    def from_mapping(cls, data: Any) -> IdentifyParams:
        """From the parsed mapping (exactly the dataclass's keys), or itself."""
        return _from_mapping(cls, IDENTIFY_KEY, data)


def label_params(params: Params) -> LabelParams:
    """Section ``label`` with its ``imu_check`` and ``identify`` built (errors start with the params file,
    name the key)."""
    cfg = stage_section(params, "label", LabelParams)
    try:
        if cfg.inertials not in ("urdf", "identified"):
            raise ConfigError(f"label.inertials must be 'urdf' or 'identified', got {cfg.inertials!r}")
        return replace(
            cfg,
            imu_check=ImuCheckParams.from_mapping(cfg.imu_check),
            identify=IdentifyParams.from_mapping(cfg.identify),
        )
    except ConfigError as exc:
        raise ConfigError(f"{params.raw.get('__file__', 'params.yaml')}: {exc}") from None


__all__ = ["IdentifyParams", "ImuCheckParams", "label_params"]
