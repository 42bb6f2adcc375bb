"""A group's evaluation: error tables against labels and truth, noise check, the model to deploy."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from pipeline.calib.exact import LEFT_OUT, NOT_CALIBRATED, not_calibrated
from pipeline.calib.registry import RAW
from pipeline.calib.scores import wrench_errors
from pipeline.evaluation.fidelity import outside_stats, unfaithful
from pipeline.evaluation.floors import noise_floor
from pipeline.evaluation.inputs import GroupInputs, wrench_of
from pipeline.evaluation.noise import highpass, noise_ratio, quasi_static_mask
from pipeline.evaluation.params import (
    EXPERIMENT,
    LABELS,
    NN7,
    ORACLE,
    PHASE,
    REFERENCES,
    SPEED,
    TRUTH,
    TRUTH_LABELLED,
    EvaluateParams,
)
from pipeline.evaluation.phases import phase_models, phase_table
from pipeline.logs import schema as S
from pipeline.logs.schema import PRED

# --- errors --------------------------------------------------------------------------------------


def score(pred: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """Thesis tables 5.1-5.3 of predictions (N, 6) against references (N, 6), N and Nm, on `mask` (N,).

    Keys ``mse``/``mae``/``rmse`` (global: the 6 components pooled, mixed units as in the thesis), with
    suffixes ``_force``, ``_torque``, ``_<axis>``, and ``samples``; NaN where no sample is left. Samples
    where either side is not finite are left out (a label is NaN where its switch is 0).
    """
    pred = np.asarray(pred, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    keep = np.isfinite(pred).all(axis=1) & np.isfinite(ref).all(axis=1)
    if mask is not None:
        keep &= np.asarray(mask, dtype=bool)
    return wrench_errors(pred[keep], ref[keep])


def ratio(numerator: float | None, denominator: float | None) -> float | None:
    """numerator / denominator, or None when either is missing, not finite, or the denominator is 0."""
    if numerator is None or denominator is None:
        return None
    if not (math.isfinite(numerator) and math.isfinite(denominator)) or denominator == 0:
        return None
    return numerator / denominator


# --- one group -----------------------------------------------------------------------------------


@dataclass
class NoiseResult:
    """Noise amplification of every model of a group on its quasi-static samples."""

    quasi_static_s: float  # s of quasi-static samples
    windows: int  # quasi-static runs
    ratio: dict[str, float | None]  # model -> worst channel's ratio
    ratio_rms: dict[str, float | None]  # model -> root mean square over channels
    per_channel: dict[str, dict[str, float | None]]  # model -> "<name>.<axis>" -> ratio
    worst_channel: dict[str, str | None]  # model -> its worst "<name>.<axis>"
    signal_fraction: float | None  # max over channels of std(HF truth) / std(HF raw); None without truth
    flagged: list[str]
    mask: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0, bool))


@dataclass
class GroupReport:
    """What evaluate@<group> writes (``report.json``) and the report page reads: everything but the samples.

    tables: name -> reference -> model -> errors (`score`); by_experiment: name -> reference -> experiment
    -> model -> global RMSE; names: the sensor, or the pair's sum then front and rear; figures: kind ->
    path relative to the reports directory.
    """

    group: str
    sensors: list[str]
    pair: str | None
    headline: str
    names: list[str]
    models: list[str]
    samples_test: int
    tables: dict[str, Any]
    by_experiment: dict[str, Any]
    noise: NoiseResult
    best_on_validation: str | None
    validation_ranking: list[str]
    recommended: str | None
    histories: dict[str, list[dict[str, float]]] = field(default_factory=dict)  # network -> epochs
    history_source: str = "none"
    train_run: str | None = None  # MLflow run id of train@<group>
    model_versions: dict[str, dict[str, str]] = field(
        default_factory=dict
    )  # network -> {name, version, model_id}
    figures: dict[str, Any] = field(default_factory=dict)
    headlines: list[str] | None = None  # several headlines (legs and feet trained together), else None
    # headline -> reference (labels, truth) -> phase -> {samples, models: model -> rmse, rmse_force,
    # rmse_torque}: the error per contact phase (pipeline.evaluation.phases) of the models `phase_models`
    phases: dict[str, Any] = field(default_factory=dict)
    phase_models: list[str] = field(default_factory=list)
    cv: dict[str, Any] | None = None  # the `cv` entry of models/<group>/metrics.json, where train wrote one
    # virtual-push fidelity (train's `fidelity`: model -> sensor -> slopes), the unfaithful models and why,
    # each sensor's excitation (train's) and the test samples' outside distance (pipeline.evaluation.fidelity)
    fidelity: dict[str, Any] = field(default_factory=dict)
    unfaithful: dict[str, str] = field(default_factory=dict)
    excitation: dict[str, Any] = field(default_factory=dict)
    outside: dict[str, Any] = field(default_factory=dict)
    floor: dict[str, float] = field(default_factory=dict)  # name -> noise floor (pipeline.evaluation.floors)
    # recorded test logs: name -> where the held-out residual comes from (pipeline.evaluation.residual)
    held_out: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)  # train's: a network not trained and why (metrics.json)
    # a group nothing could be calibrated for: why (train's record, `pipeline.calib.exact`); the sensors of a
    # calibrated group left out of it and why; in report.json only where set
    not_calibrated: str | None = None
    left_out: dict[str, str] = field(default_factory=dict)

    def headline_rmse(
        self, ref: str, model: str | None, key: str = "rmse", name: str | None = None
    ) -> float | None:
        """`key` of `model` against `ref` for the headline (or another name of the group)."""
        value = self.tables.get(name or self.headline, {}).get(ref, {}).get(model, {}).get(key)
        return None if value is None or not math.isfinite(value) else float(value)

    def ratios(self, name: str | None = None) -> dict[str, dict[str, float | None]]:
        """raw / nn7 and nn7 / oracle of the headline's (or `name`'s) global RMSE, per reference."""
        out: dict[str, dict[str, float | None]] = {"raw_over_nn7": {}, "nn7_over_oracle": {}}
        for ref in REFERENCES:
            nn7 = self.headline_rmse(ref, NN7, name=name)
            out["raw_over_nn7"][ref] = ratio(self.headline_rmse(ref, RAW, name=name), nn7)
            out["nn7_over_oracle"][ref] = ratio(nn7, self.headline_rmse(ref, ORACLE, name=name))
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (strict JSON after `pipeline.core.io.jsonable`)."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["noise"] = {f.name: getattr(self.noise, f.name) for f in fields(self.noise) if f.name != "mask"}
        return {k: v for k, v in out.items() if v or k not in (NOT_CALIBRATED, LEFT_OUT)}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> GroupReport:
        """Inverse of `to_dict` (None for NaN: tables hold None where a model has no sample)."""
        values = dict(data)
        values["noise"] = NoiseResult(**values["noise"])
        return cls(**values)


@dataclass
class GroupResult(GroupReport):
    """A `GroupReport` with the group's samples (`GroupInputs`), for the figures of evaluate@<group>."""

    inputs: GroupInputs | None = None
    seconds: float = 0.0  # the stage's wall time
    run_id: str | None = None  # the stage's MLflow run
    files: list[str] = field(default_factory=list)

    def report(self) -> GroupReport:
        """The record without the samples."""
        return GroupReport(**{f.name: getattr(self, f.name) for f in fields(GroupReport)})


