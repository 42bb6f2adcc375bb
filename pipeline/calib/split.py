"""Which labelled logs train, validate and test a group: whole logs, or time blocks of a kind's only one.

Validation and the cross-validation folds hold out whole training logs (`split_logs`), so that a model is
chosen on experiments it has not seen; a recording with one training segment (a lab's single yoga run) has
no second log of its kind to hold out, so its training log is cut into time blocks first (`time_blocks`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np
import pyarrow.parquet as pq

from pipeline.calib.data import ROLE_TEST, ROLE_TRAIN, LogInfo, derive_seed
from pipeline.core.errors import DataError
from pipeline.logs import schema as S

TIME_BLOCKS = 5  # blocks a kind's only training log is cut into (at least train.folds)
BLOCK_SEP = "#"  # a time block's name: <table>#<k>


def table_name(name: str) -> str:
    """The labelled table a log name reads (a time block's, `time_blocks`, is its table's)."""
    return name.split(BLOCK_SEP)[0]


def time_blocks(logs: Sequence[LogInfo], folds: int) -> tuple[list[LogInfo], str | None]:
    """`logs`, with each training log cut into max(TIME_BLOCKS, `folds`) blocks of equal duration
    (``<log>#<k>``) where no experiment kind has two training logs (a recording with one training segment):
    validation and the cross-validation folds then hold out blocks in time, the memory models' states
    starting afresh at each block (as at a test segment's start, or a calibrator's). Returns (logs, a note
    saying so, or None where nothing was cut)."""
    train = [log for log in logs if log.role == ROLE_TRAIN]
    kinds = [log.kind for log in train]
    if not train or any(kinds.count(k) > 1 for k in kinds):
        return list(logs), None
    k = max(TIME_BLOCKS, folds)
    out = []
    for log in logs:
        time = pq.read_table(log.path, columns=[S.TIME]).column(S.TIME).to_numpy() if log in train else []
        if len(time) == 0:
            out.append(log)
            continue
        edges = np.linspace(float(time.min()), float(time.max()), k + 1)
        edges[-1] = np.inf
        out += [
            replace(log, name=f"{log.name}{BLOCK_SEP}{b}", span=(edges[b], edges[b + 1])) for b in range(k)
        ]
    names = ", ".join(log.name for log in train)
    return (
        out,
        f"one training log per experiment kind ({names}): validation holds out {k} time blocks of it in turn",
    )


def split_logs(logs: Sequence[LogInfo], val_logs: int, seed: int, folds: int = 1) -> dict[str, Any]:
    """Whole-log split: test = role test; validation = `val_logs` training logs; train = the rest.

    Validation takes at most one log per experiment kind (type, supporting foot and part), never a
    kind's only training log, drawn with a generator seeded from `seed` (kinds in a seeded order, those of
    known-load logs first, then a seeded log of each): every kind of experiment stays in the training
    set. That is fold 0 of the cross-validation; fold k (k < `folds`) holds out, of the same kinds, the
    k-th next log of each in sorted order, so the folds' validation logs are disjoint. ``folds``: one
    {train, val} per fold.

    Raises:
        DataError: no training or no test logs, too few training logs for a validation set, or a held-out
            kind with fewer training logs than `folds`.
    """
    train = [log for log in logs if log.role == ROLE_TRAIN]
    test = [log.name for log in logs if log.role == ROLE_TEST]
    if not train:
        raise DataError("no training logs (role 'train' in the experiment metadata)")
    if not test:
        raise DataError("no test logs (role 'test' in the experiment metadata)")
    rng = np.random.default_rng(derive_seed(seed, "validation"))
    by_kind: dict[str, list[str]] = {}
    for log in train:
        by_kind.setdefault(log.kind, []).append(log.name)
    candidates = sorted(k for k, names in by_kind.items() if len(names) >= 2)
    order = [candidates[i] for i in rng.permutation(len(candidates))]
    # known-load logs are validated on first: their labels leave the relation a free limb's wrenches
    # follow, so a model that exploits it loses there (the order is otherwise the seeded one)
    loaded = {log.kind for log in train if log.known_load}
    order = [k for k in order if k in loaded] + [k for k in order if k not in loaded]
    first = {k: int(rng.integers(len(by_kind[k]))) for k in order[:val_logs]}
    if not first:
        raise DataError(
            f"cannot hold out a validation log: no experiment kind has 2 or more training logs "
            f"(training logs: {', '.join(log.name for log in train)})"
        )
    short = [k for k in first if len(by_kind[k]) < folds]
    if short:
        raise DataError(
            f"cannot make {folds} cross-validation folds by whole logs: experiment kind {short[0]!r} has "
            f"only {len(by_kind[short[0]])} training logs (train.folds at most that)"
        )
    names = sorted(log.name for log in train)
    cv = []
    for k in range(folds):
        val = sorted(sorted(by_kind[kind])[(j + k) % len(by_kind[kind])] for kind, j in first.items())
        cv.append({"train": [n for n in names if n not in val], "val": val})
    return {**cv[0], "test": sorted(test), "folds": cv}
