"""A synthetic export of all 8 FT sensors of iCubGenova09, for the inference and calibrate benchmarks.

Six groups as in params.yaml (four single sensors, two foot pairs), each a `GroupNet` of the thesis's
size (13 inputs, two hidden layers of 100, LeakyReLU then ReLU) with random weights and normalisation
constants, saved as the train stage saves networks (``models/<group>/nn13.json/.pt`` + metrics.json), then
exported by the export package itself (adapter, graphs, manifest); or (`synthetic_linear`) each group's
affine map, or its play model (memory: play operators of the widths of params.yaml), as baselines.json
holds them. Weights are random: the speed of a graph does not depend on its values.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.calib.models import GroupNet, NetConfig, save_model  # noqa: E402
from pipeline.core.config import load_params  # noqa: E402
from pipeline.core.io import write_json  # noqa: E402
from pipeline.export import csource, manifest  # noqa: E402
from pipeline.export.trained import GroupModel, read_group  # noqa: E402
from pipeline.stages.export import GROUPS_DIR  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
GROUPS = {
    "r_leg_ft": ("r_leg_ft",),
    "l_leg_ft": ("l_leg_ft",),
    "r_arm_ft": ("r_arm_ft",),
    "l_arm_ft": ("l_arm_ft",),
    "r_foot": ("r_foot_front_ft", "r_foot_rear_ft"),
    "l_foot": ("l_foot_front_ft", "l_foot_rear_ft"),
}
SCALE = np.array([60.0, 60.0, 200.0, 4.0, 4.0, 1.5, 5.0, 3, 3, 3, 0.5, 0.5, 0.5])  # per input


def synthetic_models(
    models_dir: Path, n_inputs: int = 13, hidden: int = 100, seed: int = 0
) -> tuple[list[GroupModel], list[GroupNet]]:
    """Write models/<group>/ for every group; return the export adapter's view and the torch modules."""
    torch.manual_seed(seed)
    out, nets = [], []
    for group, sensors in GROUPS.items():
        net = GroupNet(NetConfig(n_inputs, hidden, ("leaky_relu", "relu")), len(sensors))
        net.reset_parameters()
        for sub in net.nets:
            offset = np.r_[np.zeros(6), 30.0, np.zeros(n_inputs - 7)]
            sub.set_constants(offset, SCALE[:n_inputs], SCALE[:6] * 0.05)
        d = models_dir / group
        save_model(d / f"nn{n_inputs}", net, {"sensors": list(sensors)})
        (d / "metrics.json").write_text(json.dumps({"group": group, "sensors": list(sensors), "test": {}}))
        out.append(read_group(d, f"nn{n_inputs}", group))
        nets.append(net.eval())
    return out, nets


def synthetic_linear(models_dir: Path, name: str = "play", seed: int = 0) -> list[GroupModel]:
    """Write models/<group>/ with a random `name` model (``affine``, ``play`` with the width fractions or
    ``arx`` with the time constants of the params' train.defaults, at 100 Hz) in baselines.json for every
    group; return the export adapter's view."""
    from pipeline.calib.linear import LinearBaseline, monomial_powers
    from pipeline.calib.params import TrainParams
    from pipeline.core.config import stage_section

    gp = stage_section(load_params(ROOT / "params.yaml"), "train", TrainParams).group("r_arm_ft")
    span = np.r_[
        np.full(3, 300.0), np.full(3, 20.0)
    ]  # a limb's raw span, N and Nm: the widths' fractions of it
    widths = None if name != "play" else np.outer(gp.play_width_fractions, span)
    tcs = None if name != "arx" else np.asarray(gp.arx_time_constants_s, dtype=np.float64)
    rng = np.random.default_rng(seed)
    out = []
    for group, sensors in GROUPS.items():
        n = len(sensors)
        offset = np.tile(np.r_[np.zeros(6), 30.0], (n, 1))
        model = LinearBaseline(
            name, offset, np.tile(SCALE[:7], (n, 1)), monomial_powers(7, 1), np.zeros(0), widths, tcs, 0.01
        )
        model.weights = rng.normal(size=(n, 6, 8 + 6 * model.n_operators))
        d = models_dir / group
        d.mkdir(parents=True, exist_ok=True)
        write_json(d / "baselines.json", {name: model.to_dict()})
        (d / "metrics.json").write_text(json.dumps({"group": group, "sensors": list(sensors), "test": {}}))
        out.append(read_group(d, name, group))
    return out


