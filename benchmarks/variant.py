"""A variant of the default data, set in params only: another seed and stronger hidden sensor distortions.

Writes a copy of the repository (git-tracked files) into WORK with its params.yaml changed: `seed` set to
--seed and the distortion ranges of ``simulate.sensors`` (coupling, gain, temperature_gain, nonlinearity,
offset_drift_force, offset_drift_torque) multiplied by --scale. Then, in WORK, ``dvc repro`` runs the whole
pipeline on the variant and ``reports/`` holds its figures (against truth, beside the oracle), as for the
default data. Nothing else changes: same code, same simulator, same training params.

    python benchmarks/variant.py WORK [--seed 7] [--scale 2.0]
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


def variant_params(text: str, seed: int, scale: float) -> str:
    """params.yaml text with `seed` and the scaled distortion ranges (comments kept: line edits)."""
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
        if indent == 0 and key == "seed":
            line = f"seed: {seed}  # variant of the default data (benchmarks/variant.py)"
        elif section == "simulate" and sub == "sensors" and indent == 4 and key in SCALED:
            comment = line.split("#", 1)[1].strip() if "#" in line else ""
            line = f"    {key}: {values[key] * scale!r}  # x{scale:g} the default; {comment}"
        lines.append(line)
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "work", type=Path, help="new directory: a copy of the repository with the variant params"
    )
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--scale", type=float, default=2.0)
    args = parser.parse_args()
    if args.work.exists():
        sys.exit(f"error: {args.work} exists (choose a new directory)")
    subprocess.run(["git", "clone", "-q", str(ROOT), str(args.work)], check=True)
    params = args.work / "params.yaml"
    params.write_text(variant_params((ROOT / "params.yaml").read_text(), args.seed, args.scale))
    changed = yaml.safe_load(params.read_text())
    print(f"seed {changed['seed']}; simulate.sensors:")
    for key in SCALED:
        print(f"  {key}: {changed['simulate']['sensors'][key]}")
    print(f"now: cd {args.work} && dvc repro")


if __name__ == "__main__":
    main()
