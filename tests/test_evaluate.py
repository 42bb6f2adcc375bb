"""Stage `evaluate`: metrics against hand computation, the noise-amplification ratio on synthetic signals,
quasi-static segments, and end to end on a tiny synthetic models dir with labelled and truth tables (real
files, real MLflow sqlite store): metrics.json, plot data, report page, MLflow run; bad input."""

from __future__ import annotations

import html
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
import yaml

from pipeline.cli import main
from pipeline.core.config import load_params, stage_section
from pipeline.core.errors import ConfigError, DataError
from pipeline.evaluation import noise as N_
from pipeline.evaluation import results as R
from pipeline.evaluation.inputs import load_group
from pipeline.evaluation.params import EvaluateParams
from pipeline.logs import schema as S
from pipeline.logs.schema import prediction_cols
from tests.factories.labelled import FRONT, LEG, PAIR, REAR, TRANSFORMS
from tests.factories.params import repo_params, write_evaluate_params
from tests.factories.reports import CV, FS, LOGS, NOISE, NOTE, N, build_fixture, evaluate_both

pytestmark = pytest.mark.slow  # trains the groups it evaluates

ROOT = Path(__file__).resolve().parents[1]


# --- errors --------------------------------------------------------------------------------------


def test_score_matches_hand_computation() -> None:
    pred = np.array([[1.0, 2, 3, 0.1, 0.2, 0.3], [0, 0, 0, 0, 0, 0], [5, 5, 5, 5, 5, 5]])
    ref = np.array([[0.0, 0, 0, 0, 0, 0], [1, -1, 2, 0.5, 0, 0], [np.nan] * 6])  # row 2: no label
    s = R.score(pred, ref)
    err = (pred - ref)[:2]
    assert s["samples"] == 2
    assert s["mse"] == pytest.approx(np.mean(err**2))
    assert s["mae"] == pytest.approx(np.mean(np.abs(err)))
    assert s["rmse"] == pytest.approx(math.sqrt(np.mean(err**2)))
    assert s["rmse_force"] == pytest.approx(math.sqrt((1 + 4 + 9 + 1 + 1 + 4) / 6))
    assert s["mae_torque"] == pytest.approx((0.1 + 0.2 + 0.3 + 0.5) / 6)
    assert s["mse_fz"] == pytest.approx((9 + 4) / 2)
    assert s["rmse_tx"] == pytest.approx(math.sqrt((0.01 + 0.25) / 2))
    masked = R.score(pred, ref, np.array([True, False, True]))
    assert masked["samples"] == 1 and masked["mse_fy"] == pytest.approx(4.0)
    assert math.isnan(R.score(pred, ref, np.zeros(3, bool))["rmse"])


def test_ratio_is_none_when_undefined() -> None:
    assert R.ratio(10.0, 2.0) == 5.0
    assert R.ratio(None, 2.0) is None
    assert R.ratio(1.0, 0.0) is None
    assert R.ratio(math.nan, 1.0) is None


# --- noise ---------------------------------------------------------------------------------------


