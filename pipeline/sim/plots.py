"""Plots of one simulated log: joints, true vs raw wrench per sensor, contacts, temperature."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from pipeline.physics.robot import RobotModel  # noqa: E402
from pipeline.sim.motion import Motion  # noqa: E402
from pipeline.sim.truth import Truth  # noqa: E402

AXES = ("x", "y", "z")


def _save(fig: plt.Figure, path: Path) -> str:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return str(path)


def plot_log(
    out_dir: Path,
    name: str,
    robot: RobotModel,
    motion: Motion,
    truth: Truth,
    sensors: dict[str, dict[str, np.ndarray]],
) -> list[str]:
    """Write the four PNGs of log `name` into `out_dir`; returns their paths."""
    t = motion.t
    paths = []

    # joint trajectories, one panel per limb-ish group of 8 joints
    n_j = len(robot.joint_names)
    rows = int(np.ceil(n_j / 8))
    fig, axes = plt.subplots(rows, 1, figsize=(12, 2.4 * rows), sharex=True, squeeze=False)
    for r in range(rows):
        ax = axes[r, 0]
        for j in range(8 * r, min(n_j, 8 * r + 8)):
            ax.plot(t, motion.q[:, j], lw=0.8, label=robot.joint_names[j])
        ax.set_ylabel("rad")
        ax.legend(fontsize=6, ncol=4, loc="upper right")
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(f"{name}: true joint positions")
    fig.tight_layout()
    paths.append(_save(fig, out_dir / f"{name}_joints.png"))

    # true vs raw wrench, every sensor: forces left, torques right
    names = list(robot.sensors)
    fig, axes = plt.subplots(len(names), 2, figsize=(14, 1.9 * len(names)), sharex=True, squeeze=False)
    colors = ("tab:red", "tab:green", "tab:blue")
    for i, s in enumerate(names):
        for side, (sl, unit) in enumerate(((slice(0, 3), "N"), (slice(3, 6), "Nm"))):
            ax = axes[i, side]
            for a, c in zip(range(sl.start, sl.stop), colors, strict=True):
                label = ("f" if side == 0 else "t") + AXES[a % 3]
                ax.plot(t, sensors[s]["raw"][:, a], color=c, lw=0.5, alpha=0.5, label=f"raw {label}")
                ax.plot(t, sensors[s]["true"][:, a], color=c, lw=1.0, ls="--", label=f"true {label}")
            ax.set_ylabel(f"{s}\n[{unit}]", fontsize=7)
            if i == 0:
                ax.legend(fontsize=6, ncol=6, loc="upper right")
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    fig.suptitle(f"{name}: true (dashed) vs raw (solid) wrench per sensor")
    fig.tight_layout()
    paths.append(_save(fig, out_dir / f"{name}_wrench.png"))

    # contact timeline and weight transfer
    links = sorted(set().union(*motion.contact_sets))
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(12, 3.5), sharex=True, height_ratios=(2, 1))
    for i, link in enumerate(links):
        on = np.array([link in motion.contact_sets[c] for c in motion.contact_index])
        ax.fill_between(t, i - 0.4, i + 0.4, where=on, step="mid", alpha=0.7)
    ax.set_yticks(range(len(links)), links)
    ax.set_title(f"{name}: true contacts")
    vertical = {c: w[:, 2] for c, w in truth.contact_wrench.items() if not np.isnan(w).all()}
    for link, fz in vertical.items():
        ax2.plot(t, fz, lw=0.8, label=link)
    ax2.set_ylabel("ground fz [N]")
    ax2.set_xlabel("time [s]")
    if vertical:
        ax2.legend(fontsize=6, ncol=4)
    fig.tight_layout()
    paths.append(_save(fig, out_dir / f"{name}_contacts.png"))

    # temperatures
    fig, ax = plt.subplots(figsize=(12, 3))
    for s in names:
        ax.plot(t, sensors[s]["temp_true"], lw=1.0, label=s)
    ax.set_ylabel("deg C")
    ax.set_xlabel("time [s]")
    ax.set_title(f"{name}: FT sensor temperature (true)")
    ax.legend(fontsize=6, ncol=4)
    fig.tight_layout()
    paths.append(_save(fig, out_dir / f"{name}_temperature.png"))
    return paths
