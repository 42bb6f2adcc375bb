"""One group's training decisions without MLflow, in this process or a fresh one: what tests compare
between runs that differ the way two machines do.

    python -m tests.searchrun PARAMS GROUP LABELLED STUDIES    # prints the decisions as JSON

Only the standard library and `pipeline` are imported at the top, so that `pipeline` pins the numerical
kernels (`pipeline.core.kernels`) before numpy and torch load, as in an ``ftcal`` process.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path
from typing import Any

from pipeline.calib.fit import prepare
from pipeline.calib.run import fit_models
from pipeline.calib.training import one_thread
from pipeline.core.config import load_params
from pipeline.core.progress import ProgressLog


def decisions(params_path: Path, group: str, labelled: Path, studies: Path) -> dict[str, Any]:
    """The search's trials (slot, state, values, per-epoch validation errors), each network's best trial,
    epoch and a hash of its weights, every model's fold scores and the model chosen to deploy."""
    params = load_params(params_path)
    prep = prepare(params, group, labelled)
    one_thread()  # as the stage
    fitted = fit_models(params, prep, studies, ProgressLog(False))
    nets = {}
    searched = {n: m.result for n, m in fitted.models.items() if getattr(m, "result", None) is not None}
    for name, r in searched.items():
        weights = hashlib.sha256(b"".join(v.numpy().tobytes() for v in r.model.state_dict().values()))
        nets[name] = {
            "trials": [
                {"slot": i, "state": state, "values": values, "val_rmse": [h["val_rmse"] for h in history]}
                for i, values, history, state, _ in r.trials
            ],
            "best": [r.trial, r.best_epoch, r.val_rmse],
            "weights": weights.hexdigest(),
        }
    return {"networks": nets, "scores": fitted.cv["scores"], "chosen": fitted.cv["chosen"]}


if __name__ == "__main__":
    params_path, group, labelled, studies = sys.argv[1:5]
    print(json.dumps(decisions(Path(params_path), group, Path(labelled), Path(studies))))
