"""How often each label is exact: per experiment type, over every labelled log (train and test).

For every label of the labelled tables (a sensor ``sw.<sensor>``, a foot pair's sum ``sw.<pair>``, a cut
set's sum ``sw.<cut>``), the samples whose switch is 1, per experiment type (``ftcal.experiment`` type).
Besides, per experiment type with double-support samples (phase ``double`` of
`pipeline.evaluation.phases`), the same counts over the double-support samples outside the guard bands:
within ``label.guard_s`` of a contact change every switch is 0 by construction, so those samples say
nothing about which labels double support allows and are counted apart.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.core.errors import DataError
from pipeline.evaluation.phases import DOUBLE, feet_of, phases_of
from pipeline.logs import schema as S

SENSOR, PAIR, CUT = "sensor", "foot pair", "cut set"


def _kinds(label_meta: dict[str, Any], names: list[str]) -> dict[str, str]:
    pairs = set(label_meta.get("pairs") or {})
    cuts = {str(c.get("label")) for c in (label_meta.get("cut_sets") or {}).values() if isinstance(c, dict)}
    return {n: PAIR if n in pairs else CUT if n in cuts else SENSOR for n in names}


def _empty() -> dict[str, Any]:
    return {"logs": 0, "samples": 0, "guard": 0, "exact": {}}


def label_availability(labelled_dir: Path) -> dict[str, Any]:
    """Exact-label counts of every ``<log>.parquet`` of `labelled_dir` (module docstring).

    Returns ``{"guard_s": s or None, "labels": {name: kind}, "types": {type: counts}, "double": {type:
    counts}}`` with counts ``{"logs", "samples", "guard" (samples in a guard band), "exact": {label:
    samples with switch 1}}``; under "double", samples are those in double support outside the guard
    bands and "guard" the double-support samples inside one.

    Raises:
        DataError: no labelled table, or a table without contacts, guard or switch columns.
    """
    paths = sorted(p for p in Path(labelled_dir).glob(f"*{S.PARQUET_SUFFIX}") if p.is_file())
    if not paths:
        raise DataError(f"{labelled_dir}: no labelled tables (run `dvc repro label`)")
    out: dict[str, Any] = {"guard_s": None, "labels": {}, "types": {}, "double": {}}
    for path in paths:
        try:
            schema = pq.read_schema(path)
            names = [c[len(S.SWITCH) + 1 :] for c in schema.names if c.startswith(S.SWITCH + ".")]
            missing = [c for c in (S.CONTACTS, S.GUARD) if c not in schema.names]
            if missing or not names:
                raise DataError(
                    f"{path}: not a labelled table: no {missing[0] if missing else 'sw.* column'}"
                )
            cols = [S.CONTACTS, S.GUARD, *(S.switch_col(n) for n in names)]
            table = pq.read_table(path, columns=cols)
        except (OSError, pa.ArrowException) as exc:
            raise DataError(f"{path}: cannot read Parquet table: {exc}") from None
        label_meta = S.read_metadata(schema, S.META_LABEL) or {}
        kind = str((S.read_metadata(schema, S.META_EXPERIMENT) or {}).get("type", "")).strip() or "unknown"
        guard_s = (label_meta.get("params") or {}).get("guard_s")
        if out["guard_s"] is None and isinstance(guard_s, int | float):
            out["guard_s"] = float(guard_s)
        for name, what in _kinds(label_meta, names).items():
            out["labels"].setdefault(name, what)
        guard = table.column(S.GUARD).to_numpy(zero_copy_only=False).astype(bool)
        double = phases_of(table.column(S.CONTACTS).to_pylist(), feet_of(label_meta)) == DOUBLE
        per_type = out["types"].setdefault(kind, _empty())
        _add(per_type, table, names, np.ones(len(guard), dtype=bool), guard)
        if double.any():
            _add(out["double"].setdefault(kind, _empty()), table, names, double & ~guard, double & guard)
    return out


def _add(
    counts: dict[str, Any], table: pa.Table, names: list[str], rows: np.ndarray, guard: np.ndarray
) -> None:
    """Add a table's `rows` (N,) to `counts` (and `guard` (N,) to its guard count)."""
    counts["logs"] += 1
    counts["samples"] += int(rows.sum())
    counts["guard"] += int(guard.sum())
    for name in names:
        on = table.column(S.switch_col(name)).to_numpy(zero_copy_only=False) == 1
        counts["exact"][name] = counts["exact"].get(name, 0) + int((on & rows).sum())
