"""Stability of training: two trainings whose labelled inputs differ by a relative amount.

Copies the labelled tables twice into a work directory, the second with every floating-point column but
time multiplied by (1 + rel * u), u uniform in [-1, 1] (seeded), trains the groups on both (separate
Optuna studies, the same params) and evaluates them (against truth when --truth is given). Prints per
group and headline the recommended model and its test RMSE in both runs (against the labels, and the
truth), their relative difference, and whether the recommendation is the same. The last line: the
largest relative difference of the recommended models' RMSEs and whether every recommendation agrees.

Training reads the labelled values as float32 (`pipeline.calib.data`): a difference of a few float64 steps
(another machine's smoothing and labelling, --rel 1e-15) changes nothing, unless a value lies that close to
a float32 rounding boundary. The default --rel 1e-6 changes every value by about ten float32 steps, as another
simulation or recording of the same experiments would, far below the sensors' noise: the networks then
train differently, and what stays the same is what does not hang on their last digits.

    python benchmarks/stability.py LABELLED WORK [--truth INGESTED] [--params params.yaml]
        [--groups legs r_arm_ft] [--rel 1e-6]
    python benchmarks/stability.py --quick    # tiny networks on synthetic labelled logs
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks import QUICK  # noqa: E402
from pipeline.core.defaults import resolve  # noqa: E402
from pipeline.logs import schema as S  # noqa: E402
from tests.factories.labelled import LEG, write_labelled_logs  # noqa: E402


def perturb(src: Path, dst: Path, rel: float, seed: int) -> None:
    """Copy the labelled tables of `src` into `dst`, floating-point columns but time times (1 + rel u)."""
    dst.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for path in sorted(src.glob(f"*{S.PARQUET_SUFFIX}")):
        table = pq.read_table(path)
        columns = []
        for name, column in zip(table.column_names, table.columns, strict=True):
            if pa.types.is_floating(column.type) and name != S.TIME and rel > 0:
                values = column.to_numpy(zero_copy_only=False)
                values = values * (1.0 + rel * rng.uniform(-1.0, 1.0, len(values)))
                column = pa.array(values, column.type)
            columns.append(column)
        pq.write_table(pa.Table.from_arrays(columns, schema=table.schema), dst / path.name)


def quick_params(work: Path) -> Path:
    """params.yaml with one group of `tests.factories`' leg sensor and tiny networks, in `work`."""
    data = resolve(yaml.safe_load((ROOT / "params.yaml").read_text()))[0]
    data["train"]["defaults"].update(
        hidden=16, epochs=2, batch_size=128, n_trials=2, tpe_startup_trials=2, search={}
    )
    data["train"]["groups"] = {LEG: {"sensor": LEG}}
    path = work / "params.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("labelled", type=Path, nargs="?", help="labelled tables (not with --quick)")
    parser.add_argument(
        "work", type=Path, nargs="?", help="work directory (tables, models, studies, reports)"
    )
    parser.add_argument("--truth", type=Path, default=None, help="ingested directory with the truth tables")
    parser.add_argument("--params", type=Path, default=ROOT / "params.yaml")
    parser.add_argument("--groups", nargs="*", default=None, help="default: every group of train.groups")
    parser.add_argument("--rel", type=float, default=1e-6)
    parser.add_argument(
        "--quick", action="store_true", help=f"{QUICK}: tiny networks on synthetic labelled logs"
    )
    args = parser.parse_args()
    if args.quick:
        args.work = args.work or Path(tempfile.mkdtemp(prefix="ftcal-stability-"))
        args.labelled = write_labelled_logs(args.work / "source", n=300)
        args.params, args.groups = quick_params(args.work), [LEG]
    elif args.labelled is None or args.work is None:
        parser.error("LABELLED and WORK are required (or --quick)")
    os.environ.setdefault("MLFLOW_TRACKING_URI", f"sqlite:///{(args.work / 'mlflow.db').resolve()}")

    from pipeline.calib.run import train_group
    from pipeline.core.config import load_params
    from pipeline.evaluation.params import LABELS, TRUTH
    from pipeline.stages.evaluate import run as evaluate

    params = load_params(args.params)
    groups = args.groups or list(params.raw["train"]["groups"])
    runs = {"a": 0.0, "b": args.rel}
    for run, rel in runs.items():
        perturb(args.labelled, args.work / run / "labelled", rel, params.seed)
    worst, same = 0.0, True
    for group in groups:
        results = {}
        for run in runs:
            base = args.work / run
            models = base / "models" / group
            train_group(params, group, base / "labelled", models, base / "studies" / group, progress=False)
            results[run] = evaluate(
                params, group, models, base / "labelled", base / "reports", args.truth, progress=False
            )
        a, b = results["a"], results["b"]
        agree = a.recommended == b.recommended
        same &= agree
        for name in a.headlines or [a.headline]:
            parts = []
            for ref in (LABELS, TRUTH):
                va = a.headline_rmse(ref, a.recommended, name=name)
                vb = b.headline_rmse(ref, b.recommended, name=name)
                if va is None or vb is None:
                    continue
                diff = abs(va - vb) / max(va, vb)
                worst = max(worst, diff)
                parts.append(f"vs {ref} {va:.4g} / {vb:.4g} ({diff:.1%})")
            print(
                f"{group} {name}: recommended {a.recommended} / {b.recommended} "
                f"({'same' if agree else 'DIFFERENT'}); {'; '.join(parts)}"
            )
    print(
        f"largest relative difference of the recommended RMSEs: {worst:.2%} (<= 2% aimed for); "
        f"recommendations {'all the same' if same else 'DIFFER'}"
    )


if __name__ == "__main__":
    main()
