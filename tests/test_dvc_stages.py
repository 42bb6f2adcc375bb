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

import pytest
import yaml

from pipeline.core.defaults import RESOLVED_FILE
from tests.factories.docs import stages, tracked
from tests.factories.params import repo_params

pytestmark = pytest.mark.slow  # clones the repository and runs DVC on it

ROOT = Path(__file__).resolve().parents[1]


def _status(repo: Path, stage: str | None = None) -> dict:
    which = [stage] if stage else []
    proc = subprocess.run(
        [sys.executable, "-m", "dvc", "status", *which, "--json"], cwd=repo, capture_output=True, text=True
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
    real = repo_params()["deploy"]["real_logs"].rstrip("/")
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


def test_recorded_logs_only_dvc_repro_simulates_nothing(tmp_path: Path) -> None:
    """`dvc repro simulate deploy_days` on a fresh clone with ingest.source on recorded logs (data/raw) that
    holds none yet: no log simulated, no URDF loaded (robot.urdf names an absent file), data/sim a note
    saying why; the deployment days, labelled with the training labels' URDF (models/identified), wait for
    the label stage, which stops at ingest with one line naming the empty folder (the steps of deploy_days
    on recorded logs: tests/test_recorded.py)."""
    import os

    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "--quiet", str(ROOT), str(clone)], check=True)
    data = yaml.safe_load((clone / "params.yaml").read_text())
    data["ingest"]["source"] = "data/raw"
    data["robot"]["urdf"] = "robots/absent.urdf"
    (clone / "params.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(clone), os.environ.get("PYTHONPATH")])),
        "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}",
    }
    simulated, days = (
        subprocess.run(
            [sys.executable, "-m", "dvc", "repro", stage], cwd=clone, env=env, capture_output=True, text=True
        )
        for stage in ("simulate", "deploy_days")
    )
    assert simulated.returncode == 0, simulated.stderr[-2000:]
    note = "simulate: data/sim: nothing simulated: ingest.source is data/raw, not data/sim"
    assert note in simulated.stdout
    assert days.returncode != 0 and "Traceback" not in days.stdout + days.stderr
    assert "ftcal: error: data/raw: no logs found (*.mcap, *.mat)" in days.stderr
    assert [p.name for p in (clone / "data/sim").iterdir()] == ["not_simulated.txt"]
    assert not (clone / "data/deploy/tables").exists()
    assert not list(clone.rglob("*.mcap"))


_CODE_HASHES = """
import json, sys
from dvc.repo import Repo
with Repo(sys.argv[1]) as repo:
    print(json.dumps({f"{stage.name} {dep.def_path}": dep.get_hash().value
                      for stage in repo.index.stages for dep in stage.deps
                      if dep.def_path.startswith("pipeline")}))
"""