def _masks(g: GroupInputs, name: str) -> dict[str, np.ndarray]:
    f = g.frame
    out = {LABELS: f[S.switch_col(name)].to_numpy() == 1}
    if g.has_truth:
        out[TRUTH] = np.isfinite(wrench_of(f, S.TRUE, name)).all(axis=1)
        out[TRUTH_LABELLED] = out[TRUTH] & out[LABELS]
    return out


def _global_rmse(pred: np.ndarray, ref: np.ndarray) -> float:
    """The ``rmse`` of `wrench_errors` (6 components pooled) of predictions and references (N, 6), alone:
    the same operations, so the same bits; NaN if N = 0."""
    err = pred - ref
    return math.sqrt(float(np.mean(err**2))) if err.size else math.nan


def name_errors(g: GroupInputs, name: str) -> tuple[dict, dict]:
    """(tables, by_experiment) of one sensor or sum `name` of a group (see `GroupResult`).

    Each model's predictions and finite rows are read once for every reference and experiment type; the
    samples kept are those of `score` (both sides finite, on the reference's mask), so the numbers are
    `score`'s."""
    f = g.frame
    refs = {LABELS: wrench_of(f, S.EXPECTED, name)}
    if g.has_truth:
        refs[TRUTH_LABELLED] = refs[TRUTH] = wrench_of(f, S.TRUE, name)
    masks = _masks(g, name)
    experiments = f[EXPERIMENT].to_numpy()
    in_kind = {kind: experiments == kind for kind in g.experiments}
    preds = {m: wrench_of(f, f"{PRED}.{m}", name) for m in g.models}
    finite = {m: np.isfinite(p).all(axis=1) for m, p in preds.items()}
    tables: dict[str, dict[str, dict[str, float]]] = {}
    by_exp: dict[str, dict[str, dict[str, float]]] = {}
    for ref, target in refs.items():
        on_ref = masks[ref] & np.isfinite(target).all(axis=1)
        tables[ref] = {}
        for model, pred in preds.items():
            keep = on_ref & finite[model]
            tables[ref][model] = wrench_errors(pred[keep], target[keep])
        by_exp[ref] = {}
        for kind in g.experiments:
            in_ref = on_ref & in_kind[kind]
            row = by_exp[ref][kind] = {}
            for model, pred in preds.items():
                keep = in_ref & finite[model]
                row[model] = _global_rmse(pred[keep], target[keep])
    return tables, by_exp