def _signal(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A slow wrench (N, 6) and raw = wrench + white noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / FS
    w = np.column_stack([20 * np.sin(2 * np.pi * 0.3 * t + k) for k in range(6)])
    return w, w + rng.normal(size=(n, 6)) * NOISE


def test_noise_ratio_copy_noisier_smoother() -> None:
    n = 3000
    w, raw = _signal(n)
    seg = np.zeros(n, dtype=np.int64)
    mask = np.ones(n, dtype=bool)
    mask[:50] = mask[-50:] = False  # away from the ends, where the moving average below is biased
    hf = lambda x: N_.highpass(x, seg, FS, 5.0, 4)  # noqa: E731
    raw_hf = hf(raw)
    # a model that copies raw (plus an offset) passes its noise unchanged
    np.testing.assert_allclose(N_.noise_ratio(hf(raw + 30.0), raw_hf, mask), 1.0, rtol=1e-9)
    # one adding white noise of the raw's std: sqrt(2) in expectation
    noisy = raw + np.random.default_rng(1).normal(size=(n, 6)) * NOISE
    r = N_.noise_ratio(hf(noisy), raw_hf, mask)
    assert (r > 1.25).all() and (r < 1.6).all()
    # a smoother (centred 9-sample moving average) removes most of it
    kernel = np.ones(9) / 9
    smooth = np.column_stack([np.convolve(raw[:, k], kernel, mode="same") for k in range(6)])
    r = N_.noise_ratio(hf(smooth), raw_hf, mask)
    assert (r < 0.5).all()
    # the slow signal itself is not "noise": the high-pass of the clean wrench is tiny
    assert (np.std(hf(w)[100:-100], axis=0) < 0.01 * np.std(raw_hf, axis=0) + 1e-3).all()


def test_segment_ids_split_at_logs_and_lost_samples() -> None:
    stamp = (np.r_[0, 1, 2, 3, 5, 6, 0, 1, 2] * 10_000_000).astype(np.int64)  # sample 4 of log a lost
    log = np.array(["a"] * 6 + ["b"] * 3)
    seg, fs = N_.segment_ids(log, stamp)
    assert fs == pytest.approx(100.0)
    np.testing.assert_array_equal(seg, [0, 0, 0, 0, 1, 1, 2, 2, 2])


def test_highpass_keeps_stretches_apart_and_marks_short_ones() -> None:
    x = np.r_[np.zeros(200), np.full(10, 50.0), np.zeros(300)][:, None]
    seg = np.r_[np.zeros(200), np.ones(10), np.full(300, 2)].astype(np.int64)
    out = N_.highpass(x, seg, FS, 5.0, 4)
    assert np.isnan(out[200:210]).all()  # too short for the filter
    np.testing.assert_allclose(out[:200], 0.0, atol=1e-12)  # the step in between does not leak
    np.testing.assert_allclose(out[210:], 0.0, atol=1e-12)


def test_quasi_static_mask_runs_contacts_guard_edges() -> None:
    n = 1000
    speed = np.full(n, 0.01)
    speed[400:450] = 1.0  # moving: splits the log
    contacts = np.array(["a"] * 700 + ["b"] * 300, dtype=object)  # contact change at 700
    guard = np.zeros(n, dtype=bool)
    guard[880:900] = True
    seg = np.zeros(n, dtype=np.int64)
    mask = N_.quasi_static_mask(speed, contacts, guard, seg, FS, max_speed=0.3, min_s=1.0, edge_s=0.2)
    # 20 edge samples out at both ends; runs [20, 400), [450, 700) and [700, 880) are >= 1 s (100 samples);
    # [900, 980) is 80 samples: dropped
    expected = np.zeros(n, dtype=bool)
    expected[20:400] = expected[450:700] = expected[700:880] = True
    np.testing.assert_array_equal(mask, expected)
    assert not N_.quasi_static_mask(speed, contacts, guard, seg, FS, 0.3, 5.0, 0.2).any()


def test_recommend_skips_flagged_models() -> None:
    assert R.recommend(["nn13", "nn7", "raw"], ["nn13"], ["raw", "nn7", "nn13"]) == "nn7"
    assert R.recommend(["nn13"], ["nn13"], ["nn13"]) is None


def test_bad_params_name_the_key(tmp_path: Path) -> None:
    data = repo_params()
    data["evaluate"]["noise_threshold"] = -1
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"evaluate\.noise_threshold must be a positive number, got -1"):
        stage_section(load_params(path), "evaluate", EvaluateParams)


def test_repo_params_are_valid() -> None:
    cfg = stage_section(load_params(ROOT / "params.yaml"), "evaluate", EvaluateParams)
    assert cfg.highpass_hz > 0 and cfg.noise_threshold > 1


# --- end to end ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """evaluate@<group> of both groups, then the report, on the synthetic fixture, in a real MLflow store."""
    root = tmp_path_factory.mktemp("evaluate")
    dirs = build_fixture(root)
    results, out = evaluate_both(root, dirs)
    return {"results": results, "out": out, "dirs": dirs, "root": root}


def _report(evaluated: dict[str, Any], group: str) -> dict[str, Any]:
    return json.loads((evaluated["out"] / "groups" / group / "report.json").read_text())


