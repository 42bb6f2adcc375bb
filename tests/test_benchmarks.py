"""Every benchmark README.md and docs/ name runs: each command they show, with ``--quick`` (a run of seconds
through every step; its figures mean nothing), exits 0 and prints its last line. A benchmark that measures a
pipeline's outputs runs in the test that makes them; one that cannot run in seconds says why here."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from functools import cache

import pytest

from pipeline.tools import db
from tests.factories.docs import DOCS, ROOT, commands

ELSEWHERE = {  # run on the outputs of a pipeline, in the test that runs one
    "benchmarks/calibrate_agreement.py": "tests/test_e2e.py",
    "benchmarks/identify.py": "tests/test_e2e.py",
    "benchmarks/recurrent.py": "tests/test_e2e.py",
}
NOT_RUN = {  # why a benchmark cannot run in seconds
    "benchmarks/group_edit.py": "it edits params.yaml of an up-to-date pipeline and times `dvc repro`",
    "benchmarks/variant.py": "it writes a copy of the repository whose whole pipeline `dvc repro` then runs",
}
NEEDS_POSTGRES = {"benchmarks/search_scaling.py"}  # starts its own PostgreSQL server
PLACEHOLDERS = {"N": "16"}  # `--hidden N`
LAST_LINE = {  # what each benchmark's last line begins with
    "benchmarks/sim_speed.py": "simulated seconds per wall second",
    "benchmarks/label_speed.py": "ratio ours / iDynTree",
    "benchmarks/ingest_speed.py": "ratio ingest / mcap_ros2",
    "benchmarks/infer_speed.py": "ratio torch / onnxruntime",
    "benchmarks/calibrate_speed.py": "rate / target",
    "benchmarks/search_scaling.py": "  speed-up",
    "benchmarks/stability.py": "largest relative difference",
}


def named() -> set[str]:
    """Every benchmark script the docs name (in commands, inline or across a line break)."""
    return {m for doc in DOCS for m in re.findall(r"benchmarks/\w+\.py", doc.read_text())}


@cache
def quick_commands() -> tuple[str, ...]:
    """The distinct ``python benchmarks/...`` commands of the docs not run elsewhere, placeholders filled,
    with ``--quick``; ``python <script> --quick`` for a script they name without a command."""
    out = []
    for _, line in commands():
        words = shlex.split(line)
        if words[:1] != ["python"] or not words[1].startswith("benchmarks/") or words[1] in ELSEWHERE:
            continue
        words = [PLACEHOLDERS.get(w, w) for w in words]
        command = " ".join([*words, "--quick"])
        if command not in out:
            out.append(command)
    shown = {shlex.split(c)[1] for c in out}
    rest = sorted(named() - shown - set(ELSEWHERE) - set(NOT_RUN))
    return (*out, *(f"python {script} --quick" for script in rest))


def test_every_named_benchmark_runs_here_or_says_where() -> None:
    shown = {shlex.split(c)[1] for c in quick_commands()}
    assert named() <= shown | set(ELSEWHERE) | set(NOT_RUN)
    for script in named():
        assert (ROOT / script).is_file(), script
    for script, test in ELSEWHERE.items():
        assert script in (ROOT / test).read_text(), f"{test} does not run {script}"
    for script in shown:
        assert "--quick" in (ROOT / script).read_text(), f"{script} has no --quick"
        assert script in LAST_LINE, f"{script}: add what its last line begins with to LAST_LINE"


def _run(command: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MLFLOW_TRACKING_URI": ""}
    env.pop("MLFLOW_TRACKING_URI")  # each benchmark makes its own throwaway store
    args = [sys.executable, *shlex.split(command)[1:]]
    return subprocess.run(args, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def runs() -> dict[str, subprocess.CompletedProcess[str]]:
    """Every quick command, two at a time (most of their time is starting Python and its libraries)."""
    wanted = [c for c in quick_commands() if shlex.split(c)[1] not in NEEDS_POSTGRES or _postgres()]
    with ThreadPoolExecutor(2) as pool:
        return dict(zip(wanted, pool.map(_run, wanted), strict=True))


def _postgres() -> bool:
    if db.find_bindir() is not None:
        return True
    if os.environ.get("CI") == "true":
        pytest.fail("PostgreSQL server binaries absent: .ci/run installs them in CI")
    return False


@pytest.mark.slow
@pytest.mark.parametrize("command", quick_commands())
def test_benchmark_runs_quick(command: str, runs: dict[str, subprocess.CompletedProcess[str]]) -> None:
    if command not in runs:
        pytest.skip("PostgreSQL server binaries absent (apt-get install postgresql)")
    proc = runs[command]
    assert proc.returncode == 0, f"{command}:\n{proc.stderr[-3000:]}"
    last = proc.stdout.strip().splitlines()[-1]
    assert last.startswith(LAST_LINE[shlex.split(command)[1]]), f"{command}: last line {last!r}"
