"""The DVC pipeline's wiring that a new user relies on without seeing it.

Recorded deployment logs: ``deploy.real_logs`` is a folder tracked in git (it exists on every clone, empty
until a lab adds logs) and a dependency of the stages that read it, so adding a log there makes `dvc
status` report them changed and `dvc repro` re-run the deployment tests, with no `-f`. Checked on a fresh
clone of the committed repository.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import yaml

from tests.test_readme import stages, tracked

ROOT = Path(__file__).resolve().parents[1]


def _status(repo: Path, stage: str) -> dict:
    proc = subprocess.run(
        [sys.executable, "-m", "dvc", "status", stage, "--json"], cwd=repo, capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr[-1000:]
    return json.loads(proc.stdout or "{}")


def _changed_deps(status: dict, stage: str) -> dict[str, str]:
    out: dict[str, str] = {}
    for entry in status.get(stage, []):
        if isinstance(entry, dict):
            out.update(entry.get("changed deps", {}))
    return out


def test_adding_recorded_logs_makes_the_deployment_stages_stale(tmp_path: Path) -> None:
    real = yaml.safe_load((ROOT / "params.yaml").read_text())["deploy"]["real_logs"].rstrip("/")
    assert any(f.startswith(real + "/") for f in tracked()), f"{real} is not a folder tracked in git"
    wired = stages()
    assert real in wired["deploy_days"]["deps"]
    readers = [name for name in wired if name.startswith("evaluate@")]
    assert readers and all(real in wired[name]["deps"] for name in readers)

    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "--quiet", str(ROOT), str(clone)], check=True)
    assert (clone / real).is_dir()
    stage = "deploy_days"
    assert real not in _changed_deps(_status(clone, stage), stage)
    (clone / real / "2026_11_25_robot_logger_device.mat").write_bytes(b"a recorded deployment log")
    assert _changed_deps(_status(clone, stage), stage).get(real) == "modified"
