"""An exception inside a forked job reaches the user as one line, ``ftcal: error: <job's file or name>:
<what>``, exit 2, with its full traceback in a file the line names: a library's own exceptions (scipy's
ValueError, Pinocchio's RuntimeError, raised for real), an FtcalError as it is, a killed worker. Each stage
that forks runs through the CLI with its job's function made to raise (the inputs need only reach it)."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from pipeline.cli import main
from pipeline.core.errors import DataError, JobError
from pipeline.core.parallel import forked_map
from tests.conftest import REPO
from tests.factories.labelled import LEG
from tests.factories.params import repo_params


def scipy_error(*_: object, **__: object) -> None:
    import scipy.signal

    scipy.signal.savgol_filter(np.zeros(3), 7, 2)  # ValueError: the window is longer than the data


def pinocchio_error(*_: object, **__: object) -> None:
    import pinocchio as pin

    pin.Inertia(1.0, np.zeros(3), -np.eye(3))  # RuntimeError: The 3d inertia should be positive.


SCIPY = r"ValueError: If mode is 'interp', window_length must be less than or equal to the size of x\."
PINOCCHIO = r"RuntimeError: The 3d inertia should be positive\."


def _traceback_file(line: str, label: str, what: str, function: str) -> Path:
    """The file named by a job's error line (checked: the label, the exception, the traceback in it)."""
    match = re.fullmatch(rf"{label}: {what} \(traceback in (\S+)\)", line)
    assert match, line
    path = Path(match.group(1))
    text = path.read_text()
    assert re.fullmatch(label, text.splitlines()[0]), text[:200]  # headed by the job's label
    assert "Traceback (most recent call last)" in text and f"in {function}" in text
    return path


@pytest.mark.parametrize("workers", [2, 1])
def test_a_library_exception_names_the_job_and_its_traceback_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, workers: int
) -> None:
    monkeypatch.chdir(tmp_path)
    jobs, labels = [lambda: 1, scipy_error, lambda: 3], ["a.mcap", "b.mcap", "c.mcap"]
    with pytest.raises(JobError) as info:
        list(forked_map(jobs, workers=workers, labels=labels))
    path = _traceback_file(str(info.value), "b.mcap", SCIPY, "scipy_error")
    assert path.parent == Path(".ftcal", "tracebacks")
    with pytest.raises(JobError) as info:
        list(forked_map([lambda: 0, pinocchio_error], workers=workers, labels=["l_leg_ft", "r_leg_ft"]))
    _traceback_file(str(info.value), "r_leg_ft", PINOCCHIO, "pinocchio_error")


def test_an_ftcal_error_keeps_its_message() -> None:
    def bad_log() -> None:
        raise DataError("data/raw/run.mcap: truncated chunk at byte 1234")

    for workers in (2, 1):
        with pytest.raises(DataError) as info:
            list(forked_map([lambda: 0, bad_log], workers=workers, labels=["x", "y"]))
        assert str(info.value) == "data/raw/run.mcap: truncated chunk at byte 1234"


def test_a_killed_worker_is_named_among_the_pending_jobs() -> None:
    def killed() -> None:
        os.kill(os.getpid(), signal.SIGKILL)

    with pytest.raises(JobError, match=r"^b\.parquet(, \S+)*: a worker process ended abruptly"):
        list(forked_map([lambda: 0, killed], workers=2, labels=["a.parquet", "b.parquet"]))


# --- every forking stage through the CLI ------------------------------------------------------------------


def _junk(folder: Path, suffix: str) -> list[Path]:
    """Two files the stage finds (their contents never read: the job raises first)."""
    folder.mkdir(parents=True, exist_ok=True)
    files = [folder / f"{name}{suffix}" for name in ("a", "b")]
    for f in files:
        f.write_bytes(b"never read")
    return files


