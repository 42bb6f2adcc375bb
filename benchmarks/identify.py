"""What the training logs can tell about the robot's inertial parameters, against the simulator's truth.

Every label is the wrench a robot model predicts, so it carries the model's mass and centre-of-mass errors.
Run in a pipeline directory after `dvc repro` on simulated logs (it reads params.yaml, data/smoothed,
data/labelled, the truth tables data/ingested/*.truth.parquet and the URDF the labels were made with,
models/identified/labels.urdf: robot.urdf's or the identified model, `--labels-urdf`). Per sensor, on its
exact-label samples of every log, the labels' error against the true wrench (RMSE, 6 axes pooled, N and Nm):

1. ``labels``: the labels as the label stage made them;
2. ``true inertials``: the same labels recomputed with the simulated robot's true inertial parameters,
   ``label + Y (pi_true - pi_labels)`` (``Y`` the reading regressor, `pipeline.physics.regressor`): what the
   estimated joint velocities and accelerations alone leave, the floor of any identification;
3. ``identified``: the labels recomputed with parameters identified from them, ``label + Y delta``.

The identification is the label stage's (`pipeline.labels.inertials`): every massive link's mass and first
moment (prior: the URDF's, sd 10 % of the mass and 2 cm of centre of mass; the inertia about the centre of
mass held), jointly with a model of each sensor, from the training logs' exact samples (cut sets are not
used), with ``label.identify``'s step, weight and play widths unless given. The forward model of a reading is

    reading - label = Y_s delta + W_s phi(label, T) + noise

where ``phi`` is the sensor model (``--sensor``): ``offset`` (a constant: the sensor known but for its
offset), ``affine`` (its gain, coupling and lever too: the confounds of a mass's scale and a centre of
mass), ``hysteresis`` (the offset and the play operators' states of the reading, as the training's play
model), ``full`` (all of these, temperature, the temperature's gain and the own-axis quadratic), each
coefficient with a Gaussian prior (`pipeline.labels.inertials.PRIOR_SD`). The model is fed the label, not the
reading: a map fitted on the reading would shrink the masses and itself together. ``--reading true`` puts
the simulator's true wrench in place of the raw reading (what the experiments identify with a perfect
sensor), ``--reading oracle`` the exact static inverse of the simulated sensor applied to it (hysteresis
and noise left). Every part is freed here (the label stage holds the parts the data do not identify). Per
part (the links between FT joints), the mass: the labels' URDF, identified, posterior sd, leave-one-log-out
(jackknife) sd, true.

    python benchmarks/identify.py --run .
    python benchmarks/identify.py --run . --reading true --sensor offset

The last line counts the parts of at least 1 kg whose mass is identified within 1 % of the truth.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.core.config import Params, load_params, repo_root, resolve_urdf  # noqa: E402
from pipeline.labels.identify import part_table, training_stems  # noqa: E402
from pipeline.labels.imu_params import label_params  # noqa: E402
from pipeline.labels.inertials import (  # noqa: E402
    BASE_FEATURES,
    FREE,
    SENSOR_MODELS,
    ExactSamples,
    Posterior,
    Sources,
    link_basis,
    log_weights,
    normal_equations,
    prior_precision,
    sensor_columns,
    solve,
    with_change,
)
from pipeline.logs import schema as S  # noqa: E402
from pipeline.physics.regressor import link_params  # noqa: E402
from pipeline.physics.robot import RobotModel, load_robot  # noqa: E402
from pipeline.sim.params import simulate_params  # noqa: E402
from pipeline.sim.world import build_world  # noqa: E402

READINGS = {"raw": S.FT, "true": S.TRUE, "oracle": S.ORACLE}  # what stands for the reading


def rmse(errors: list[np.ndarray]) -> float:
    e = np.concatenate(errors) if errors else np.zeros((0, 6))
    return float(np.sqrt(np.mean(e**2))) if len(e) else float("nan")


def parse() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", type=Path, default=Path("."), help="a pipeline directory after dvc repro")
    ap.add_argument("--params", type=Path, help="default: RUN/params.yaml")
    for name in ("smoothed", "labelled", "ingested"):
        ap.add_argument(f"--{name}", type=Path, help=f"default: RUN/data/{name}")
    ap.add_argument(
        "--labels-urdf",
        type=Path,
        help="the labels' URDF (default: RUN/models/identified/labels.urdf if any, else robot.urdf)",
    )
    ap.add_argument("--sensor", choices=list(SENSOR_MODELS), default="full", help="the sensor model")
    ap.add_argument("--reading", choices=list(READINGS), default="raw", help="what stands for the reading")
    ap.add_argument("--step", type=int, help="every step-th exact sample (default: label.identify.step)")
    ap.add_argument("--weight", type=float, help="each sample's weight (default: label.identify.weight)")
    ap.add_argument("--quick", action="store_true", help="a run of seconds (every 200th sample)")
    return ap.parse_args()


def report_parts(
    robot: RobotModel,
    links: list[str],
    pi_urdf: np.ndarray,
    pi_true: np.ndarray,
    post: Posterior,
    shrink: float,
    reject_p: float,
) -> None:
    """Per part (links between FT joints): its mass as the URDF, the identification (posterior and jackknife
    sd) and the truth say; the count of parts of at least 1 kg identified within 1 % last."""
    print("\npart (heaviest link)   URDF kg   identified kg   posterior sd   jackknife sd    true kg")
    close = heavy = 0
    for p in part_table(robot, links, pi_urdf, post, pi_true, shrink, reject_p):
        masses = f"{p.mass_urdf:9.3f} {p.mass:15.3f} {p.sd:14.3f} {p.jackknife:14.3f} {p.mass_true:10.3f}"
        print(f"{p.name:>20} {masses}")
        if p.mass_urdf >= 1.0:
            heavy += 1
            close += abs(p.mass - p.mass_true) <= 0.01 * p.mass_true
    print(f"parts of at least 1 kg identified within 1 % of the truth: {close} of {heavy}")


def identify(
    src: Sources, robot: RobotModel, links: list[str], params: Params, args: argparse.Namespace
) -> Posterior:
    """The posterior over every link's mass and first moment (`link_basis`) from the training logs."""
    widths = np.asarray(args.cfg.widths(), dtype=float).reshape(-1, 6)
    cols = sensor_columns(args.sensor, BASE_FEATURES + len(widths))
    pi_urdf = link_params(robot, links)
    basis, eqs = link_basis(pi_urdf), []
    for stem in training_stems(src.labelled):
        log = ExactSamples(
            src,
            stem,
            robot,
            links,
            gravity=params.robot.gravity,
            step=args.step,
            widths=widths,
            basis=basis,
            reading=READINGS[args.reading],
        )
        eqs.append(normal_equations(log, cols))
        print(f"{stem}: {len(log.sw)} exact samples", flush=True)
    prior = prior_precision(pi_urdf, cols, len(widths), len(robot.sensors))
    return solve(eqs, prior, FREE * len(links), log_weights(eqs, prior, args.weight))


