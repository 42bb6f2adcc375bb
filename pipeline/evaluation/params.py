"""Params and names of the evaluation: section `evaluate` of params.yaml, references, output files."""

from __future__ import annotations

import math
from dataclasses import dataclass

from pipeline.calib.registry import nn_name
from pipeline.core.errors import ConfigError

STAGE = "evaluate"
ORACLE = "oracle"  # the simulator's oracle calibration, an extra model in the tables (truth tables only)
LABELS, TRUTH = "labels", "truth"  # references the errors are computed against
NO_TRUTH = "no truth: against labels on held-out segments"  # recorded test logs, in the metrics and the page
# truth scored on the labelled samples only: like for like with LABELS (TRUTH also covers the samples
# without labels, e.g. double support, where a model interpolates without supervision)
TRUTH_LABELLED = "truth_labelled"
REFERENCES = (LABELS, TRUTH_LABELLED, TRUTH)
REFERENCE_TITLES = {
    LABELS: "labels",
    TRUTH_LABELLED: "truth (labelled samples)",
    TRUTH: "truth (all samples)",
}
NN6, NN7, NN13 = nn_name(6), nn_name(7), nn_name(13)  # wrench; + temperature; + IMU
# Outputs, under the reports directory: evaluate@<group> writes GROUPS_DIR/<group>/ (GROUP_REPORT and
# PLOTS_DIR), METRICS_DIR/<group>/<headline>.json (for `dvc metrics`) and PLOTS_DATA_DIR/*/<group>*.csv (for
# `dvc plots`); the report stage writes REPORT_FILE and PLOTS_DIR (the overview figures).
GROUPS_DIR = "groups"
GROUP_REPORT = "report.json"
METRICS_DIR = "metrics"
REPORT_FILE = "index.html"
DEPLOYMENT_PAGE = "deployment.html"  # the deployment tests' page beside it (pipeline.deploy.page)
PLOTS_DIR = "plots"
IDENTIFIED_FIGURE = f"{PLOTS_DIR}/identified_parts.png"  # the label stage's parts.png, copied by `report`
PLOTS_DATA_DIR = "plots_data"
TRAIN_METRICS = "metrics.json"  # in models/<group>/
PREDICTIONS = "predictions.parquet"
# In-memory columns that evaluate adds to a group's prediction table (never written to Parquet).
EXPERIMENT = "experiment"  # experiment type of the sample's log (pole, balancing, ...)
PHASE = "phase"  # contact phase of the sample (pipeline.evaluation.phases: single, double, pole, air, other)
SPEED = "speed"  # rad/s: angular speed of the group's FT boards (gyroscope norm, low-passed; max over boards)
MAX_STEP = 1.5  # a stamp step above this many nominal periods splits a contiguous stretch


@dataclass(frozen=True)
class EvaluateParams:
    """Section `evaluate` of params.yaml (see the comments there)."""

    highpass_hz: float  # Hz: noise = what a high-pass at this cutoff keeps
    highpass_order: int  # Butterworth order (applied forward and backward)
    still_gyro_rad_s: float  # rad/s: quasi-static below this angular speed of the FT boards
    still_min_s: float  # s: shortest quasi-static run
    noise_threshold: float  # noise amplification above this (worst axis) flags a model ...
    noise_margin: float  # ... by more than this fraction of it (so last-bit differences cannot flip it)
    zoom_s: float  # s: length of the per-experiment zoom of the time-series plots
    target_raw_over_nn7: float  # acceptance: raw RMSE / NN7 RMSE at least this
    target_nn7_over_oracle: float  # acceptance: NN7 RMSE / oracle RMSE at most this
    fidelity_tolerance: float  # a model whose virtual-push slope (pipeline.calib.fidelity) on any axis is
    # farther than this from 1 is flagged unfaithful and not recommended
    memory_tolerance: float  # a model with memory whose slope at a push's onset differs from its held
    # one by more than this (any axis, any scale) is flagged unfaithful: its memory stands in for the wrench

    def __post_init__(self) -> None:
        for name in (
            "highpass_hz",
            "still_gyro_rad_s",
            "still_min_s",
            "noise_threshold",
            "noise_margin",
            "zoom_s",
            "target_raw_over_nn7",
            "target_nn7_over_oracle",
            "fidelity_tolerance",
            "memory_tolerance",
        ):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, int | float)
                or not math.isfinite(value)
                or value <= 0
            ):
                raise ConfigError(f"evaluate.{name} must be a positive number, got {value!r}")
            object.__setattr__(self, name, float(value))
        order = self.highpass_order
        if isinstance(order, bool) or not isinstance(order, int) or not 1 <= order <= 8:
            raise ConfigError(f"evaluate.highpass_order must be an integer in [1, 8], got {order!r}")

    @property
    def noise_limit(self) -> float:
        """Output-noise ratio (worst axis, model / raw) above which a model is flagged: the threshold
        widened by the margin (2.0 with 0.25 -> 2.5), so ratios that move in the last bits between runs
        cannot flip a flag. The one rule of `evaluate` and of the deployment's Test A."""
        return self.noise_threshold * (1.0 + self.noise_margin)
