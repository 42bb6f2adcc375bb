"""Step `identify` (stage `label`): the robot's inertial parameters identified from the FT sensors, and the
labels made with them when ``label.inertials`` is ``identified``.

``ftcal identify SMOOTHED LABELLED OUT [--truth INGESTED]`` reads the training logs' smoothed and labelled
tables (labelled with ``robot.urdf``), identifies every massive link's mass and first moment jointly with a
model of each sensor (`pipeline.labels.inertials`, `pipeline.labels.identify`) and writes OUT (replaced
whole, atomically):

- ``identification.json``: the decision (``identified`` or ``urdf``, and why), per part its mass (URDF,
  identified, posterior and jackknife sd, prior sd, whether the data identify it or reject the URDF's
  values, with the chi-square statistic; the truth for simulated logs), per sensor the labels' change
  and, for simulated logs, their error against the true wrench with the URDF's and with the identified
  parameters;
- ``parts.csv`` (the same per part) and ``links.csv`` (per changed link: mass and centre of mass, URDF's
  and identified, with the posterior sd);
- ``model.urdf``: ``robot.urdf`` with the identified links' inertial values (the URDF's own values where the
  model is refused), a robot model a lab can use elsewhere;
- ``labels.urdf``: the URDF the labels are made with (``model.urdf`` with ``inertials: identified`` and an
  accepted model, else a copy of ``robot.urdf``), what the deployment days label with;
- ``parts.png``: each part's identified mass change with its sd (and the truth's).

With ``label.inertials: identified`` and an accepted model, LABELLED is labelled again with ``labels.urdf``.
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path
from typing import Any

from pipeline.core.cliargs import add_params_option
from pipeline.core.errors import DataError

STAGE = "identify"
MODEL_URDF, LABELS_URDF, SUMMARY = "model.urdf", "labels.urdf", "identification.json"


def _truth_robot(params: Any, truth_dir: Path | None) -> Any:
    """The simulated robot's true model when `truth_dir` holds truth tables of simulated logs, else None."""
    if truth_dir is None or not any(truth_dir.glob("*.truth.parquet")):
        return None
    from pipeline.sim.params import simulate_params
    from pipeline.sim.world import build_world

    return build_world(params, simulate_params(params)).truth_robot


def _write_tables(out: Path, res: Any) -> None:
    """parts.csv and links.csv of the identification `res`."""
    import numpy as np

    from pipeline.core.io import write_csv
    from pipeline.labels.identify import to_inertial
    from pipeline.labels.inertials import FREE
    from pipeline.physics.regressor import PARAMS

    write_csv(
        out / "parts.csv",
        [
            "part",
            "mass_urdf_kg",
            "mass_kg",
            "sd_kg",
            "jackknife_sd_kg",
            "prior_sd_kg",
            "identified",
            "mass_true_kg",
            "chi2",
            "dof",
            "urdf_rejected",
        ],
        [
            [p.name, p.mass_urdf, p.mass, p.sd, p.jackknife, p.prior_sd, int(p.identified), p.mass_true]
            + [p.chi2, p.dof, int(p.rejected)]
            for p in res.parts
        ],
    )
    rows = []
    for k, link in enumerate(res.links):
        a, b = (to_inertial(pi[PARAMS * k : PARAMS * (k + 1)]) for pi in (res.pi_urdf, res.pi))
        sd = res.link_sd[FREE * k : FREE * (k + 1)]
        if a.mass != b.mass or not np.array_equal(a.com, b.com):
            rows.append([link, a.mass, b.mass, sd[0], *a.com, *b.com])
    com = [f"com_{x}_m" for x in "xyz"]
    header = ["link", "mass_urdf_kg", "mass_kg", "mass_sd_kg", *(f"{c}_urdf" for c in com), *com]
    write_csv(out / "links.csv", header, rows)


