"""Contact phases of labelled samples, and a headline's error per phase.

A sample's phase follows from its contact set (the ``contacts`` column of a labelled table: declared by
the experiment or detected from the foot forces) and the foot pairs of the labelled metadata
``ftcal.label``:

- ``single``: the links in contact all lie on one foot (a whole sole, or its front or rear half);
- ``double``: they lie on two feet (and nowhere else);
- ``pole``: no foot touches, another link is held (the robot on the pole, root_link clamped);
- ``air``: no contact at all;
- ``other``: feet and another link at once (shown only where such samples exist).

A link lies on a foot when it is the foot's sole or, when the metadata has the foot pair's cut set
(``cut_sets.*.label`` = the pair, ``part`` = the links of the isolated part), on the foot's side of that
cut (the side holding the sole). Guard bands are not excluded here: against the truth every sample of a
phase counts; against the labels only the samples where the headline's switch is 1 do (never in a guard
band).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.calib.registry import complexity, families, in_family
from pipeline.evaluation.params import ORACLE

SINGLE, DOUBLE, POLE, AIR, OTHER = "single", "double", "pole", "air", "other"
PHASES = (SINGLE, DOUBLE, POLE, AIR)  # always in the tables (0 samples where none); OTHER only if present
PHASE_TITLES = {
    SINGLE: "single support",
    DOUBLE: "double support",
    POLE: "pole (held, no foot contact)",
    AIR: "in the air (no contact)",
    OTHER: "other (feet and a held link)",
}
PHASE_KEYS = ("rmse", "rmse_force", "rmse_torque")  # N and Nm pooled, N, Nm


@dataclass(frozen=True)
class Foot:
    """A foot pair's links: its sole, and the links of its pair's cut set (`part`) with the side of it
    the foot is on (`inside`: the foot's links are those in `part`, else those not in it)."""

    sole: str
    part: frozenset[str] | None = None
    inside: bool = False

    def holds(self, link: str) -> bool:
        """Whether `link` lies on this foot."""
        if link == self.sole:
            return True
        return self.part is not None and (link in self.part) == self.inside


def feet_of(label_meta: Mapping[str, Any]) -> dict[str, Foot]:
    """Foot -> `Foot` from a labelled table's ``ftcal.label`` metadata: its ``feet`` (every foot, one
    or two sensors, with the links its sensors cut off), else its foot pairs (module docstring)."""
    feet = label_meta.get("feet") or {}
    if feet:
        return {
            str(name): Foot(str(f.get("sole") or ""), frozenset(str(x) for x in f.get("links") or ()), True)
            for name, f in feet.items()
        }
    pairs = label_meta.get("pairs") or {}
    cuts = {
        str(c.get("label")): c for c in (label_meta.get("cut_sets") or {}).values() if isinstance(c, dict)
    }
    out = {}
    for name, pair in pairs.items():
        sole = str((pair or {}).get("sole") or "")
        cut = cuts.get(str(name)) or {}
        part = cut.get("part")
        if isinstance(part, list) and part:
            links = frozenset(str(link) for link in part)
            out[str(name)] = Foot(sole, links, inside=sole in links)
        else:
            out[str(name)] = Foot(sole)
    return out


def phase_of(contacts: str, feet: Mapping[str, Foot]) -> str:
    """The phase (module docstring) of one contact set, a comma-separated list of links."""
    links = [c for c in str(contacts).split(",") if c]
    if not links:
        return AIR
    touching = {name for name, foot in feet.items() for link in links if foot.holds(link)}
    held = [link for link in links if not any(foot.holds(link) for foot in feet.values())]
    if not touching:
        return POLE
    if held:
        return OTHER
    return SINGLE if len(touching) == 1 else DOUBLE


def phases_of(contacts: np.ndarray, feet: Mapping[str, Foot]) -> np.ndarray:
    """(N,) object array of phases of the contact sets `contacts` (N,) (None/NaN read as no contact)."""
    values = np.array(["" if not isinstance(c, str) else c for c in contacts], dtype=object)
    keys, inverse = np.unique(values.astype(str), return_inverse=True)
    return np.array([phase_of(k, feet) for k in keys], dtype=object)[inverse.reshape(-1)]


def phase_models(models: Sequence[str], ranking: Sequence[str], recommended: str | None) -> list[str]:
    """The models of the phase tables, in order: every family's models simplest first (of a family shown
    by its best on validation, `Family.one_on_tables`, the polynomials: that one; a family not
    `Family.on_tables`, the offset, left out), then the recommended model and the oracle (those the group
    has, each once)."""
    wanted = []
    for family in families():
        own = [m for m in models if in_family(m, family.key)]
        if not family.on_tables:
            continue
        if family.one_on_tables:
            own = [m for m in ranking if m in own][:1]
        wanted += sorted(own, key=complexity)
    wanted += [recommended or "", ORACLE]
    return [m for m in dict.fromkeys(wanted) if m in models]


def phase_table(
    preds: Mapping[str, np.ndarray],
    target: np.ndarray,
    mask: np.ndarray,
    phases: np.ndarray,
    scorer: Any,
) -> dict[str, dict[str, Any]]:
    """phase -> {"samples": int, "models": {model -> {rmse, rmse_force, rmse_torque}}} of predictions
    (model -> (N, 6)) against `target` (N, 6) on `mask` (N,) split by `phases` (N,); `scorer(pred, ref,
    mask)` is `results.score`. Every phase of PHASES is present (0 samples: values None); OTHER if any."""
    present = [p for p in (*PHASES, OTHER) if p in PHASES or bool(np.any(phases == p))]
    out: dict[str, dict[str, Any]] = {}
    finite_target = np.isfinite(target).all(axis=1)
    for phase in present:
        m = mask & (phases == phase) & finite_target
        row: dict[str, Any] = {"samples": int(m.sum()), "models": {}}
        for model, pred in preds.items():
            errors = scorer(pred, target, m)
            row["models"][model] = {
                k: (None if not np.isfinite(errors[k]) else float(errors[k])) for k in PHASE_KEYS
            }
        out[phase] = row
    return out
