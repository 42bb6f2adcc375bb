"""Variants of the default data, set in params only: stronger hidden distortions, or another gait.

Writes a copy of the repository (git-tracked files) into WORK with its params.yaml changed, then, in WORK,
``dvc repro`` runs the whole pipeline on the variant and ``reports/`` holds its figures (against truth,
beside the oracle), as for the default data. Nothing else changes: same code, same simulator, same
training params.

- distortion variant (default): `seed` set to --seed and the distortion ranges of ``simulate.sensors``
  (coupling, gain, temperature_gain, nonlinearity, offset_drift_force, offset_drift_torque) multiplied by
  --scale.
- gait variant (--gait): `seed` set to --seed and the walking of ``simulate.motion`` changed: longer double
  support (weight transfer), shorter single support and longer steps, so the robot walks faster, with
  more of each step on both feet (where no leg has a label of its own); distortions as the default's unless
  --scale is given.

    python benchmarks/variant.py WORK [--seed 7] [--scale 2.0]
    python benchmarks/variant.py WORK --gait [--seed 11]
    cd WORK && dvc repro
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
SCALED = (
    "coupling",
    "gain",
    "temperature_gain",
    "nonlinearity",
    "offset_drift_force",
    "offset_drift_torque",
)
# the gait variant's walking (simulate.motion): default 0.4 s double and 0.8 s single support, steps of
# L / 8 (about 0.07 m on iCub 3)
GAIT = {"double_support_s": 0.7, "single_support_s": 0.6, "step_length_m": 0.12}


def variant_params(text: str, seed: int, scale: float, gait: bool = False) -> str:
    """params.yaml text with `seed`, the scaled distortion ranges and (`gait`) the variant's walking
    (comments kept: line edits)."""
    values = yaml.safe_load(text)["simulate"]["sensors"]
    lines, section, sub = [], None, None
    for line in text.splitlines():
        stripped = line.strip()
        indent = len(line) - len(line.lstrip())
        if indent == 0 and stripped and not stripped.startswith("#"):
            section = stripped.split(":")[0]
        elif indent == 2 and stripped and not stripped.startswith("#"):
            sub = stripped.split(":")[0]
        key = stripped.split(":")[0]
        comment = line.split("#", 1)[1].strip() if "#" in line else ""
        if indent == 0 and key == "seed":
            line = f"seed: {seed}  # variant of the default data (benchmarks/variant.py)"
        elif section == "simulate" and sub == "sensors" and indent == 4 and key in SCALED and scale != 1.0:
            line = f"    {key}: {values[key] * scale!r}  # x{scale:g} the default; {comment}"
        elif section == "simulate" and sub == "motion" and indent == 4 and key in GAIT and gait:
            line = f"    {key}: {GAIT[key]!r}  # gait variant (benchmarks/variant.py); {comment}"
        lines.append(line)
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "work", type=Path, help="new directory: a copy of the repository with the variant params"
    )
    parser.add_argument("--gait", action="store_true", help="the gait variant instead of the distortion one")
    parser.add_argument("--seed", type=int, default=None, help="seed (default 7, or 11 with --gait)")
    parser.add_argument(
        "--scale", type=float, default=None, help="distortion scale (default 2, 1 with --gait)"
    )
    args = parser.parse_args()
    seed = args.seed if args.seed is not None else (11 if args.gait else 7)
    scale = args.scale if args.scale is not None else (1.0 if args.gait else 2.0)
    if args.work.exists():
        sys.exit(f"error: {args.work} exists (choose a new directory)")
    subprocess.run(["git", "clone", "-q", str(ROOT), str(args.work)], check=True)
    params = args.work / "params.yaml"
    params.write_text(variant_params((ROOT / "params.yaml").read_text(), seed, scale, args.gait))
    changed = yaml.safe_load(params.read_text())
    print(f"seed {changed['seed']}; simulate.sensors:")
    for key in SCALED:
        print(f"  {key}: {changed['simulate']['sensors'][key]}")
    print("simulate.motion:")
    for key in GAIT:
        print(f"  {key}: {changed['simulate']['motion'][key]}")
    print(f"now: cd {args.work} && dvc repro")


if __name__ == "__main__":
    main()
