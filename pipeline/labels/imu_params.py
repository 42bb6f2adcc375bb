"""Section ``label.imu_check`` of params.yaml: the thresholds of the FT boards' IMU check.

The check and the reasons for the defaults: `pipeline.labels.imu_check`. Light imports only (no numpy):
params are validated when they are loaded, whichever stage runs (`pipeline.core.config.SECTIONS`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

from pipeline.core.config import LabelParams, Params, stage_section
from pipeline.core.errors import ConfigError

KEY = "label.imu_check"


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
        if isinstance(data, cls):
            return data
        if not isinstance(data, dict):
            raise ConfigError(f"{KEY} must be a mapping, got {data!r}")
        names = {f.name for f in fields(cls)}
        for key in sorted(set(data) ^ names):
            what = "unknown" if key in data else "missing"
            raise ConfigError(f"{what} key {KEY}.{key}")
        return cls(**data)


def label_params(params: Params) -> LabelParams:
    """Section ``label`` with its ``imu_check`` built (errors start with the params file, name the key)."""
    cfg = stage_section(params, "label", LabelParams)
    try:
        return replace(cfg, imu_check=ImuCheckParams.from_mapping(cfg.imu_check))
    except ConfigError as exc:
        raise ConfigError(f"{params.raw.get('__file__', 'params.yaml')}: {exc}") from None


__all__ = ["ImuCheckParams", "label_params"]
