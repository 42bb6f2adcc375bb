"""Pruning of a network search's trials that does not depend on which trial finished first, nor on the
last bits of their errors.

Optuna's MedianPruner compares a trial with the trials complete when it asks. With several processes
sharing a study (`pipeline.calib.studies`) that set depends on which trials finished first, and a trial
whose error lies within a last bit of the median is pruned on one machine and run to the end on another,
where it may become the best. `SlotPruner` decides from the study's slots instead:

- trial k (its slot, `pipeline.calib.studies.trial_index`) is compared at epoch e with the slots before
  it that reported epoch e, whatever they became later (complete, pruned after e, still running: it then
  waits for their epoch e), never with a later slot; the first ``startup`` slots are never pruned;
- it is pruned at an epoch e >= ``warmup`` when its lowest error so far exceeds their median by more than
  ``margin`` (relative).

One process runs the slots in order, so its decisions are those of any number of processes. A trial
within the margin of the median, which may still end best, always runs to the end; a trial pruned lags
the median by more than the margin and would seldom have become the best: a last-bit difference that
moves a trial across the boundary seldom changes which trial wins. A slot whose process died is not
waited for (a database marks it failed after two heartbeats; it runs again later): only then can the
decision depend on timing.
"""

from __future__ import annotations

import math
import time
import warnings
from typing import Any

import numpy as np

from pipeline.calib.studies import trial_index

_POLL_S = 0.5  # s between looks at a slot still running before the epoch a decision needs


class SlotPruner:
    """An Optuna pruner (`optuna.pruners.BasePruner`'s interface): see the module docstring."""

    def __init__(self, startup: int, warmup: int, margin: float, poll: float = _POLL_S) -> None:
        self.startup, self.warmup, self.margin, self.poll = startup, warmup, margin, poll

    def prune(self, study: Any, trial: Any) -> bool:
        """Whether `trial` (a FrozenTrial that just reported its epoch) stops here."""
        step = trial.last_step
        index = trial_index(trial)
        if step is None or step < self.warmup or index < self.startup:
            return False
        best = min(trial.intermediate_values.values())
        if math.isnan(best):
            return True
        reference = self.reference(study, index, step)
        if not reference:
            return False
        return best > (1.0 + self.margin) * float(np.median(reference))

    def reference(self, study: Any, index: int, step: int) -> list[float]:
        """The errors at epoch `step` of the slots before `index`, in slot order (waiting for a running
        slot's epoch `step` on a shared storage)."""
        values: list[float] = []
        for slot in range(index):
            value = self._slot_value(study, slot, step)
            if value is not None:
                values.append(value)
        return values

    def _slot_value(self, study: Any, slot: int, step: int) -> float | None:
        from optuna.storages import fail_stale_trials
        from optuna.storages._heartbeat import is_heartbeat_enabled
        from optuna.trial import TrialState

        shared = is_heartbeat_enabled(study._storage)
        while True:
            live = [
                t
                for t in study.get_trials(deepcopy=False)
                if trial_index(t) == slot
                and t.state in (TrialState.COMPLETE, TrialState.PRUNED, TrialState.RUNNING)
            ]
            if not live:  # not run yet, or failed and queued again: nothing to wait for
                return None
            t = live[0]
            if step in t.intermediate_values:
                return float(t.intermediate_values[step])
            if t.state != TrialState.RUNNING or not shared:  # ended before `step` (or a journal's leftover)
                return None
            with warnings.catch_warnings():  # Optuna calls heartbeats experimental
                warnings.simplefilter("ignore")
                fail_stale_trials(study)  # a dead process's slot stops being waited for
            time.sleep(self.poll)
