"""Labels recomputed with iDynTree (the test oracle) from the same smoothed kinematics."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.logs import schema as S
from tests.idyntree_ref import IDynTreeFT

GRAVITY = np.array([0.0, 0.0, -9.80665])


def relabel_with_idyntree(labelled: Path, smoothed: Path, robot_source: str, samples: int = 500) -> float:
    """Max |label - iDynTree| (N, Nm) over `samples` labelled samples spread over the table, every sensor
    whose switch is 1 there. `robot_source`: URDF path or icub-models name. Joints the log lacks (NaN
    kinematics: an absent joint stream) get random values: a label whose switch is 1 does not need them."""
    from pipeline.physics.robot import load_robot

    robot = load_robot(robot_source)
    table = pd.read_parquet(labelled)
    kin_table = pd.read_parquet(smoothed).set_index(S.STAMP).reindex(table[S.STAMP].to_numpy())
    oracle = IDynTreeFT(robot.urdf_path, robot.joint_names)
    rows = np.flatnonzero((table[[S.switch_col(s) for s in robot.sensors]].to_numpy() == 1).any(axis=1))
    assert rows.size, f"{labelled}: no labelled sample"
    rows = rows[np.linspace(0, len(rows) - 1, min(samples, rows.size)).astype(int)]
    worst, compared = 0.0, 0
    for (contacts, fixed), group in table.iloc[rows].groupby([S.CONTACTS, S.FIXED_LINK]):
        idx = group.index.to_numpy()
        kin = [kin_table[S.joint_cols(k, robot.joint_names)].to_numpy()[idx] for k in (S.QS, S.DQS, S.DDQS)]
        rng = np.random.default_rng(len(idx))
        kin = [np.where(np.isfinite(k), k, rng.uniform(-1.0, 1.0, k.shape)) for k in kin]
        ref = oracle.expected(*kin, contacts.split(","), fixed, GRAVITY)
        for s in robot.sensors:
            on = group[S.switch_col(s)].to_numpy() == 1
            if on.any():
                diff = group[S.wrench_cols(S.EXPECTED, s)].to_numpy()[on] - ref[s][on]
                worst = max(worst, float(np.abs(diff).max()))
                compared += int(on.sum())
    assert compared >= min(samples, rows.size)
    return worst
