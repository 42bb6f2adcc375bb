"""The answer per headline: the model to deploy, its error against what the logs can judge it by, and a
verdict. One computation, read by `dvc metrics show` (reports/metrics/<group>/<name>.json, one row each)
and by the first table of the report page.

On simulated test logs a headline is judged against the truth on every test sample, beside the oracle (the
inverse of each sensor's static distortion: the floor of a memoryless model) and the noise floor (the
white noise alone: the floor of a model with memory):

- ``at noise floor``: within `AT_FLOOR` of the noise floor (what no calibration beats);
- ``beats oracle``: between the two (a model with memory undoing part of the hysteresis);
- ``at oracle``: within `AT_ORACLE` above the oracle (the best a memoryless map can do);
- ``above oracle``: more than that above it (a calibration a lab should not accept);
- ``below floor``: under the noise floor, which a calibration of the sensor cannot reach: the model reads
  a prior over the robot's motions.

On recorded test logs there is no truth: the headline is judged against the labels of the held-out
segments, beside the plain least-squares affine map (``ls``, the reference a lab computes itself):
``<= least squares`` (within `SAME`), ``above least squares`` (the page says why), ``worse than raw``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from pipeline.calib.exact import NOT_CALIBRATED_TEXT
from pipeline.calib.params import LS_AFFINE
from pipeline.calib.registry import RAW
from pipeline.evaluation.params import LABELS, ORACLE, TRUTH
from pipeline.evaluation.residual import SAME
from pipeline.evaluation.results import GroupReport

AT_FLOOR = 0.15  # within this fraction above the noise floor: at it
AT_ORACLE = 0.10  # within this fraction above the oracle: at it
TRUTH_ALL = "truth"  # the reference of a simulated headline: the true wrench on every test sample
HELD_OUT = "held-out labels"  # of a recorded one: the labels of the held-out segments


@dataclass(frozen=True)
class Answer:
    """One headline's answer (errors: global RMSE, the 6 axes pooled, N and Nm; None where not scored).

    against: `TRUTH_ALL` or `HELD_OUT`; ls: the plain least squares' error (recorded logs only); detail: one
    sentence saying what the verdict means for this headline (the page folds it under the row)."""

    group: str
    name: str
    deployed: str
    against: str | None
    rmse: float | None
    oracle: float | None
    floor: float | None
    raw: float | None
    ls: float | None
    verdict: str
    detail: str

    @property
    def bad(self) -> bool:
        """Whether the verdict asks a lab to look before deploying."""
        return self.verdict in ("above oracle", "below floor", "above least squares", "worse than raw")

    def metrics_row(self) -> dict[str, Any]:
        """The `dvc metrics show` row: short keys, numbers to 4 significant digits, nothing missing."""
        row: dict[str, Any] = {"deployed": self.deployed, "against": self.against}
        for key in ("rmse", "ls", "oracle", "floor", "raw"):
            value = getattr(self, key)
            if value is not None:
                row[key] = float(f"{value:.4g}")
        row["verdict"] = self.verdict
        return {k: v for k, v in row.items() if v is not None}


def answers(r: GroupReport) -> list[Answer]:
    """Every headline of `r` (one, or the legs' and feet's of a group trained together), then each sensor
    left out of it; a group not calibrated is one answer saying why."""
    if r.not_calibrated is not None:
        return [_not_calibrated(r.group, r.group, r.not_calibrated)]
    out = [_judged(r, name) for name in r.headlines or [r.headline]]
    return out + [_not_calibrated(r.group, sensor, why) for sensor, why in r.left_out.items()]


def _not_calibrated(group: str, name: str, why: str) -> Answer:
    text = NOT_CALIBRATED_TEXT
    return Answer(group, name, text, None, None, None, None, None, None, text, why)


def _judged(r: GroupReport, name: str) -> Answer:
    deployed = r.recommended or "none"
    truth = r.headline_rmse(TRUTH, deployed, name=name)
    if truth is not None:
        oracle, floor = r.headline_rmse(TRUTH, ORACLE, name=name), r.floor.get(name)
        verdict, detail = _against_truth(deployed, truth, oracle, floor)
        raw = r.headline_rmse(TRUTH, RAW, name=name)
        return Answer(r.group, name, deployed, TRUTH_ALL, truth, oracle, floor, raw, None, verdict, detail)
    rmse, raw = r.headline_rmse(LABELS, deployed, name=name), r.headline_rmse(LABELS, RAW, name=name)
    ls = r.headline_rmse(LABELS, LS_AFFINE, name=name)
    why = (r.held_out.get(name) or {}).get("why_not_lower")
    verdict, detail = _against_labels(deployed, rmse, ls, raw, why)
    return Answer(r.group, name, deployed, HELD_OUT, rmse, None, None, raw, ls, verdict, detail)


def _against_truth(deployed: str, rmse: float, oracle: float | None, floor: float | None) -> tuple[str, str]:
    if floor is not None and rmse < floor:
        return "below floor", (
            f"{deployed} {rmse:.3g} is under the sensor's white noise ({floor:.3g}), which no calibration of "
            "the sensor alone can remove: it reads a prior over the training motions"
        )
    if floor is not None and rmse <= floor * (1 + AT_FLOOR):
        return "at noise floor", f"{deployed} {rmse:.3g} is {rmse / floor - 1:.0%} above the noise floor"
    if oracle is None:
        return "scored", f"{deployed} {rmse:.3g} against the truth (no oracle)"
    if rmse < oracle:
        closed = (oracle - rmse) / (oracle - floor) if floor is not None and oracle > floor else None
        gap = f", {closed:.0%} of the way from the oracle to the noise floor" if closed is not None else ""
        return "beats oracle", f"{deployed} {rmse:.3g} below the oracle {oracle:.3g}{gap}"
    if rmse <= oracle * (1 + AT_ORACLE):
        return "at oracle", f"{deployed} {rmse:.3g} within {AT_ORACLE:.0%} of the oracle {oracle:.3g}"
    return "above oracle", (
        f"{deployed} {rmse:.3g} is {rmse / oracle - 1:.0%} above the oracle {oracle:.3g}, the best any "
        "memoryless map can do: the calibration leaves error a model can remove"
    )


def _against_labels(
    deployed: str, rmse: float | None, ls: float | None, raw: float | None, why: str | None
) -> tuple[str, str]:
    if rmse is None:
        return "not scored", f"{deployed} has no held-out labelled sample"
    if raw is not None and rmse > raw:
        return "worse than raw", f"{deployed} {rmse:.3g} is above raw's {raw:.3g} on the held-out segments"
    if ls is None or rmse <= ls * (1 + SAME):
        plain = f", {LS_AFFINE} {ls:.3g}" if ls is not None else ""
        return "<= least squares", f"{deployed} {rmse:.3g} against the held-out labels{plain}"
    return "above least squares", why or f"{deployed} {rmse:.3g} above {LS_AFFINE} {ls:.3g}"


def answer_rows(results: Sequence[GroupReport]) -> list[Answer]:
    """The answers of every group, in `results` order."""
    return [a for r in results for a in answers(r)]


def answer_table(results: Sequence[GroupReport]) -> str:
    """The page's first table: one row per headline (`answers`), the verdict's detail folded in its cell."""
    from pipeline.evaluation.html import esc, fmt

    rows = answer_rows(results)
    recorded = any(a.against == HELD_OUT for a in rows)
    simulated = any(a.against == TRUTH_ALL for a in rows)
    columns = ["group", "sensor / sum", "deploy", "RMSE", "against"]
    columns += ["oracle", "noise floor"] if simulated else []
    columns += [f"least squares ({LS_AFFINE})"] if recorded else []
    columns += ["raw", "verdict"]
    body = []
    for a in rows:
        cells = [
            esc(a.group),
            esc(a.name),
            f"<b>{esc(a.deployed)}</b>",
            esc(fmt(a.rmse)),
            esc(a.against or ""),
        ]
        cells += [esc(fmt(a.oracle)), esc(fmt(a.floor))] if simulated else []
        cells += [esc(fmt(a.ls))] if recorded else []
        cells.append(esc(fmt(a.raw)))
        tds = "".join(f"<td>{c}</td>" for c in cells)
        cls = "verdict bad" if a.bad else "verdict ok"
        verdict = f"<details><summary>{esc(a.verdict)}</summary>{esc(a.detail)}</details>"
        body.append(f"<tr>{tds}<td class='{cls}'>{verdict}</td></tr>")
    head = "".join(f"<th>{esc(c)}</th>" for c in columns)
    return (
        f"<table class='num answer'><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"
        "<p class='note'>RMSE: the 6 axes pooled (N and Nm) of the model to deploy, against the true wrench "
        "on every test sample (simulated logs) or the labels of the held-out segments (recorded logs). "
        "Oracle: the inverse of each sensor's static distortion (the best memoryless map); noise floor: the "
        "sensor's white noise alone (what no calibration removes). Click a verdict for what it means.</p>"
    )