def _code_hashes(repo: Path) -> dict[str, str]:
    """'<stage> <code path>' -> the hash DVC computes for that dependency now (what `dvc status` compares)."""
    proc = subprocess.run([sys.executable, "-c", _CODE_HASHES, str(repo)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-1000:]
    return json.loads(proc.stdout)


def _changed_params(repo: Path) -> dict[str, dict]:
    """stage -> the params `dvc status` finds changed against dvc.lock (key -> state), in the effective
    configuration the stages track (params.resolved.yaml, as the stage `config` writes it)."""
    out: dict[str, dict] = {}
    for name, entries in _status(repo).items():
        for entry in entries:
            changed = entry.get("changed deps", {}) if isinstance(entry, dict) else {}
            if isinstance(changed.get(RESOLVED_FILE), dict):
                out[name] = changed[RESOLVED_FILE]
    return out


def _resolve(clone: Path, env: dict[str, str]) -> None:
    """What `dvc repro config` does first: the clone's effective configuration written for its stages."""
    cmd = [sys.executable, "-m", "pipeline.cli", "params", "--write", RESOLVED_FILE]
    subprocess.run(cmd, cwd=clone, env=env, check=True, capture_output=True)


def test_bytecode_is_not_code_and_one_groups_edit_stales_only_its_stages(tmp_path: Path) -> None:
    """With Python writing bytecode (the default on a user's machine), an `ftcal` command's ``__pycache__``
    folders leave every stage's code dependencies as DVC hashes them; then an edit of one group's params
    makes only that group's train and evaluate stages and the report changed, and nothing else below them;
    a default moved in pipeline/defaults.yaml (the time-series zoom) makes only the stages that read it."""
    import os

    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "--quiet", str(ROOT), str(clone)], check=True)
    before, params_before = _code_hashes(clone), _changed_params(clone)
    assert before and not list((clone / "pipeline").rglob("__pycache__"))
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPATH"] = str(clone)
    for cmd in (["-m", "pipeline.cli", "simulate", "--help"], ["-m", "compileall", "-q", "pipeline"]):
        subprocess.run([sys.executable, *cmd], cwd=clone, env=env, check=True, capture_output=True)
    assert list((clone / "pipeline" / "stages" / "__pycache__").glob("*.pyc"))
    assert _code_hashes(clone) == before

    data = yaml.safe_load((clone / "params.yaml").read_text())
    group = next(iter(data["train"]["groups"]))
    data["train"]["groups"][group]["epochs"] = 3
    (clone / "params.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    _resolve(clone, env)
    after = _changed_params(clone)
    changed = {name for name in after if after[name] != params_before.get(name)}
    assert changed == {f"train@{group}", f"evaluate@{group}", "report"}  # the report reads train.groups
    wired, stale = stages(), set(changed)

    def paths(stage: dict, key: str) -> list[str]:
        return [(p if isinstance(p, str) else next(iter(p))).rstrip("/") for p in stage.get(key, [])]

    def reads(stage: dict, outs: list[str]) -> bool:
        deps = paths(stage, "deps")
        return any(d == o or o.startswith(d + "/") or d.startswith(o + "/") for d in deps for o in outs)

    while True:  # every stage below them: a dependency on (a folder of, a file in) one of their outputs
        outs = [o for name in stale for o in paths(wired[name], "outs")]
        below = {name for name, stage in wired.items() if reads(stage, outs)}
        if below <= stale:
            break
        stale |= below
    assert stale == changed

    defaults = clone / "pipeline" / "defaults.yaml"  # a default moved: what reads it, wherever it is set
    text = defaults.read_text()
    assert "  zoom_s: 8.0 " in text
    defaults.write_text(text.replace("  zoom_s: 8.0 ", "  zoom_s: 6.0 "))
    _resolve(clone, env)
    moved = {name for name, keys in _changed_params(clone).items() if keys != after.get(name)}
    assert moved == {name for name in wired if name.startswith("evaluate@")} | {"report"}, moved


def test_dvc_metrics_show_is_a_row_per_headline_and_per_day_within_a_terminal() -> None:
    """The committed metrics (a default `dvc repro`'s): one row per headline (the model to deploy, its error,
    the oracle, the noise floor, raw, a verdict) and one per deployment day, within 160 columns."""
    shown = subprocess.run(
        [sys.executable, "-m", "dvc", "metrics", "show"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout
    lines = shown.splitlines()
    assert max(map(len, lines)) <= 160, shown
    header, rows = lines[0].split(), {line.split()[0]: line for line in lines[1:] if line.strip()}
    assert {"deployed", "rmse", "oracle", "floor", "raw", "verdict"} <= set(header), header
    files = {f for f in tracked() if f.startswith("reports/metrics/") and f.endswith(".json")}
    assert set(rows) == files, sorted(set(rows) ^ files)  # each headline's and each day's file a row
    days = {f for f in files if f.startswith("reports/metrics/deployment/")}
    assert days and len(files - days) >= len(repo_params()["train"]["groups"])