def test_group_report_has_every_table_and_small_metrics(evaluated: dict[str, Any]) -> None:
    for name, group in ((LEG, LEG), (PAIR, PAIR), (FRONT, PAIR), (REAR, PAIR)):
        tables = _report(evaluated, group)["tables"]
        for ref in ("labels", "truth"):
            for model in ("raw", "affine", "nn7", "nn13", "oracle"):
                for metric in ("mse", "mae", "rmse"):
                    for suffix in ("", "_force", "_torque", *(f"_{a}" for a in S.WRENCH_AXES)):
                        value = tables[name][ref][model][f"{metric}{suffix}"]
                        assert isinstance(value, float) and math.isfinite(value)
    for group in (LEG, PAIR):
        text = (evaluated["out"] / "metrics" / group / f"{group}.json").read_text()
        row = json.loads(text)
        tables = _report(evaluated, group)["tables"][group]["truth"]
        assert row["deployed"] == "nn7" and row["against"] == "truth"  # nn13 is noise-flagged
        for key, model in (("rmse", "nn7"), ("oracle", "oracle"), ("raw", "raw")):
            assert row[key] == pytest.approx(tables[model]["rmse"], rel=1e-3), key
        assert row["verdict"] in ("at noise floor", "beats oracle", "at oracle", "above oracle", "scored")
        assert {"deployed", "against", "rmse", "oracle", "raw", "verdict"} <= set(row)
        assert set(row) <= {"deployed", "against", "rmse", "oracle", "floor", "raw", "verdict"}
        assert "NaN" not in text  # nothing dvc could not parse


def test_errors_match_an_independent_computation(evaluated: dict[str, Any]) -> None:
    r_pair, r_leg = evaluated["results"][PAIR], evaluated["results"][LEG]
    dirs = evaluated["dirs"]
    frames = [
        pq.read_table(dirs["ingested"] / f"{log}{S.TRUTH_SUFFIX}.parquet").to_pandas() for log, *_ in LOGS
    ]
    pred = pd.read_parquet(dirs["models"] / PAIR / "predictions.parquet")
    truth = pd.concat(frames, ignore_index=True).set_index(S.STAMP).loc[pred[S.STAMP]]
    true_sum = (
        truth[S.wrench_cols(S.TRUE, FRONT)].to_numpy() @ TRANSFORMS[0].T
        + truth[S.wrench_cols(S.TRUE, REAR)].to_numpy() @ TRANSFORMS[1].T
    )
    oracle_sum = (
        truth[S.wrench_cols(S.ORACLE, FRONT)].to_numpy() @ TRANSFORMS[0].T
        + truth[S.wrench_cols(S.ORACLE, REAR)].to_numpy() @ TRANSFORMS[1].T
    )
    err = oracle_sum - true_sum
    assert r_pair.tables[PAIR]["truth"]["oracle"]["rmse"] == pytest.approx(math.sqrt(np.mean(err**2)))
    nn7 = pred[prediction_cols("nn7", PAIR)].to_numpy()
    assert r_pair.tables[PAIR]["truth"]["nn7"]["mae_torque"] == pytest.approx(
        np.mean(np.abs(nn7 - true_sum)[:, 3:])
    )
    # labels: only where the switch is 1 (the walking log has half of them at 0)
    leg = pd.read_parquet(dirs["models"] / LEG / "predictions.parquet")
    m = leg[S.switch_col(LEG)].to_numpy() == 1
    e = leg[prediction_cols("raw", LEG)].to_numpy()[m] - leg[S.wrench_cols(S.EXPECTED, LEG)].to_numpy()[m]
    assert r_leg.tables[LEG]["labels"]["raw"]["samples"] == m.sum() < len(leg)
    assert r_leg.tables[LEG]["labels"]["raw"]["mse_fy"] == pytest.approx(np.mean(e[:, 1] ** 2))
    ratios = r_leg.ratios()
    assert ratios["raw_over_nn7"]["labels"] == pytest.approx(
        r_leg.headline_rmse("labels", "raw") / r_leg.headline_rmse("labels", "nn7")
    )


def test_noise_check_flags_the_noisy_network_and_recommends_the_next(evaluated: dict[str, Any]) -> None:
    for group in (LEG, PAIR):
        r = evaluated["results"][group]
        # only the still pole log is quasi-static (the walking log turns and changes contacts)
        assert 3.0 < r.noise.quasi_static_s < N / FS
        assert r.noise.ratio["raw"] == pytest.approx(1.0)
        assert r.noise.ratio["affine"] == pytest.approx(1.0)
        assert r.noise.ratio["nn13"] > 2.5
        assert r.noise.signal_fraction < 0.1
        assert r.best_on_validation == "nn13" and r.recommended == "nn7"
        assert r.noise.flagged == ["nn13"]