def synthetic_window(models_dir: Path, seed: int = 0) -> list[GroupModel]:
    """Write models/<group>/win.json with a random windowed network for every group (the window, network size
    and play widths of the params' train.defaults, at 100 Hz) over a random play model; return the export
    adapter's view."""
    from pipeline.calib.linear import LinearBaseline
    from pipeline.calib.params import TrainParams
    from pipeline.calib.window import Layer, WindowModel, WindowNet
    from pipeline.core.config import stage_section

    gp = stage_section(load_params(ROOT / "params.yaml"), "train", TrainParams).group("r_arm_ft")
    taus = np.asarray(gp.window_time_constants_s, dtype=np.float64)
    synthetic_linear(models_dir, "play", seed)  # each group's play model, in its baselines.json
    rng = np.random.default_rng(seed + 1)
    out = []
    for group, sensors in GROUPS.items():
        entry = json.loads((models_dir / group / "baselines.json").read_text())["play"]
        nets = []
        for _ in sensors:
            sizes = [6 * (len(taus) + 1) + 1, *[gp.window_hidden] * len(gp.window_activations), 6]
            acts = [*gp.window_activations, None]
            layers = [
                Layer(rng.normal(size=(o, i)) / np.sqrt(i), rng.normal(size=o) * 0.1, a, 0.01)
                for i, o, a in zip(sizes[:-1], sizes[1:], acts, strict=True)
            ]
            scale = np.r_[np.tile(SCALE[:6], len(taus) + 1), 1.0]
            nets.append(WindowNet(np.zeros(sizes[0]), scale, np.r_[np.full(3, 1.0), np.full(3, 0.2)], layers))
        model = WindowModel(LinearBaseline.from_dict(entry), taus, 0.01, nets)
        write_json(models_dir / group / "win.json", model.to_dict())
        out.append(read_group(models_dir / group, "win", group))
    return out


def synthetic_export(out_dir: Path, models: list[GroupModel]) -> dict:
    """Export `models` into `out_dir` as the export steps lay an export out (`pipeline.stages.export`): each
    group's graphs and manifest in ``groups/<group>/``, the fused graph and ``manifest.json`` at the top;
    returns that manifest; the fused graph's C calibrator in ``c/`` (`pipeline.export.csource`). No check
    against stored predictions (there are none)."""
    params = load_params(ROOT / "params.yaml")
    robot, topics = params.robot.urdf, params.topics
    trainings = {m.group: manifest.training(m, "synthetic", None) for m in models}
    entries = {}
    for m in models:
        where = out_dir / GROUPS_DIR / m.group
        where.mkdir(parents=True, exist_ok=True)
        entry, graphs = manifest.build_graph(m.group, [m], topics, robot, {m.group: trainings[m.group]})
        entry = manifest.write_graphs(where, m.group, entry, graphs)
        write_json(where / manifest.MANIFEST_FILE, manifest.document(robot, {m.group: entry}, fused=None))
        entry["files"] = {d: f"{GROUPS_DIR}/{m.group}/{f}" for d, f in entry["files"].items()}
        entries[m.group] = entry
    entry, graphs = manifest.build_graph(manifest.FUSED, models, topics, robot, trainings)
    entries[manifest.FUSED] = manifest.write_graphs(out_dir, manifest.FUSED, entry, graphs)
    (out_dir / "c").mkdir(exist_ok=True)  # the fused graph's C calibrator, where the export writes it
    for name, text in csource.generate(models, entry).items():
        (out_dir / "c" / name).write_text(text)
    doc = manifest.document(robot, entries)
    write_json(out_dir / manifest.MANIFEST_FILE, doc)
    return doc


def random_inputs(n: int, n_inputs: int = 13, seed: int = 1) -> np.ndarray:
    """(n, 8 n_inputs) plausible raw inputs for the fused graph (sensors in GROUPS order)."""
    rng = np.random.default_rng(seed)
    one = rng.normal(size=(n, 8, n_inputs)) * SCALE[:n_inputs]
    one[:, :, 6] += 30.0
    return one.reshape(n, -1)
