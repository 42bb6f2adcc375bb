"""Same data, same params, another machine: the same training, search and choice of the model to deploy.

Runs of one group's training (`tests.searchrun`: its trials, pruned or not, per-epoch validation errors, best
trials, weights, fold scores and chosen model) that differ the way two machines do must agree bit for bit:
another CPU's instruction sets (emulated through the libraries' own variables, in a fresh process: MKL,
OpenBLAS, numpy, ATen and oneDNN each take their AVX2 kernels on this machine), one core with OpenMP and MKL
asked for two threads (training takes one whatever they say: `pipeline.calib.training.one_thread`), labelled
inputs changed in their last bits, and trials that finish in another order. Another CPU vendor cannot be
emulated: MKL takes its one vendor-independent branch (`pipeline.core.kernels`).
"""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from pipeline.calib.crossval import close_steps
from pipeline.calib.params import select_by_folds, selection_steps
from pipeline.calib.pruning import SlotPruner
from pipeline.core import kernels
from pipeline.logs import schema as S
from tests.factories.labelled import LEG, write_labelled_logs
from tests.factories.params import TRAIN_PARAMS, write_params
from tests.searchrun import decisions

pytestmark = pytest.mark.slow  # trains the same search in several fresh processes

ROOT = Path(__file__).resolve().parents[1]
TWO_THREADS = {"OMP_NUM_THREADS": "2", "MKL_NUM_THREADS": "2", "MKL_DYNAMIC": "FALSE"}
# what an AVX2-only x86 machine's libraries would choose by themselves (this one may have AVX-512)
AVX2_MACHINE = {
    "MKL_ENABLE_INSTRUCTIONS": "AVX2",
    "ATEN_CPU_CAPABILITY": "avx2",
    "ONEDNN_MAX_CPU_ISA": "AVX2",
    "OPENBLAS_CORETYPE": "Haswell",
    "NPY_DISABLE_CPU_FEATURES": kernels.NUMPY_AVX512,
}


