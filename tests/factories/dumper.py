"""YARP dataDumper runs: where the recorded run lies, and the tolerances of the dumper's printed numbers.

The dumper prints times with 6 decimals, so a stamp comes back within STAMP_TOL_NS (0.5 us of rounding,
plus the 0.12 us of a float64 second at today's epoch) of its MCAP ns value; values are printed with 6
decimals, a column copied from one message within HALF_PRINTED of a printed unit.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[2]
# a recorded dataDumper run of iCub (yoga on the right foot), in ../shared beside developer checkouts
REAL_RUN = REPO.parent / "shared" / "data" / "icub02-yoga-right-foot"
STAMP_TOL_NS = 620
HALF_PRINTED = 0.5e-6


def interpolated_bound(ref: pd.DataFrame, column: str, printed: float, spacing_s: float) -> float:
    """Largest error of an interpolated `column` (in its unit): `printed` (half a printed unit) plus the
    weight change of stamps moved by <= STAMP_TOL_NS (3 x STAMP_TOL_NS / `spacing_s`, the smallest message
    spacing in s) times twice the largest step between two of `ref`'s samples."""
    step = np.nanmax(np.abs(np.diff(ref[column].to_numpy())))
    return printed + 3 * STAMP_TOL_NS * 1e-9 / spacing_s * 2 * step + 1e-12
