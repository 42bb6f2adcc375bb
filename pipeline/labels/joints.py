"""Per-joint availability of a log's kinematics, and what each label loses to joints that are not there.

A recording may lack whole joint streams (a dataDumper run without an arm's ``stateExt:o``) or a joint's
positions for a stretch: `smooth` then leaves only that joint's columns NaN and its ``ok.kinematics.<joint>``
False. A label needs only some joints (:mod:`pipeline.physics.needs`): where those are ok it is computed
with the others set to 0; where its contact case makes it exact but a joint it needs is not ok, the sample
is *lost*, and the label *lacks* that joint. The summary names the joint streams as the recording does
(``left_arm/stateExt:o``, from the ingest's ``recording`` record) where it can, else the joints.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from pipeline.logs import schema as S
from pipeline.logs.sidecar import declared_absent


def joint_ok_of(table: pd.DataFrame, joints: Sequence[str]) -> np.ndarray:
    """(N, J) bool: the joint's smoothed kinematics are usable (its ``ok.kinematics.<joint>``, or the
    table's ``ok.kinematics`` where a table has no per-joint flags) and finite."""
    every = table[S.ok_col(S.KINEMATICS_STREAM)].to_numpy(bool)
    flags = [table[c].to_numpy(bool) if c in table else every for c in S.joint_ok_cols(joints)]
    ok = np.column_stack(flags) if flags else np.zeros((len(table), 0), dtype=bool)
    for quantity in (S.QS, S.DQS, S.DDQS):
        ok &= np.isfinite(table[S.joint_cols(quantity, joints)].to_numpy())
    return ok


def joint_streams(meta: Mapping[str, Any]) -> dict[str, str]:
    """Joint -> the recording's name of its absent stream, from a table's metadata (the ingest's
    ``recording`` record; empty where the log declares none)."""
    return declared_absent((meta.get(S.META_SOURCE.decode()) or {}).get("metadata") or {})["joint_streams"]


@dataclass
class Lacking:
    """Per label name: samples lost (exact by contacts, a joint it needs not ok), the joints missing there."""

    lost: dict[str, int] = field(default_factory=dict)
    joints: dict[str, set[int]] = field(default_factory=dict)

    def gate(self, name: str, on: np.ndarray, ok: np.ndarray, needed: np.ndarray) -> np.ndarray:
        """`on` (M,) bool where the joints `needed` (columns) of `ok` (M, J) are all ok; counts the rest."""
        have = ok[:, needed].all(axis=1)
        lost = on & ~have
        if lost.any():
            self.lost[name] = self.lost.get(name, 0) + int(lost.sum())
            missing = ~ok[np.ix_(lost, needed)]
            self.joints.setdefault(name, set()).update(needed[missing.any(axis=0)].tolist())
        return on & have

    def summary(
        self, exact: Mapping[str, int], joint_names: Sequence[str], streams: Mapping[str, str]
    ) -> dict[str, dict[str, Any]]:
        """Label name -> {samples: exact labels, lost: samples lost to missing joints, lacks: the streams
        (or joints) missing there}, for every name of `exact`."""
        out = {}
        for name, samples in exact.items():
            lacks = {streams.get(joint_names[k], joint_names[k]) for k in self.joints.get(name, ())}
            out[name] = {"samples": int(samples), "lost": self.lost.get(name, 0), "lacks": sorted(lacks)}
        return out


def merge_exact(summaries: Sequence[Mapping[str, Mapping[str, Any]]]) -> dict[str, dict[str, Any]]:
    """The `Lacking.summary` entries of several logs added up per label name (lacks: their union)."""
    out: dict[str, dict[str, Any]] = {}
    for summary in summaries:
        for name, entry in summary.items():
            total = out.setdefault(name, {"samples": 0, "lost": 0, "lacks": []})
            total["samples"] += int(entry.get("samples", 0))
            total["lost"] += int(entry.get("lost", 0))
            total["lacks"] = sorted({*total["lacks"], *(entry.get("lacks") or ())})
    return out


def exact_text(name: str, entry: Mapping[str, Any]) -> str:
    """``r_leg_ft 1200 (3000 lost, lacks left_arm/stateExt:o)``: a label's exact samples, what it lacked."""
    lacks = ", ".join(entry.get("lacks") or ())
    if not lacks:
        return f"{name} {entry['samples']}"
    lost = f"{entry['lost']} lost, " if entry["samples"] else ""
    return f"{name} {entry['samples']} ({lost}lacks {lacks})"


__all__ = ["Lacking", "exact_text", "joint_ok_of", "joint_streams", "merge_exact"]
