"""Section `ingest` of params.yaml: tolerances of the alignment, bad-log policy, the .mat name map."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from pipeline.core.errors import ConfigError


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
    mat: Any = None  # MatParams (section ingest.mat): where .mat logger files keep each quantity

    def __post_init__(self) -> None:
        if not isinstance(self.source, str) or not self.source.strip():
            raise ConfigError(f"ingest.source must be a non-empty path, got {self.source!r}")
        for key in ("max_gap_s", "max_gap_temperature_s", "max_reorder_s"):
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
