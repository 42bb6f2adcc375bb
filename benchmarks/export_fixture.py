"""A synthetic export of all 8 FT sensors of iCubGenova09, for the inference and calibrate benchmarks.

Six groups as in params.yaml (four single sensors, two foot pairs), each a `GroupNet` of the thesis's
size (13 inputs, two hidden layers of 100, LeakyReLU then ReLU) with random weights and normalisation
constants, saved as the train stage saves networks (``models/<group>/nn13.json/.pt`` + metrics.json), then
exported by the export package itself (adapter, graphs, manifest). Weights are random: the speed of a
graph does not depend on its values.
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
from pipeline.export import manifest  # noqa: E402
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


def synthetic_export(out_dir: Path, models: list[GroupModel]) -> dict:
    """Export `models` into `out_dir` as the export steps lay an export out (`pipeline.stages.export`): each
    group's graphs and manifest in ``groups/<group>/``, the fused graph and ``manifest.json`` at the top;
    returns that manifest. No check against stored predictions (there are none)."""
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
    doc = manifest.document(robot, entries)
    write_json(out_dir / manifest.MANIFEST_FILE, doc)
    return doc


def random_inputs(n: int, n_inputs: int = 13, seed: int = 1) -> np.ndarray:
    """(n, 8 n_inputs) plausible raw inputs for the fused graph (sensors in GROUPS order)."""
    rng = np.random.default_rng(seed)
    one = rng.normal(size=(n, 8, n_inputs)) * SCALE[:n_inputs]
    one[:, :, 6] += 30.0
    return one.reshape(n, -1)
