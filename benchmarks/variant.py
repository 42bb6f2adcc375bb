"""Variants of the default data, set in params only: stronger hidden distortions, another gait, or other
sensor memory physics.

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
- memory variants (--memory wide|slow): the sensors' path- and time-dependence of ``simulate.sensors`` set
  to physics the models were not tuned on, everything else the default's (seed included unless --seed):
  ``wide``, hysteresis 0.5 % of full scale over 5 play operators of widths 0.2-10 % of full scale, creep
  0.6 % with time constants 5-60 s, the gauges 30 s behind the thermometer; ``slow``, hysteresis 0.4 % of
  full scale in one operator of 1 %, creep 0.2 % with time constants 200-900 s, the gauges 240 s behind.

    python benchmarks/variant.py WORK [--seed 7] [--scale 2.0]
    python benchmarks/variant.py WORK --gait [--seed 11]
    python benchmarks/variant.py WORK --memory wide
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
MEMORY = {
    "wide": {
        "hysteresis": 0.005, "hysteresis_width_min": 0.002, "hysteresis_width_max": 0.1,
        "hysteresis_operators": 5, "creep": 0.006, "creep_tau_min_s": 5.0, "creep_tau_max_s": 60.0,
        "thermal_lag_s": 30.0,
    },
    "slow": {
        "hysteresis": 0.004, "hysteresis_width_min": 0.01, "hysteresis_width_max": 0.01,
        "hysteresis_operators": 1, "creep": 0.002, "creep_tau_min_s": 200.0, "creep_tau_max_s": 900.0,
        "thermal_lag_s": 240.0,
    },
}  # fmt: skip


def variant_params(
    text: str, seed: int, scale: float, gait: bool = False, memory: dict[str, float] | None = None
) -> str:
    """A lab's params.yaml text with `seed`, the scaled distortion ranges, (`gait`) the variant's walking and
    (`memory`) the sensors' memory physics set in it (scaled from the effective values: the defaults'
    unless the file sets them); every other key as it was."""
    from pipeline.core.defaults import resolve

    data = yaml.safe_load(text)
    effective = resolve(data)[0]["simulate"]
    data["seed"] = seed
    simulate = data.setdefault("simulate", {})
    sensors, motion = simulate.setdefault("sensors", {}), simulate.setdefault("motion", {})
    if scale != 1.0:
        sensors.update({k: effective["sensors"][k] * scale for k in SCALED})
    sensors.update(memory or {})
    if gait:
        motion.update(GAIT)
    for key in ("sensors", "motion"):
        if not simulate[key]:
            del simulate[key]
    if not simulate:
        del data["simulate"]
    head = "# A variant of the default data (benchmarks/variant.py): the lab's params.yaml, its values set\n"
    return head + yaml.safe_dump(data, sort_keys=False)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "work", type=Path, help="new directory: a copy of the repository with the variant params"
    )
    parser.add_argument("--gait", action="store_true", help="the gait variant instead of the distortion one")
    parser.add_argument(
        "--memory", choices=sorted(MEMORY), default=None, help="a memory variant instead (module docstring)"
    )
    parser.add_argument(
        "--seed", type=int, default=None, help="seed (default 7, 11 with --gait, the default's with --memory)"
    )
    parser.add_argument(
        "--scale", type=float, default=None, help="distortion scale (default 2, 1 with --gait)"
    )
    args = parser.parse_args()
    default_seed = int(yaml.safe_load((ROOT / "params.yaml").read_text())["seed"])
    seed = args.seed if args.seed is not None else default_seed if args.memory else (11 if args.gait else 7)
    scale = args.scale if args.scale is not None else (1.0 if args.gait or args.memory else 2.0)
    if args.work.exists():
        sys.exit(f"error: {args.work} exists (choose a new directory)")
    subprocess.run(["git", "clone", "-q", str(ROOT), str(args.work)], check=True)
    params = args.work / "params.yaml"
    memory = MEMORY[args.memory] if args.memory else None
    params.write_text(variant_params((ROOT / "params.yaml").read_text(), seed, scale, args.gait, memory))
    from pipeline.core.defaults import resolve

    changed = resolve(yaml.safe_load(params.read_text()))[0]
    print(f"seed {changed['seed']}; simulate.sensors:")
    for key in (*SCALED, *(memory or {})):
        print(f"  {key}: {changed['simulate']['sensors'][key]}")
    print("simulate.motion:")
    for key in GAIT:
        print(f"  {key}: {changed['simulate']['motion'][key]}")
    print(f"now: cd {args.work} && dvc repro")


if __name__ == "__main__":
    main()