def _simulate(tmp: Path, _: dict) -> tuple[list[str], str]:
    data = repo_params()
    data["simulate"].update(
        workers=2, plots=False, logs=[{"type": "pole", "duration_s": 2, "role": "train"}] * 2
    )
    (tmp / "params.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    argv = ["simulate", str(tmp / "sim"), "--quiet", "--params", str(tmp / "params.yaml")]
    return argv, r"simulate\.logs\[[01]\] \(0[01]_pole_train\)"


def _files_stage(command: str, suffix: str) -> Callable[[Path, dict], tuple[list[str], str]]:
    def build(tmp: Path, _: dict) -> tuple[list[str], str]:
        files = _junk(tmp / "in", suffix)
        label = "|".join(re.escape(str(f)) for f in files)
        return [command, str(tmp / "in"), str(tmp / "out")], f"(?:{label})"

    return build


def _train(tmp: Path, trained: dict) -> tuple[list[str], str]:
    argv = [
        "train", LEG, str(trained["labelled"]), str(tmp / "models"), "--studies", str(tmp / "studies"),
        "--params", str(trained["params"]),
    ]  # fmt: skip
    return argv, rf"{LEG}: search of the (?:7|13)-input network"


def _evaluate(tmp: Path, trained: dict) -> tuple[list[str], str]:
    argv = [
        "evaluate", LEG, str(trained["models"] / LEG), str(trained["labelled"]), str(tmp / "reports"),
        "--params", str(trained["params"]),
    ]  # fmt: skip
    return argv, rf"{LEG}: (?:noise check|errors of \S+)"


STAGES = {  # command -> (its inputs and argv, the function its forked jobs call, the exception raised there)
    "simulate": (_simulate, "pipeline.sim.experiment.simulate_log", pinocchio_error),
    "ingest": (_files_stage("ingest", ".mcap"), "pipeline.stages.ingest.ingest_one", scipy_error),
    "smooth": (_files_stage("smooth", ".parquet"), "pipeline.logs.smoothing.smooth_table", scipy_error),
    "label": (_files_stage("label", ".parquet"), "pipeline.labels.table.label_table", pinocchio_error),
    "deploy-prepare": (
        _files_stage("deploy-prepare", ".mcap"),
        "pipeline.deploy.prepare._prepare_one",
        scipy_error,
    ),
    "train": (_train, "pipeline.calib.search.search_network", pinocchio_error),
    "evaluate": (_evaluate, "pipeline.evaluation.results.noise_check", scipy_error),
}


@pytest.mark.parametrize("command", list(STAGES))
def test_a_forked_stage_job_error_is_one_line_and_exit_2(
    command: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capfd: pytest.CaptureFixture[str],
    request: pytest.FixtureRequest,
    mlflow_store: None,
) -> None:
    build, target, raising = STAGES[command]
    trained = request.getfixturevalue("trained_models") if command in ("train", "evaluate") else {}
    argv, label = build(tmp_path, trained)
    monkeypatch.setattr(target, raising)
    monkeypatch.chdir(tmp_path)
    capfd.readouterr()
    assert main(argv) == 2
    err = capfd.readouterr().err
    assert len(err.splitlines()) == 1, err
    what = SCIPY if raising is scipy_error else PINOCCHIO
    path = _traceback_file(err.removeprefix("ftcal: error: ").rstrip("\n"), label, what, raising.__name__)
    assert (tmp_path / path).is_file()


def test_a_deployment_test_error_names_the_log_group_and_day(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The deployment tests of a group (`ftcal deploy-test`) run each test of each day in a forked job."""
    from pipeline.deploy import group as G
    from pipeline.deploy.prepare import DeployLog

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(
        G, "DAY_TESTS", {"test_a": ("standing", lambda c, g: ({}, {})), "test_c": ("pole", pinocchio_error)}
    )
    ctx = G.GroupDay(LEG, [LEG], tmp_path, tmp_path, "nn7", None, None, None, None, "later", tmp_path)
    logs = [
        DeployLog(
            kind,
            Path(f"data/deploy/later/{k:02d}_{kind}_test.mcap"),
            tmp_path,
            tmp_path,
            None,
            {"type": kind},
        )
        for k, kind in enumerate(("standing", "pole"))
    ]
    with pytest.raises(JobError) as info:
        G.run_days([(ctx, logs)])
    label = rf"data/deploy/later/01_pole_test\.mcap \({LEG} test_c, day later\)"
    _traceback_file(str(info.value), label, PINOCCHIO, "pinocchio_error")


# --- nothing left behind: a failed or interrupted stage ends and reaps its workers ----------------------


def _session(sid: int) -> list[str]:
    """The processes of session `sid` (zombies too), as ``pid state``."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()  # after "pid (comm)": state ppid pgrp sid
        except (OSError, IndexError):
            continue
        if int(fields[3]) == sid:
            found.append(f"{stat.parent.name} {fields[0]}")
    return found


def _children(pid: int) -> list[int]:
    kids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, IndexError):
            if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == pid:
                kids.append(int(stat.parent.name))
    return kids


def _interruptible() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class _Ftcal:
    """`python -m pipeline.cli ARGS` in a session of its own, its stdout and stderr pipes read to their end
    by threads that note when each closed."""

    def __init__(self, argv: list[str], cwd: Path) -> None:
        env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{cwd / 'mlflow.db'}"}
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "pipeline.cli", *argv],
            cwd=cwd,
            env={**env, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))},
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            start_new_session=True,
            # as a terminal's foreground job: SIGINT handled (a shell's background job, as a CI runner may
            # start this suite, inherits it ignored, and Python then never raises KeyboardInterrupt)
            preexec_fn=_interruptible,
        )
        self.text: dict[str, str] = {}
        self.closed: dict[str, float] = {}
        self.readers = [
            threading.Thread(target=self._read, args=(name, stream), daemon=True)
            for name, stream in (("out", self.proc.stdout), ("err", self.proc.stderr))
        ]
        for reader in self.readers:
            reader.start()

    def _read(self, name: str, stream: Any) -> None:
        self.text[name] = stream.read().decode(errors="replace")
        self.closed[name] = time.monotonic()

    def finish(self, timeout: float = 120.0) -> tuple[int, float, list[str]]:
        """(exit status, seconds from the process's exit until both pipes closed, the processes of its
        session left then); whatever is left is killed, so that a failing test leaves nothing either."""
        try:
            status = self.proc.wait(timeout=timeout)
            exited = time.monotonic()
            for reader in self.readers:
                reader.join(timeout=10.0)
            left = _session(self.proc.pid)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
        assert set(self.closed) == {"out", "err"}, f"pipes open 10 s after the exit: {left}"
        return status, max(self.closed.values()) - exited, left