def print_label_errors(
    src: Sources,
    stems: list[str],
    robot: RobotModel,
    links: list[str],
    basis: np.ndarray,
    params: Params,
    step: int,
) -> None:
    """Per sensor, the labels' RMSE against truth on every log's exact samples: as labelled, and with the
    parameter changes of `basis` (10 L, 2: the truth's, the identified)."""
    print("\nlabels against truth on exact samples, every log (RMSE, 6 axes pooled, N and Nm)")
    print(f"{'sensor':>18} {'labels':>8} {'true inertials':>15} {'identified':>11}")
    errs: dict[tuple[str, str], list[np.ndarray]] = {}
    for stem in stems:
        none = np.zeros((0, 6))
        log = ExactSamples(
            src, stem, robot, links, gravity=params.robot.gravity, step=step, widths=none, basis=basis
        )
        for k, s in enumerate(robot.sensors):
            on = log.sw[:, k] & np.isfinite(log.true[:, k]).all(1)
            base = log.label[on, k] - log.true[on, k]
            for name, e in (
                ("urdf", base),
                ("true", base + log.Y[on, k, :, 0]),
                ("ident", base + log.Y[on, k, :, 1]),
            ):
                errs.setdefault((s, name), []).append(e)
    for s in robot.sensors:
        urdf, true, ident = (rmse(errs[s, name]) for name in ("urdf", "true", "ident"))
        print(f"{s:>18} {urdf:8.3f} {true:15.3f} {ident:11.3f}")


def main() -> None:
    args = parse()
    params = load_params(args.params or args.run / "params.yaml")
    dirs = {n: getattr(args, n) or args.run / "data" / n for n in ("smoothed", "labelled", "ingested")}
    stems = sorted(p.stem for p in dirs["labelled"].glob("*.parquet"))
    missing = [s for s in stems if not (dirs["ingested"] / f"{s}.truth.parquet").is_file()]
    if not stems or missing:
        what = (
            f"{dirs['labelled']}: no labelled table"
            if not stems
            else (f"{dirs['ingested']}: no <log>.truth.parquet for {len(missing)} of {len(stems)} logs")
        )
        sys.exit(f"identify: {what} (it needs simulated logs after dvc repro)")
    labels_urdf = args.labels_urdf or args.run / "models" / "identified" / "labels.urdf"
    robot = load_robot(labels_urdf if labels_urdf.is_file() else resolve_urdf(params.robot.urdf, repo_root()))
    truth_robot = build_world(params, simulate_params(params)).truth_robot
    links = [lk for lk, i in robot.links.items() if i is not None and i.mass > 0]
    pi_urdf = link_params(robot, links)
    truth_delta = link_params(truth_robot, links) - pi_urdf
    args.cfg = label_params(params).identify
    args.step = 200 if args.quick else (args.step or args.cfg.step)
    args.weight = args.weight or args.cfg.weight
    src = Sources(dirs["smoothed"], dirs["labelled"], dirs["ingested"])
    post = identify(src, robot, links, params, args)
    delta = with_change(pi_urdf, post.delta) - pi_urdf
    print_label_errors(src, stems, robot, links, np.column_stack([truth_delta, delta]), params, args.step)
    report_parts(robot, links, pi_urdf, pi_urdf + truth_delta, post, args.cfg.shrink, args.cfg.reject_p)


if __name__ == "__main__":
    main()