def scored(g: GroupInputs, cfg: EvaluateParams) -> tuple[dict, dict, NoiseResult]:
    """(tables, by_experiment, noise) of a group (see GroupResult; the oracle is scored where it exists):
    the noise check and each name's errors (`name_errors`) side by side in forked processes."""
    from pipeline.core.parallel import forked_map

    jobs = [lambda: noise_check(g, cfg), *(lambda name=name: name_errors(g, name) for name in g.names)]
    labels = [f"{g.group}: noise check", *(f"{g.group}: errors of {name}" for name in g.names)]
    noise, *per_name = forked_map(jobs, labels=labels)
    tables = {name: t for name, (t, _) in zip(g.names, per_name, strict=True)}
    by_exp = {name: b for name, (_, b) in zip(g.names, per_name, strict=True)}
    return tables, by_exp, noise


def phase_errors(g: GroupInputs, models: Sequence[str]) -> dict[str, Any]:
    """Headline -> reference -> phase table (`pipeline.evaluation.phases.phase_table`) of `models`:
    against the labels where the headline's switch is 1, against the truth on every sample of a phase."""
    f = g.frame
    phases = f[PHASE].to_numpy(object)
    out: dict[str, Any] = {}
    for name in g.headlines or [g.headline]:
        masks = _masks(g, name)
        refs = {LABELS: wrench_of(f, S.EXPECTED, name)}
        if g.has_truth:
            refs[TRUTH] = wrench_of(f, S.TRUE, name)
        preds = {m: wrench_of(f, f"{PRED}.{m}", name) for m in models}
        out[name] = {
            ref: phase_table(preds, target, masks[ref], phases, score) for ref, target in refs.items()
        }
    return out


def noise_check(g: GroupInputs, cfg: EvaluateParams) -> NoiseResult:
    """Noise amplification ratios of every model of a group (module docstring)."""
    f = g.frame
    mask = quasi_static_mask(
        f[SPEED].to_numpy(),
        f[S.CONTACTS].fillna("").to_numpy(dtype=object),
        f[S.GUARD].to_numpy(bool),
        g.segments,
        g.fs,
        cfg.still_gyro_rad_s,
        cfg.still_min_s,
        edge_s=1.0 / cfg.highpass_hz,
    )

    def hf(quantity: str) -> np.ndarray:
        x = np.concatenate([wrench_of(f, quantity, name) for name in g.names], axis=1)
        return highpass(x, g.segments, g.fs, cfg.highpass_hz, cfg.highpass_order)

    channels = [f"{name}.{axis}" for name in g.names for axis in S.WRENCH_AXES]
    raw_hf = hf(f"{PRED}.{RAW}")
    result = NoiseResult(
        quasi_static_s=float(mask.sum() / g.fs) if math.isfinite(g.fs) else 0.0,
        windows=int(np.sum(np.diff(np.r_[0, mask.astype(np.int8)]) == 1)),  # rising edges
        ratio={},
        ratio_rms={},
        per_channel={},
        worst_channel={},
        signal_fraction=None,
        flagged=[],
        mask=mask,
    )
    for model in g.models:
        r = noise_ratio(hf(f"{PRED}.{model}"), raw_hf, mask)
        finite = np.isfinite(r)
        result.per_channel[model] = {
            c: (float(v) if np.isfinite(v) else None) for c, v in zip(channels, r, strict=True)
        }
        if finite.any():
            worst = int(np.nanargmax(np.where(finite, r, -np.inf)))
            result.ratio[model] = float(r[worst])
            result.worst_channel[model] = channels[worst]
            result.ratio_rms[model] = float(np.sqrt(np.mean(r[finite] ** 2)))
        else:
            result.ratio[model] = result.ratio_rms[model] = result.worst_channel[model] = None
        limit = cfg.noise_limit
        if model != ORACLE and result.ratio[model] is not None and result.ratio[model] > limit:
            result.flagged.append(model)
    if g.has_truth:
        sig = noise_ratio(hf(S.TRUE), raw_hf, mask)
        if np.isfinite(sig).any():
            result.signal_fraction = float(np.nanmax(sig))
    return result