def _figure(path: Path, res: Any) -> None:
    """Each part's identified mass change from the URDF's (%), with 2 sd, and the truth's."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    parts = res.parts
    fig, ax = plt.subplots(figsize=(8, 0.4 * len(parts) + 1.5))
    for i, p in enumerate(parts):
        change, sd = 100 * (p.mass / p.mass_urdf - 1), 200 * p.sd / p.mass_urdf
        look = ("o", "C0") if p.identified else ("D", "C1") if p.rejected else ("x", "0.6")
        ax.errorbar(change, i, xerr=sd, fmt=look[0], color=look[1])
        if p.mass_true is not None:
            ax.plot(100 * (p.mass_true / p.mass_urdf - 1), i, "s", mfc="none", color="C3")
    ax.axvline(0, color="0.3", lw=0.8)
    ax.set_yticks(range(len(parts)), [p.name for p in parts])
    ax.set_xlabel(
        "mass change from the URDF's, %\n"
        "(bars: 2 sd; blue: identified; orange: re-estimated; grey x: URDF's; red square: truth)"
    )
    ax.set_title(f"identified robot model: {res.status}" + (f" ({res.reason[:60]})" if res.reason else ""))
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _write(out: Path, res: Any, src_urdf: str, labels_urdf_from_model: bool) -> None:
    from pipeline.core.io import write_json
    from pipeline.physics.urdf_write import write_inertials

    write_json(out / SUMMARY, res.to_dict() | {"labels": "identified" if labels_urdf_from_model else "urdf"})
    _write_tables(out, res)
    write_inertials(src_urdf, out / MODEL_URDF, res.inertials() if res.accepted else {})
    if labels_urdf_from_model:
        shutil.copyfile(out / MODEL_URDF, out / LABELS_URDF)
    else:
        shutil.copyfile(src_urdf, out / LABELS_URDF)
    _figure(out / "parts.png", res)


def run(
    params: Any, smoothed: str | Path, labelled: str | Path, out: str | Path, truth: str | Path | None = None
) -> Any:
    """Identify, write OUT, relabel if asked (module docstring); the `Identification`."""
    import mlflow

    from pipeline.core.config import repo_root, resolve_urdf
    from pipeline.core.io import atomic_dir
    from pipeline.core.progress import progress_bar
    from pipeline.core.tracking import stage_run
    from pipeline.labels.identify import identify_robot
    from pipeline.labels.imu_params import label_params
    from pipeline.labels.inertials import Sources
    from pipeline.physics.robot import load_robot
    from pipeline.physics.urdf import resolve_urdf as urdf_file

    t0 = time.perf_counter()
    cfg = label_params(params)
    smoothed, labelled, out = Path(smoothed), Path(labelled), Path(out)
    for d in (smoothed, labelled):
        if not d.is_dir():
            raise DataError(f"{d}: input directory not found")
    truth_dir = Path(truth) if truth is not None else None
    src_urdf = str(urdf_file(resolve_urdf(params.robot.urdf, repo_root())))
    robot = load_robot(src_urdf)
    with stage_run(STAGE, {"label.inertials": cfg.inertials, "label.identify": cfg.identify.__dict__}):
        with progress_bar() as bar:
            task = bar.add_task("identify", total=None)
            res = identify_robot(
                robot,
                Sources(smoothed, labelled, truth_dir),
                cfg.identify,
                params.robot.gravity,
                _truth_robot(params, truth_dir),
                progress=lambda _stem: bar.advance(task),
            )
        relabel = cfg.inertials == "identified" and res.accepted
        with atomic_dir(out) as tmp:
            _write(tmp, res, src_urdf, relabel)
        mlflow.log_metrics(_metrics(res) | {"seconds": time.perf_counter() - t0})
        mlflow.set_tags(
            {"identify.status": res.status, "identify.labels": "identified" if relabel else "urdf"}
        )
        mlflow.log_artifacts(str(out), "identified")
    if relabel:
        from pipeline.stages import label

        label.run(params, smoothed, labelled, truth_dir, urdf=out / LABELS_URDF)
    return res


def _metrics(res: Any) -> dict[str, float]:
    out: dict[str, float] = {"identified": float(res.accepted), "exact_samples": float(res.samples)}
    for p in res.parts:
        out[f"mass.{p.name}"] = p.mass
        out[f"mass_sd.{p.name}"] = p.sd
    for s, d in res.sensors.items():
        out |= {f"{k}.{s}": v for k, v in d.items() if v is not None}
    return out


def _cmd(args: argparse.Namespace) -> int:
    from pipeline.core.config import load_params
    from pipeline.labels.imu_params import label_params

    params = load_params(args.params)
    res = run(params, args.smoothed, args.labelled, args.out, args.truth)
    choice = label_params(params).inertials
    print(f"identify: {res.status}{': ' + res.reason if res.reason else ''} ({res.samples} exact samples)")
    for p in res.parts:
        true = f", true {p.mass_true:.3f}" if p.mass_true is not None else ""
        print(f"  {p.name}: URDF {p.mass_urdf:.3f} kg, {p.mass:.3f} +- {p.sd:.3f} kg {p.state}{true}")
    for s, d in res.sensors.items():
        truth = ""
        if d["error_urdf"] is not None:
            truth = f"; vs truth: URDF {d['error_urdf']:.3f}, identified {d['error_identified']:.3f}"
        print(f"  {s}: labels change {d['label_change']:.3f}{truth}")
    used = "identified" if choice == "identified" and res.accepted else "URDF"
    print(
        f"labels: the {used} inertial parameters (label.inertials: {choice}); model: {args.out / MODEL_URDF}"
    )
    return 0


def add_cli(subparsers: Any) -> None:
    """Add `ftcal identify SMOOTHED LABELLED OUT [--truth DIR]`."""
    p = subparsers.add_parser(
        STAGE, help="identify the robot's inertial parameters", description=(__doc__ or "").split("\n\n")[0]
    )
    p.add_argument("smoothed", type=Path, help="directory of smoothed <log>.parquet tables")
    p.add_argument(
        "labelled", type=Path, help="directory of labelled <log>.parquet tables (relabelled in place)"
    )
    p.add_argument("out", type=Path, help="output directory (models/identified)")
    p.add_argument(
        "--truth", type=Path, default=None, help="directory of simulated <log>.truth.parquet tables"
    )
    add_params_option(p)
    p.set_defaults(func=_cmd)


__all__ = ["LABELS_URDF", "MODEL_URDF", "STAGE", "add_cli", "run"]
