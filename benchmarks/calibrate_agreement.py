"""`ftcal calibrate` on a pipeline test log against the pipeline's own test predictions of that log.

Needs the outputs of a pipeline run: the log (data/sim/<log>.mcap), its labelled table (data/labelled),
the train outputs (models/<group>/predictions.parquet) and an export of them (exported/). Prints:

1. the copy: every original message byte-identical (mcap's reader), one calibrated message per raw
   wrench message (except those stamped before the sensor's first temperature/IMU message);
2. where the inputs agree, the outputs agree: the exported graph (float64) on the labelled table's inputs
   (the ingest-aligned samples that `evaluate` scores) against the stored test predictions, max |diff|;
3. where they legitimately differ: calibrate's inputs are each raw wrench message as recorded and the
   latest temperature/IMU at or before its stamp (causal); evaluate's are interpolated at the joint-state
   stamps. Per sensor, the RMS difference between the calibrated messages and the predictions interpolated
   to their stamps, next to the same RMS for the raw wrench (the input difference it comes from).

    python benchmarks/calibrate_agreement.py data/sim/10_pole_test.mcap --models exported \\
        --trained models --labelled data/labelled
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.core.config import load_params  # noqa: E402
from pipeline.export.check import run, session  # noqa: E402
from pipeline.logs import schema as S  # noqa: E402
from pipeline.logs.rosmsg import LogReader, concat_batches  # noqa: E402
from pipeline.tools import calibrate as C  # noqa: E402


def _messages(path: Path) -> list[tuple]:
    from mcap.reader import make_reader

    with path.open("rb") as f:
        return [
            (c.topic, m.log_time, m.publish_time, m.sequence, bytes(m.data))
            for _, c, m in make_reader(f).iter_messages(log_time_order=False)
        ]


def _at(stamps: np.ndarray, values: np.ndarray, when: np.ndarray) -> np.ndarray:
    """(len(when), 6) values (N, 6) at `stamps` linearly interpolated to `when` (ns)."""
    return np.column_stack([np.interp(when, stamps, values[:, a]) for a in range(6)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("log", type=Path)
    ap.add_argument("--models", type=Path, required=True, help="export directory")
    ap.add_argument("--trained", type=Path, required=True, help="train outputs (models/<group>)")
    ap.add_argument("--labelled", type=Path, required=True)
    ap.add_argument("--params", type=Path, default=None)
    args = ap.parse_args()
    params = load_params(args.params)
    manifest = json.loads((args.models / "manifest.json").read_text())
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "calibrated.mcap"
        (result,) = C.run(params, args.log, out, args.models, force=True, offsets=False)  # as delivered
        original, copied = _messages(args.log), _messages(out)
        same = [m for m in copied if not m[0].endswith("_calibrated")] == original
        print(
            f"{args.log}: {len(original)} messages, byte-identical in the copy: {same}; {result.added} added"
        )
        with LogReader(args.log) as r_in, LogReader(out) as r_out:
            decoded_in = {t: concat_batches(b) for t, b in r_in.read().items()}
            decoded_out = {t: concat_batches(b) for t, b in r_out.read().items() if t.endswith("_calibrated")}
    table = pd.read_parquet(args.labelled / f"{args.log.stem}.parquet")
    for group, entry in manifest["graphs"].items():
        if group == manifest["fused"]:
            continue
        name = entry["models"][group]
        pred = pd.read_parquet(args.trained / group / "predictions.parquet")
        pred = pred[pred[S.LOG] == args.log.stem].merge(table, on=S.STAMP, how="left")
        x = pred[[c["column"] for c in entry["inputs"]]].to_numpy(np.float64)
        y = run(session(args.models / entry["files"]["float64"]), x)
        stored = pred[[c for s in entry["sensors"] for c in S.prediction_cols(name, s)]].to_numpy()
        print(
            f"{group} ({name}): graph on evaluate's inputs vs its predictions, {len(x)} samples: "
            f"max |diff| {np.abs(y - stored).max():.2g} N/Nm"
        )
        for s, sensor in enumerate(entry["sensors"]):
            raw = decoded_in[params.topics.sensor_topic("ft_wrench", sensor)]
            cal = decoded_out[params.topics.sensor_topic("ft_wrench", sensor) + "_calibrated"]
            print(
                f"  {sensor}: {len(raw['stamp_ns'])} raw wrench messages, {len(cal['stamp_ns'])} calibrated"
            )
            stamps = pred[S.STAMP].to_numpy()
            inside = (cal["stamp_ns"] >= stamps[0]) & (cal["stamp_ns"] <= stamps[-1])
            pred_at = _at(stamps, stored[:, 6 * s : 6 * s + 6], cal["stamp_ns"][inside])
            raw_cols = pred[S.wrench_cols(S.FT, sensor)].to_numpy()
            raw_in = np.isin(raw["stamp_ns"], cal["stamp_ns"][inside])
            raw_at = _at(stamps, raw_cols, raw["stamp_ns"][raw_in])
            d_cal = np.sqrt(np.mean((cal["wrench"][inside] - pred_at) ** 2, axis=0))
            d_raw = np.sqrt(np.mean((raw["wrench"][raw_in] - raw_at) ** 2, axis=0))
            print(f"    RMS calibrated message - prediction at its stamp (fx..tz): {np.round(d_cal, 3)}")
            print(f"    RMS raw message - evaluate's raw input at its stamp:       {np.round(d_raw, 3)}")


if __name__ == "__main__":
    main()
