"""The two floors of a simulated sensor's error against the truth, and the warning when a model beats them.

- The oracle inverts each sensor's *static* distortion exactly (`pipeline.sim.distortion.oracle_inverse`):
  its error is the white noise plus the hysteresis it cannot know.
- The noise floor is the white noise alone: ``raw - distorted`` of the simulator's truth (the reading minus
  its noise-free value, static part and hysteresis), per sample in the reading's units (N, Nm), a foot
  pair's mapped to the sole frame as its sum is. No memoryless calibration can go below it.

A memoryless model may sit a little below the oracle legitimately: fitted on moving data, it absorbs part of
the hysteresis's minor-loop gain. A model with memory (`pipeline.calib.registry`: play, arx) goes below
it honestly, down to the noise floor, by undoing the hysteresis from the reading's path. Below the noise
floor any model can only be reading a prior over the robot's motions (its training relation), not the
sensor. `prior_notes` says which, per headline and model, where a model beats the oracle against the truth
on all test samples.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from pipeline.calib.registry import has_memory
from pipeline.logs import schema as S

GroupReport = Any  # pipeline.evaluation.results.GroupReport (which imports this module)

NOISE = "noise"  # column prefix ``noise.<name>.<axis>``: the reading's white noise (N, Nm)
MARK = "&#8224;"  # the footnote mark of a summary cell below the oracle (dagger)


def noise_columns(
    frame: Any,
    sensors: Sequence[str],
    pairs: Mapping[str, Sequence[str]],
    names: Sequence[str],
    transforms: Mapping[str, np.ndarray],
) -> dict[str, np.ndarray]:
    """``noise.<name>.<axis>`` columns (raw - distorted; a pair's parts mapped and summed with its (2, 6, 6)
    transforms), for every name, where the frame holds both; else none."""
    per: dict[str, np.ndarray] = {}
    for s in sensors:
        raw, clean = S.wrench_cols(S.FT, s), S.wrench_cols(S.DISTORTED, s)
        if raw[0] in frame and clean[0] in frame:
            per[s] = frame[raw].to_numpy(np.float64) - frame[clean].to_numpy(np.float64)
    for pair, members in pairs.items():
        if all(s in per for s in members) and pair in transforms:
            per[pair] = np.einsum(
                "sij,nsj->ni", transforms[pair], np.stack([per[s] for s in members], axis=1)
            )
    return {c: per[n][:, a] for n in names if n in per for a, c in enumerate(S.wrench_cols(NOISE, n))}


def noise_floor(frame: Any, names: Sequence[str]) -> dict[str, float]:
    """name -> RMS of its white noise, the 6 axes pooled as the headline RMSE pools them (N and Nm), over
    the test samples with truth; names without the columns are left out."""
    out = {}
    for name in names:
        cols = S.wrench_cols(NOISE, name)
        true = S.wrench_cols(S.TRUE, name)
        if cols[0] not in frame or true[0] not in frame:
            continue
        noise = frame[cols].to_numpy(np.float64)
        ok = np.isfinite(noise).all(axis=1) & np.isfinite(frame[true].to_numpy(np.float64)).all(axis=1)
        if ok.any():
            out[name] = float(np.sqrt(np.mean(noise[ok] ** 2)))
    return out


def below_oracle(r: GroupReport, name: str, model: str | None) -> tuple[float, float, float | None] | None:
    """(the model's RMSE, the oracle's, the noise floor) against the truth on all test samples, when the
    model (not the oracle, not raw) beats the oracle there; else None."""
    from pipeline.evaluation.params import ORACLE, TRUTH

    if model in (None, ORACLE, "raw"):
        return None
    rmse, oracle = r.headline_rmse(TRUTH, model, name=name), r.headline_rmse(TRUTH, ORACLE, name=name)
    if rmse is None or oracle is None or rmse >= oracle:
        return None
    return rmse, oracle, r.floor.get(name)


_PRIOR = (
    "impossible for a calibration of the sensor alone; it reads a prior over the robot's motions (its "
    "training relation), not the sensor, and will misreport what its training did not show"
)
_GAIN = (
    "part of the sensor's hysteresis absorbed as gain, which a memoryless model can do; a warning, not a win"
)
_MEMORY = "its memory undoes the sensor's hysteresis, which is what the noise floor leaves to be undone"


def prior_notes(results: Sequence[GroupReport], models: Sequence[str]) -> list[tuple[bool, bool, str]]:
    """Per (group, headline, model among `models` or the deployed one) below the oracle: whether it asks
    for a look (below the noise floor, or a memoryless model between the two), whether it is the deployed
    model, and one sentence."""
    notes = []
    for r in results:
        for name in r.headlines or [r.headline]:
            for model in dict.fromkeys([*models, r.recommended]):
                found = below_oracle(r, name, model)
                if found is None:
                    continue
                rmse, oracle, floor = found
                memory = has_memory(str(model))
                if floor is not None and rmse < floor:
                    look, why = True, f"below the noise floor ({floor:.3g}) too: {_PRIOR}"
                else:
                    where = (
                        f"above the noise floor ({floor:.3g})" if floor is not None else "(no noise floor)"
                    )
                    look, why = not memory, f"{where}: {_MEMORY if memory else _GAIN}"
                notes.append(
                    (
                        look,
                        model == r.recommended,
                        f"{MARK} {r.group} / {name}: <b>{model}</b> scores {rmse:.3g} against the truth on "
                        f"all test samples, below the oracle ({oracle:.3g}), {why}.",
                    )
                )
    return notes


def prior_box(results: Sequence[GroupReport], models: Sequence[str]) -> str:
    """The page's one line on the models below the oracle (empty when none is), the sentences folded below;
    a warning only where one asks for a look (`prior_notes`), else a green line."""
    from pipeline.evaluation.html import warning

    notes = prior_notes(results, models)
    if not notes:
        return ""
    head = (
        "The oracle inverts each simulated sensor's static distortion exactly, so a memoryless model below "
        "it is either absorbing the hysteresis's minor-loop gain (between the oracle and the noise floor, "
        "the white noise raw - distorted of the simulator's truth) or reading a prior over the robot's "
        "motions, not the sensor (below the noise floor). A model with memory (play, arx) may go down to "
        "the noise floor: it undoes the hysteresis from the reading's path; below it, it too reads a prior "
        "(or averages the noise over time, which a push sees as lag)."
    )
    deployed = sum(look and mine for look, mine, _ in notes)
    others = sum(look and not mine for look, mine, _ in notes)
    if deployed:
        summary = f"{deployed} deployed model(s) ask for a look"
    else:
        summary = f"{len(notes)} model(s) below the oracle, no deployed one asking for a look"
    summary += f" ({others} not deployed do)" if others else ""
    items = "".join(f"<li>{n}</li>" for _, _, n in notes)
    return warning("Below the oracle", summary, f"<p>{head}</p><ul>{items}</ul>", ok=not deployed)