def test_report_page_and_plots(evaluated: dict[str, Any]) -> None:
    out = evaluated["out"]
    page = (out / "index.html").read_text()
    for group, names in ((LEG, (LEG,)), (PAIR, (PAIR, FRONT, REAR))):
        plots = out / "groups" / group / "plots"
        pngs = sorted(p.name for p in plots.glob("*.png"))
        for name in names:
            for kind in ("timeseries", "zoom", "residuals", "rmse"):
                assert f"{name}_{kind}.png" in pngs
        assert "loss.png" in pngs and "noise.png" in pngs
        for png in pngs:
            assert f'src="groups/{group}/plots/{png}"' in page
            assert (plots / png).stat().st_size > 5000
    for png in ("rmse_overview.png", "noise_amplification.png"):
        assert f'src="plots/{png}"' in page and (out / "plots" / png).stat().st_size > 5000
    assert "<b>Noise flags:</b> " in page and f"{LEG}/nn13" in page
    assert "<b>Not trained:</b> 1 network(s)" in page and f"<li>{html.escape(NOTE)}</li>" in page
    answer = page.index("<table class='num answer'>")  # the answer first: one row per headline
    assert answer < page.index("<b>Noise flags:</b>") < page.index("Every model, per headline")
    heads = sum(len(_report(evaluated, g).get("headlines") or [g]) for g in (LEG, PAIR))
    assert page[answer : page.index("</table>", answer)].count("<tr>") == 1 + heads  # a row per headline
    assert page.count("<table") >= 2 + 4 * (2 * 3 + 2)  # summary, noise; per name: refs x metrics + per type
    loss = (out / "plots_data" / "loss" / LEG / "nn7.csv").read_text().splitlines()
    assert loss[0] == "epoch,train_loss,val_rmse" and len(loss) == 6
    for sub in ("rmse_labels", "rmse_truth"):
        rmse = pd.read_csv(out / "plots_data" / sub / f"{PAIR}.csv")
        assert list(rmse["model"]) == ["raw", "affine", "nn7", "nn13", "oracle"]
        assert (rmse["rmse"] > 0).all()
    noise = pd.read_csv(out / "plots_data" / "noise" / f"{LEG}.csv").set_index("model")
    assert noise.loc["raw", "ratio"] == pytest.approx(1.0) and noise.loc["nn13", "ratio"] > 2.5


def test_mlflow_run_has_metrics_tags_and_artifacts(evaluated: dict[str, Any]) -> None:
    from mlflow import MlflowClient

    client = MlflowClient(f"sqlite:///{evaluated['root'] / 'mlflow.db'}")
    run = client.get_run(evaluated["results"][PAIR].run_id)
    assert run.info.status == "FINISHED" and run.data.tags["dvc.stage"] == f"evaluate@{PAIR}"
    assert run.data.tags["recommended"] == "nn7" and run.data.tags["flagged"] == "nn13"
    assert run.data.metrics[f"{PAIR}.truth.oracle.rmse"] > 0
    assert run.data.metrics["noise_ratio.nn13"] > 2.5
    artifacts = {a.path for a in client.list_artifacts(run.info.run_id)}
    assert {"report.json", "plots"} <= artifacts
    assert len(client.list_artifacts(run.info.run_id, "plots")) >= 14


# --- bad input -----------------------------------------------------------------------------------


def test_cli_missing_models_dir_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    params = write_evaluate_params(tmp_path)
    args = [LEG, str(tmp_path / "nope"), str(tmp_path), str(tmp_path / "out"), "--params", str(params)]
    code = main(["evaluate", *args])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.count("\n") == 0
    assert (
        err == f"ftcal: error: {tmp_path / 'nope'}: no models for group {LEG} (run `dvc repro train@{LEG}`)"
    )


def test_group_without_predictions_is_a_data_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    dirs = build_fixture(tmp_path)
    (dirs["models"] / PAIR / "predictions.parquet").unlink()
    params = write_evaluate_params(tmp_path)
    cfg = stage_section(load_params(params), "evaluate", EvaluateParams)
    with pytest.raises(DataError, match=r"r_foot/predictions\.parquet: group r_foot has no test predictions"):
        load_group(PAIR, dirs["models"] / PAIR, dirs["labelled"], dirs["ingested"], cfg)
    code = main(
        [
            "evaluate",
            PAIR,
            str(dirs["models"] / PAIR),
            str(dirs["labelled"]),
            str(tmp_path / "out"),
            "--params",
            str(params),
        ]
    )
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("ftcal: error: ") and err.count("\n") == 0
    assert "predictions.parquet" in err


def test_missing_labelled_test_log_is_a_data_error(tmp_path: Path) -> None:
    dirs = build_fixture(tmp_path)
    (dirs["labelled"] / "11_walking_test.parquet").unlink()
    cfg = stage_section(load_params(write_evaluate_params(tmp_path)), "evaluate", EvaluateParams)
    with pytest.raises(
        DataError, match=r"11_walking_test\.parquet: labelled table of test log 11_walking_test not found"
    ):
        load_group(LEG, dirs["models"] / LEG, dirs["labelled"], dirs["ingested"], cfg)