@pytest.mark.slow
def test_a_failed_stage_leaves_no_process_and_closes_the_callers_pipes(tmp_path: Path) -> None:
    """Both logs fail in their workers while the other worker waits for work: every worker ended."""
    _junk(tmp_path / "in", ".mcap")
    run = _Ftcal(["ingest", str(tmp_path / "in"), str(tmp_path / "out")], tmp_path)
    status, lag, left = run.finish()
    assert status == 2, run.text
    assert run.text["err"].startswith("ftcal: error: ") and len(run.text["err"].splitlines()) == 1
    assert lag < 1.0, f"the pipes closed {lag:.2f} s after ftcal exited"
    assert left == []
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out*"))


@pytest.mark.slow
@pytest.mark.parametrize("how", ["Ctrl-C", "SIGTERM"])
def test_an_interrupted_stage_leaves_no_process_and_no_output(tmp_path: Path, how: str) -> None:
    data = repo_params()
    logs = [{"type": "pole", "duration_s": 300, "role": "train"}] * 2  # minutes of work each
    data["simulate"].update(workers=2, plots=False, logs=logs)
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    argv = ["simulate", str(tmp_path / "sim"), "--quiet", "--params", str(tmp_path / "params.yaml")]
    run = _Ftcal(argv, tmp_path)
    deadline = time.monotonic() + 60.0
    while len(_children(run.proc.pid)) < 2:  # both workers forked and simulating
        assert run.proc.poll() is None and time.monotonic() < deadline, run.text
        time.sleep(0.05)
    time.sleep(0.5)
    if how == "Ctrl-C":  # the terminal sends SIGINT to the whole foreground process group
        os.killpg(run.proc.pid, signal.SIGINT)
    else:  # a supervisor (DVC, a CI job, systemd) signals the process it started
        os.kill(run.proc.pid, signal.SIGTERM)
    status, lag, left = run.finish(timeout=30.0)
    assert status == (130 if how == "Ctrl-C" else 143), run.text
    assert run.text["err"].strip() == ("ftcal: interrupted" if how == "Ctrl-C" else "ftcal: terminated")
    assert lag < 1.0, f"the pipes closed {lag:.2f} s after ftcal exited"
    assert left == []
    assert not (tmp_path / "sim").exists() and not list(tmp_path.glob(".sim*"))