def not_calibrated_result(record: Mapping[str, Any]) -> GroupResult:
    """The result of a group that is not calibrated (train's record): no model, no table, the reason."""
    sensors = [str(s) for s in record.get("sensors") or ()]
    return GroupResult(
        group=str(record["group"]),
        sensors=sensors,
        pair=None,
        headline=str(record["group"]),
        names=[],
        models=[],
        samples_test=0,
        tables={},
        by_experiment={},
        noise=NoiseResult(0.0, 0, {}, {}, {}, {}, None, []),
        best_on_validation=None,
        validation_ranking=[],
        recommended=None,
        not_calibrated=not_calibrated(record),  # per sensor where the reasons differ
    )


def recommend(ranking: Sequence[str], flagged: Iterable[str], available: Iterable[str]) -> str | None:
    """The first model of the validation ranking that is not flagged and was evaluated (None if none)."""
    flagged, available = set(flagged), set(available)
    return next((m for m in ranking if m not in flagged and m in available), None)


def evaluate_group(g: GroupInputs, cfg: EvaluateParams) -> GroupResult:
    """Tables, per-experiment RMSE, noise check and recommendation of one group (pure: no I/O)."""
    tables, by_exp, noise = scored(g, cfg)
    ranking = [str(m) for m in (g.train.get("validation_ranking") or [])]
    best = g.train.get("best_on_validation")
    if best is not None and best not in ranking:
        ranking.insert(0, str(best))
    fidelity = dict(g.train.get("fidelity") or {})
    unfaithful_models = unfaithful(fidelity, cfg.fidelity_tolerance, cfg.memory_tolerance)
    recommended = recommend(ranking, [*noise.flagged, *unfaithful_models], g.models)
    shown = phase_models(g.models, ranking, recommended)
    cv = g.train.get("cv")
    excitation = dict(g.train.get("excitation") or {})
    deployed = {s: wrench_of(g.frame, f"{PRED}.{recommended}", s) for s in g.sensors} if recommended else {}
    return GroupResult(
        group=g.group,
        sensors=list(g.sensors),
        pair=g.pair,
        headline=g.headline,
        names=list(g.names),
        models=list(g.models),
        samples_test=len(g.frame),
        tables=tables,
        by_experiment=by_exp,
        noise=noise,
        best_on_validation=None if best is None else str(best),
        validation_ranking=ranking,
        recommended=recommended,
        inputs=g,
        headlines=g.headlines,
        phases=phase_errors(g, shown),
        phase_models=shown,
        cv=cv if isinstance(cv, dict) else None,
        fidelity=fidelity,
        unfaithful=unfaithful_models,
        excitation=excitation,
        outside=outside_stats(excitation, deployed),
        floor=noise_floor(g.frame, g.names),
        notes=[str(n) for n in g.train.get("notes") or []],
        left_out=dict(g.train.get(LEFT_OUT) or {}),
    )


# --- MLflow --------------------------------------------------------------------------------------


def mlflow_metrics(r: GroupReport) -> dict[str, float]:
    """Metrics of the evaluate@<group> run: ratios, noise ratios, and per sensor (or sum), reference and
    model the global/force/torque MSE, MAE and RMSE (the full tables are the report.json artifact)."""
    out: dict[str, float] = {}

    def put(key: str, value: Any) -> None:
        if isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value):
            out[key] = float(value)

    for key, by_ref in r.ratios().items():
        for ref, v in by_ref.items():
            put(f"{key}.{ref}", v)
    for model, v in r.noise.ratio.items():
        put(f"noise_ratio.{model}", v)
    put("quasi_static_s", r.noise.quasi_static_s)
    for name, refs in r.tables.items():
        for ref, models in refs.items():
            for model, errors in models.items():
                for key in ("rmse", "rmse_force", "rmse_torque", "mae", "mse"):
                    put(f"{name}.{ref}.{model}.{key}", errors.get(key))
    return out