# --- contact phases, cross-validation, exact-label availability ----------------------------------


def test_phase_tables_match_an_independent_computation(evaluated: dict[str, Any]) -> None:
    dirs, r = evaluated["dirs"], evaluated["results"][LEG]
    pred = pd.read_parquet(dirs["models"] / LEG / "predictions.parquet")
    parts = []
    for log, *_ in LOGS:
        lab = pq.read_table(dirs["labelled"] / f"{log}.parquet", columns=[S.STAMP, S.CONTACTS]).to_pandas()
        tru = pq.read_table(dirs["ingested"] / f"{log}{S.TRUTH_SUFFIX}.parquet").to_pandas()
        parts.append(lab.merge(tru[[S.STAMP, *S.wrench_cols(S.TRUE, LEG)]], on=S.STAMP))
    ref = pd.concat(parts, ignore_index=True).set_index(S.STAMP).loc[pred[S.STAMP]]
    phase = (
        ref[S.CONTACTS].map({"root_link": "pole", "r_sole": "single", "l_sole,r_sole": "double"}).to_numpy()
    )
    assert r.phase_models == ["raw", "affine", "nn7", "nn13", "oracle"]  # no polynomial in this group
    truth, labels = r.phases[LEG]["truth"], r.phases[LEG]["labels"]
    assert list(truth) == ["single", "double", "pole", "air"]
    assert truth["pole"]["samples"] == N - 1 and truth["air"]["samples"] == 0
    assert truth["single"]["samples"] + truth["double"]["samples"] == N - 1
    labelled = pred[S.switch_col(LEG)].to_numpy() == 1
    assert (
        labels["double"]["samples"] == 0
        and labels["single"]["samples"] == (labelled & (phase == "single")).sum()
    )
    true = ref[S.wrench_cols(S.TRUE, LEG)].to_numpy()
    for name in ("single", "double"):
        m = phase == name
        err = pred[prediction_cols("nn7", LEG)].to_numpy()[m] - true[m]
        got = truth[name]["models"]["nn7"]
        assert got["rmse"] == pytest.approx(math.sqrt(np.mean(err**2)))
        assert got["rmse_torque"] == pytest.approx(math.sqrt(np.mean(err[:, 3:] ** 2)))
    assert truth["air"]["models"]["nn7"]["rmse"] is None
    page = (evaluated["out"] / "index.html").read_text()
    assert page.count("RMSE per contact phase") == 2  # one per headline (LEG, PAIR)


def test_cv_passes_through_to_the_page_only_where_train_wrote_it(evaluated: dict[str, Any]) -> None:
    assert _report(evaluated, PAIR)["cv"] == CV and _report(evaluated, LEG)["cv"] is None
    page = (evaluated["out"] / "index.html").read_text()
    assert page.count("Cross-validation behind the recommendation") == 1
    section = page[page.index("Cross-validation behind") :]
    assert "<td>0.42</td><td>0.97</td><td>0.695</td><td>0.275</td>" in section  # nn13: folds, mean, spread
    assert "<b>nn7</b> (chosen)" in page


def test_label_availability_counts_every_labelled_log(evaluated: dict[str, Any]) -> None:
    from pipeline.evaluation.availability import label_availability

    avail = label_availability(evaluated["dirs"]["labelled"])
    walking = pq.read_table(evaluated["dirs"]["labelled"] / f"{LOGS[1][0]}.parquet").to_pandas()
    double = walking[S.CONTACTS].to_numpy() == "l_sole,r_sole"
    guard = walking[S.GUARD].to_numpy()
    leg = walking[S.switch_col(LEG)].to_numpy() == 1
    assert avail["labels"] == {LEG: "sensor", PAIR: "foot pair"}
    assert avail["types"]["pole"] == {"logs": 1, "samples": N, "guard": 0, "exact": {LEG: N, PAIR: N}}
    assert avail["types"]["walking"]["exact"][LEG] == leg.sum() < N
    assert avail["types"]["walking"]["guard"] == guard.sum() > 0
    ds = avail["double"]["walking"]
    assert ds["samples"] == (double & ~guard).sum() and ds["guard"] == (double & guard).sum() > 0
    assert ds["exact"] == {LEG: 0, PAIR: ds["samples"]}
    assert list(avail["double"]) == ["walking"]
    page = (evaluated["out"] / "index.html").read_text()
    assert "Exact-label availability" in page and "double support outside guard bands" in page
