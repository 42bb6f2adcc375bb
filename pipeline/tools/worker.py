"""`ftcal worker GROUP IN`: run trials of a group's Optuna searches beside the stage `train@GROUP`.

With ``train.storage`` (or ``$FTCAL_OPTUNA_STORAGE``) set to a database URL, any number of workers, on any
machine with the same code, params and labelled directory, join the studies the stage opens for GROUP (one
per network size, in the stage's order) and run their trials until each holds its n_trials; the stage
then picks the best network and writes its outputs as it always does. A worker prepares the data with the
stage's own code (`pipeline.calib.fit.prepare`), so it finds the study by the same name, a hash of
params, data and code: a worker with other data or code waits for a study that never comes, and says so.
A worker needs no MLflow: each trial's record stays in the study, and the stage logs every trial of its
search, wherever it ran, once as a child of its own MLflow run. Stop a worker at any time: a trial it was
running is failed and run again by another process.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from pipeline.core.errors import ConfigError

DEFAULT_WAIT = 600.0  # s a worker waits for the stage to open a study


def run_worker_group(
    params_path: Path | None, group_name: str, in_dir: Path, wait: float = DEFAULT_WAIT
) -> dict[str, int]:
    """Join each network study of `group_name` in turn and run its trials; return trials run per network.

    Raises:
        ConfigError: no database storage is configured (a journal file is not shared).
        StudyError: the stage did not open a study within `wait` s, or the database is unreachable.
    """
    from pipeline.calib import studies
    from pipeline.calib.fit import prepare
    from pipeline.calib.fitting import fit_affine
    from pipeline.calib.run import study_identity
    from pipeline.calib.search import _Search  # the stage's search of one network, joined here
    from pipeline.calib.training import one_thread
    from pipeline.core.config import load_params
    from pipeline.core.progress import ProgressLog

    params = load_params(params_path)
    prep = prepare(params, group_name, in_dir)
    url = studies.storage_url(prep.cfg.storage)
    if url is None:
        raise ConfigError(
            f"ftcal worker needs a shared study: set train.storage or ${studies.ENV_STORAGE} to a database "
            "URL"
        )
    one_thread()
    storage = studies.open_storage(url, Path(), prep.cfg.heartbeat)
    identity = study_identity(params, prep)
    ui = ProgressLog()
    # the networks correct the group's affine map: fitted as the stage fits it (deterministic least squares)
    start = fit_affine(prep.gp, prep.group, prep.train, prep.seed)
    ran: dict[str, int] = {}
    with ui.running():
        for n_inputs in prep.gp.inputs:
            data = (prep.train, prep.val)
            gp, group, seed = prep.gp, prep.group, params.seed
            search = _Search(gp, group, data, start, n_inputs, seed, storage, identity, ui)
            search.join(wait)
            ran[search.name], _ = search.run()
    return ran


def _cmd(args: argparse.Namespace) -> int:
    ran = run_worker_group(args.params, args.group, args.inputs, args.wait)
    print(
        f"{args.group}: " + ", ".join(f"{name} {n} trials" for name, n in ran.items()) + " run by this worker"
    )
    return 0


def add_cli(subparsers: Any) -> None:
    """Add `ftcal worker GROUP IN`."""
    parser = subparsers.add_parser(
        "worker",
        help="run Optuna trials of a group's search beside the stage (shared database)",
        description=(__doc__ or "").split("\n\n")[0],
    )
    parser.add_argument("group", help="sensor group: a key of train.groups in params.yaml")
    parser.add_argument("inputs", type=Path, metavar="IN", help="directory of labelled <log>.parquet tables")
    parser.add_argument(
        "--wait",
        type=float,
        default=DEFAULT_WAIT,
        metavar="S",
        help=f"seconds to wait for the stage to open each study (default {DEFAULT_WAIT:.0f})",
    )
    parser.add_argument(
        "--params",
        type=Path,
        default=None,
        metavar="PATH",
        help="params file (default: params.yaml at the repo root)",
    )
    parser.set_defaults(func=_cmd)