@pytest.fixture(scope="module")
def labelled(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_labelled_logs(tmp_path_factory.mktemp("labelled"), n=400)


def search_params(tmp_path: Path) -> Path:
    """A small search with params.yaml's policy: random trials only (tpe_startup_trials = n_trials)."""
    train = copy.deepcopy(TRAIN_PARAMS)
    train["defaults"].update(n_trials=3, tpe_startup_trials=3, prune_startup_trials=1, epochs=4)
    tmp_path.mkdir(parents=True, exist_ok=True)
    return write_params(tmp_path, train)


def _start(params: Path, labelled: Path, work: Path, env: dict[str, str], one_core: bool) -> subprocess.Popen:
    drop = (*AVX2_MACHINE, *TWO_THREADS, *kernels.PINS, kernels.ENV_SWITCH)
    clean = {k: v for k, v in os.environ.items() if k not in drop}
    cpu = min(os.sched_getaffinity(0))
    return subprocess.Popen(
        [sys.executable, "-m", "tests.searchrun", str(params), LEG, str(labelled), str(work / "studies")],
        cwd=ROOT,
        env={**clean, "OMP_WAIT_POLICY": "PASSIVE", **env},  # OpenMP's waits: two threads share one core
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=(lambda: os.sched_setaffinity(0, {cpu})) if one_core else None,
    )


@pytest.mark.skipif(not kernels.cpu_has_avx2(), reason="the kernels are pinned on x86-64 CPUs with AVX2")
def test_another_cpu_and_core_count_train_the_same(tmp_path: Path, labelled: Path) -> None:
    runs = {
        "this machine": (search_params(tmp_path / "a"), {}, False),
        "an AVX2 machine": (search_params(tmp_path / "b"), AVX2_MACHINE, False),
        "one core, two threads asked for": (search_params(tmp_path / "c"), TWO_THREADS, True),
    }
    procs = {
        name: _start(params, labelled, tmp_path / name.replace(" ", "_"), env, one_core)
        for name, (params, env, one_core) in runs.items()
    }
    out = {}
    for name, proc in procs.items():
        stdout, stderr = proc.communicate(timeout=300)
        assert proc.returncode == 0, (name, stderr[-2000:])
        out[name] = json.loads(stdout)
    first = out["this machine"]
    assert {t["state"] for n in first["networks"].values() for t in n["trials"]} == {"COMPLETE", "PRUNED"}
    for name, result in out.items():
        assert result == first, name


def perturb(src: Path, dst: Path, ulps: int, seed: int) -> None:
    """Copy the labelled tables, every float column but time changed by up to `ulps` float64 steps."""
    dst.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for path in sorted(src.glob("*.parquet")):
        table = pq.read_table(path)
        columns = []
        for name, column in zip(table.column_names, table.columns, strict=True):
            if pa.types.is_float64(column.type) and name != S.TIME:
                values = column.to_numpy(zero_copy_only=False)
                values = values * (1.0 + rng.integers(-ulps, ulps + 1, len(values)) * 2.0**-52)
                column = pa.array(values, pa.float64())
            columns.append(column)
        pq.write_table(pa.Table.from_arrays(columns, schema=table.schema), dst / path.name)


def test_inputs_changed_in_their_last_bits_train_the_same(tmp_path: Path, labelled: Path) -> None:
    """Another machine's smoothing and labelling may end in other last bits: the same training."""
    perturb(labelled, tmp_path / "changed", ulps=2, seed=0)
    params = search_params(tmp_path)
    a = decisions(params, LEG, labelled, tmp_path / "studies_a")
    b = decisions(params, LEG, tmp_path / "changed", tmp_path / "studies_b")
    assert a == b


def test_selection_records_its_steps_and_those_close_to_the_margin() -> None:
    # nn13 is 9.6 % better than nn7 on both folds: short of the 10 % margin by less than CLOSE
    scores = {"raw": [10.0, 10.2], "affine": [1.0, 1.1], "nn7": [0.5, 0.52], "nn13": [0.452, 0.47]}
    steps = selection_steps(scores, 0.1)
    assert [(s["model"], s["against"], s["won"]) for s in steps] == [
        ("affine", "raw", True),
        ("nn7", "affine", True),
        ("nn13", "nn7", False),
    ]
    assert steps[2]["gain"] == pytest.approx(1 - 0.461 / 0.51)
    assert select_by_folds(scores, 0.1) == "nn7"
    assert [s["model"] for s in close_steps(steps, 0.1)] == ["nn13"]
    assert close_steps(selection_steps(scores, 0.2), 0.2) == []  # 9.6 % is far from 20 %


# --- pruning ---------------------------------------------------------------------------------------

# a study with heartbeats whose trials the test drives itself (without Study.optimize): Optuna warns
HEARTBEATS = pytest.mark.filterwarnings(
    "ignore::UserWarning", "ignore::optuna.exceptions.ExperimentalWarning"
)

CURVES = {  # validation error per epoch of slots 0, 1 and two candidates for slot 2
    0: [1.0, 0.9, 0.8, 0.7],
    1: [1.0, 0.95, 0.85, 0.8],
    "close": [1.0, 0.97, 0.9, 0.8],  # within 10 % of the median (0.925, 0.825, 0.75): never pruned
    "lagging": [1.0, 1.0, 1.0, 0.9],  # 1.0 > 1.1 x 0.825 at epoch 2
}


def _study(tmp_path: Path, name: str, pruner: Any = None) -> Any:
    import optuna
    from optuna.storages import RDBStorage

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    # a database with heartbeats: a shared study, where the pruner waits for the earlier slots' epochs
    storage = RDBStorage(f"sqlite:///{tmp_path / name}.db", heartbeat_interval=60, grace_period=120)
    pruner = pruner or SlotPruner(startup=2, warmup=1, margin=0.1)
    return optuna.create_study(storage=storage, pruner=pruner)


def _run_slot(study: Any, trial: Any, curve: list[float], pause: float = 0.0) -> int | None:
    """Report `curve` epoch by epoch; the epoch the trial is pruned at, or None."""
    from optuna.trial import TrialState

    for epoch, value in enumerate(curve):
        time.sleep(pause)
        trial.report(value, epoch)
        if trial.should_prune():
            study.tell(trial, state=TrialState.PRUNED)
            return epoch
    study.tell(trial, curve[-1])
    return None


@HEARTBEATS
@pytest.mark.parametrize("third", ["close", "lagging"])
def test_pruning_does_not_depend_on_which_trial_finishes_first(tmp_path: Path, third: str) -> None:
    # in slot order, as one process runs them
    study = _study(tmp_path, "in_order")
    for slot in (0, 1):
        _run_slot(study, study.ask(), CURVES[slot])
    in_order = _run_slot(study, study.ask(), CURVES[third])
    # slot 2 reports each epoch before slots 0 and 1 do (other processes, slower): it waits for them
    study = _study(tmp_path, "out_of_order")
    trials = [study.ask() for _ in range(3)]
    early = threading.Thread(
        target=lambda: [_run_slot(study, trials[s], CURVES[s], pause=0.05) for s in (0, 1)]
    )
    early.start()
    out_of_order = _run_slot(study, trials[2], CURVES[third])
    early.join()
    assert in_order == out_of_order == {"close": None, "lagging": 2}[third]


@HEARTBEATS
def test_pruner_spares_the_startup_slots_and_a_trial_within_the_margin(tmp_path: Path) -> None:
    import optuna

    study = _study(tmp_path, "startup", SlotPruner(startup=2, warmup=1, margin=0.0))
    assert [_run_slot(study, study.ask(), CURVES[c]) for c in (0, "lagging")] == [None, None]
    pruned = {}
    for name, pruner in {
        "margin": SlotPruner(startup=2, warmup=1, margin=0.1),
        "no margin": SlotPruner(startup=2, warmup=1, margin=0.0),
        "median": optuna.pruners.MedianPruner(n_startup_trials=2, n_warmup_steps=1),
    }.items():
        study = _study(tmp_path, name.replace(" ", "_"), pruner)
        for slot in (0, 1):
            _run_slot(study, study.ask(), CURVES[slot])
        pruned[name] = _run_slot(study, study.ask(), CURVES["close"])
    # 0.97 > 0.925, the median of the earlier slots at epoch 1, but by less than 10 %
    assert pruned == {"margin": None, "no margin": 1, "median": 1}


# --- the pinned kernels ----------------------------------------------------------------------------


def test_pin_sets_what_is_unset_and_only_on_an_avx2_cpu(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    flags = tmp_path / "cpuinfo"
    flags.write_text("processor : 0\nflags : fpu sse2 avx avx2 fma avx512f\n")
    monkeypatch.setattr(kernels.platform, "machine", lambda: "x86_64")
    assert kernels.cpu_has_avx2(flags)
    flags.write_text("processor : 0\nflags : fpu sse2 avx\n")
    assert not kernels.cpu_has_avx2(flags)
    monkeypatch.setattr(kernels, "cpu_has_avx2", lambda: True)
    env = {"OPENBLAS_CORETYPE": "SkylakeX"}  # chosen by the user: kept
    assert kernels.pin(env) == {k: v for k, v in kernels.PINS.items() if k != "OPENBLAS_CORETYPE"}
    assert env == {**kernels.PINS, "OPENBLAS_CORETYPE": "SkylakeX"}
    assert kernels.pin({kernels.ENV_SWITCH: "native"}) == {}
    monkeypatch.setattr(kernels, "cpu_has_avx2", lambda: False)
    assert kernels.pin({}) == {}
