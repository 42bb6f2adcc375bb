"""The deployment verdict: every group's results of a day gathered, its few numbers and whether it passes.

A day is fit to deploy when every test passes: Test A, no deployed model flagged for output noise (and its
noise measured); Test B, raw / calibrated RMSE against the truth at least ``evaluate.target_raw_over_nn7``
for every calibrated sensor and foot sum; Test C, raw / calibrated RMSE of the judged joint's torque
(``deploy.figure_joint``) at least ``deploy.torque_target``; Test D, every pushed sensor's deployed
calibration following the pushes as the oracle does (`pipeline.deploy.interaction.judge`), and following
the virtual pushes of every scale as the oracle does (`pipeline.deploy.scales.judge`). Otherwise it is
time to recalibrate.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

RESULT_FILE = "result.json"  # a group's results of every day (`pipeline.stages.deploy_test`)
REZEROED = "rezeroed"  # a day's tests after re-zeroing from its first still seconds (its key in the results)


def merge(groups: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """One day's result from its groups' (group -> `pipeline.deploy.group.run_day` result): the logs,
    Test A per group, Tests B, C and D per sensor (and foot sum)."""
    out: dict[str, Any] = {"logs": []}
    for group, result in groups.items():
        out["logs"] = out["logs"] or list(result.get("logs", []))
        for test, value in result.items():
            if test == "logs":
                continue
            if test == "test_a":
                out.setdefault(test, {})[group] = value
            else:
                out.setdefault(test, {}).update(value)
    return out


def summarize(result: dict[str, Any], dp: Any, target_b: float, joint: str) -> dict[str, Any]:
    """The day's few numbers for `dvc metrics` and its verdict (fit to deploy, or time to recalibrate):
    each test's (``a.passed``, ...) and the day's (``fit_to_deploy``). `result`: every group's results of
    the day (`merge`); `target_b`: Test B's least raw / calibrated RMSE ratio against truth; `joint`: the
    suffix of the joints whose torque RMSE ratio Test C judges (``deploy.torque_target``)."""
    out: dict[str, Any] = {}
    for group, a in result.get("test_a", {}).items():
        out[f"a.{group}.deployed_noise_ratio"] = a["models"][a["deployed"]]["worst"]
        out[f"a.{group}.flagged"] = sorted(m for m, r in a["models"].items() if r["flagged"])
    for name, b in result.get("test_b", {}).items():
        if "truth" in b:
            out[f"b.{name}.rmse_truth_raw"] = b["truth"]["raw"]["rmse"]
            out[f"b.{name}.rmse_truth_calibrated"] = b["truth"]["calibrated"]["rmse"]
            out[f"b.{name}.ratio"] = b["ratio_truth"]
    for c in result.get("test_c", {}).values():
        for j, v in c["joints"].items():
            if j.endswith(joint):
                out[f"c.{j}.rmse_raw"] = v["raw"]["rmse"]
                out[f"c.{j}.rmse_calibrated"] = v["calibrated"]["rmse"]
                out[f"c.{j}.ratio"] = v["ratio_rmse"]
                out[f"c.{j}.ratio_max"] = v["ratio_max"]
    for sensor, d in result.get("test_d", {}).items():
        verdict = d["verdict"]
        for key in ("worst_slope_excess", "change_ratio", "slope_gap", "rmse_ratio"):
            if verdict.get(key) is not None:
                out[f"d.{sensor}.{key}"] = verdict[key]
        out[f"d.{sensor}.passed"] = verdict["pass"]
    from pipeline.deploy.scales import summary_keys

    out.update(summary_keys(result.get("test_d_scales", {})))
    # a deployed model whose noise could not be measured (no quasi-static stretch) has not passed Test A
    deployed = [a["models"][a["deployed"]] for a in result.get("test_a", {}).values()]
    ok_a = all(not r["flagged"] and math.isfinite(r["worst"]) for r in deployed)
    ok_b = all(v >= target_b for k, v in out.items() if k.startswith("b.") and k.endswith(".ratio"))
    ok_c = all(v >= dp.torque_target for k, v in out.items() if k.startswith("c.") and k.endswith(".ratio"))
    ok_d = all(d["verdict"]["pass"] for d in result.get("test_d", {}).values())
    ok_ds = bool(out.get("ds.passed", True))  # Test D from the noise level up (pipeline.deploy.scales)
    out.update({"a.passed": ok_a, "b.passed": ok_b, "c.passed": ok_c, "d.passed": ok_d})
    out["fit_to_deploy"] = bool(ok_a and ok_b and ok_c and ok_d and ok_ds)
    return out


def headline(summary: dict[str, Any]) -> dict[str, Any]:
    """A day's few numbers for `dvc metrics show`: the verdict (``fit``), the smallest Test B and Test C
    ratios (raw / calibrated against truth: ``b_min``, ``c_min``), the largest output noise ratio of a
    deployed model (``a_max``), Test D's worst slope excess over the oracle's error and its worst ratio of
    the pushes' change error to the oracle's (``d_slope``, ``d_change``); every number is in
    deployment/details.json."""

    def pick(prefix: str, suffix: str) -> list[float]:
        return [v for k, v in summary.items() if k.startswith(prefix) and k.endswith(suffix)]

    out: dict[str, Any] = {"fit": summary["fit_to_deploy"]}
    for key, values, best in (
        ("b_min", pick("b.", ".ratio"), min),
        ("c_min", pick("c.", ".ratio"), min),
        ("a_max", pick("a.", ".deployed_noise_ratio"), max),
        ("d_slope", pick("d.", ".worst_slope_excess"), max),
        ("d_change", pick("d.", ".change_ratio"), max),
    ):
        if values:
            out[key] = round(float(best(values)), 4)
    from pipeline.deploy.scales import headline_keys

    out.update(headline_keys(summary))
    return out
