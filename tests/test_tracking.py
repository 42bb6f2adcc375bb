"""MLflow plumbing against a real sqlite store: URI resolution, one tagged run per stage, FAILED on error."""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
from mlflow import MlflowClient

from pipeline.core.tracking import MAX_PARAM_VALUE_LENGTH, flatten, stage_run, tracking_uri

ROOT = Path(__file__).resolve().parent.parent


def git(repo: Path, *args: str) -> str:
    cmd = ["git", "-c", "user.name=ftcal-test", "-c", "user.email=test@example.invalid", *args]
    return subprocess.run(cmd, cwd=repo, check=True, capture_output=True, text=True).stdout.strip()


@pytest.fixture(scope="module")
def temp_repo(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A committed git repo with a dvc.yaml: stage_run's default store is its mlflow.db.

    Shared by the module because creating an MLflow database takes seconds.
    """
    repo = tmp_path_factory.mktemp("repo")
    git(repo, "init", "-q")
    (repo / "dvc.yaml").write_text("stages: {}\n")
    (repo / ".gitignore").write_text("mlflow.db\nmlartifacts/\n")
    git(repo, "add", "dvc.yaml", ".gitignore")
    git(repo, "commit", "-q", "-m", "init")
    return repo


@pytest.fixture
def in_repo(temp_repo: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.chdir(temp_repo)
    yield temp_repo


def test_default_uri_is_repo_root_db_from_another_cwd(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # tmp_path has no dvc.yaml above it: the root is found from the installed package.
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.chdir(tmp_path)
    assert tracking_uri() == f"sqlite:///{(ROOT / 'mlflow.db').as_posix()}"
    monkeypatch.chdir(ROOT / "tests")
    assert tracking_uri() == f"sqlite:///{(ROOT / 'mlflow.db').as_posix()}"


def test_default_uri_follows_the_dvc_yaml(in_repo: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (in_repo / "sub").mkdir(exist_ok=True)
    monkeypatch.chdir(in_repo / "sub")
    assert tracking_uri() == f"sqlite:///{in_repo / 'mlflow.db'}"


def test_env_overrides_uri(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    uri = f"sqlite:///{tmp_path / 'elsewhere.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    assert tracking_uri() == uri


def test_flatten() -> None:
    nested = {"seed": 42, "robot": {"gravity": 9.8, "pairs": {"l": {"front": "a"}}, "list": [1, 2]}, "e": {}}
    assert flatten(nested) == {
        "seed": "42",
        "robot.gravity": "9.8",
        "robot.pairs.l.front": "a",
        "robot.list": "[1, 2]",
        "e": "{}",
    }
    assert flatten({"b": True, "n": None}) == {"b": "true", "n": "null"}
    long = flatten({"x": "y" * (MAX_PARAM_VALUE_LENGTH + 100)})["x"]
    assert len(long) == MAX_PARAM_VALUE_LENGTH and long.endswith("...")


def runs_of(client: MlflowClient, experiment: str) -> list:
    exp = client.get_experiment_by_name(experiment)
    assert exp is not None
    return client.search_runs([exp.experiment_id])


def test_a_step_of_a_dvc_stage_is_tagged_with_both(in_repo: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # `ftcal export ... + deploy-test ...` in stage evaluate@legs: DVC names the stage in $DVC_STAGE
    monkeypatch.setenv("DVC_STAGE", "evaluate@legs")
    with stage_run("export@legs", experiment="test-steps") as run:
        run_id = run.info.run_id
    tags = MlflowClient(f"sqlite:///{in_repo / 'mlflow.db'}").get_run(run_id).data.tags
    assert (tags["step"], tags["dvc.stage"]) == ("export@legs", "evaluate@legs")


def test_stage_run_logs_one_tagged_run(in_repo: Path) -> None:
    params = {"seed": 42, "robot": {"urdf": "iCubGenova09", "gravity": 9.80665}, "long": "z" * 7000}
    with stage_run("label", params, experiment="test-one-run") as run:
        run_id = run.info.run_id

    client = MlflowClient(f"sqlite:///{in_repo / 'mlflow.db'}")
    runs = runs_of(client, "test-one-run")
    assert [r.info.run_id for r in runs] == [run_id]
    got = runs[0]
    assert got.info.status == "FINISHED"
    assert got.info.run_name == "label"
    sha = git(in_repo, "rev-parse", "HEAD")
    assert got.data.tags["dvc.stage"] == got.data.tags["step"] == "label"  # run outside DVC
    assert got.data.tags["git.commit"] == sha
    assert got.data.tags["mlflow.source.git.commit"] == sha
    assert got.data.tags["git.dirty"] == "false"
    assert got.data.params["seed"] == "42"
    assert got.data.params["robot.urdf"] == "iCubGenova09"
    assert got.data.params["robot.gravity"] == "9.80665"
    assert len(got.data.params["long"]) == MAX_PARAM_VALUE_LENGTH
    # Artifacts live beside the database, not in the working directory.
    assert got.info.artifact_uri.startswith((in_repo / "mlartifacts").as_uri())


def test_failing_block_marks_run_failed(in_repo: Path) -> None:
    (in_repo / "untracked.txt").write_text("change")
    try:
        with (
            pytest.raises(RuntimeError, match="boom"),
            stage_run("train", {"lr": 0.1}, experiment="test-fail"),
        ):
            raise RuntimeError("boom")
    finally:
        (in_repo / "untracked.txt").unlink()

    client = MlflowClient(f"sqlite:///{in_repo / 'mlflow.db'}")
    runs = runs_of(client, "test-fail")
    assert len(runs) == 1
    assert runs[0].info.status == "FAILED"
    assert runs[0].data.tags["dvc.stage"] == "train"
    assert runs[0].data.tags["git.dirty"] == "true"
    # The failed run is closed: the next stage starts a fresh run.
    with stage_run("train", experiment="test-fail"):
        pass
    assert sorted(r.info.status for r in runs_of(client, "test-fail")) == ["FAILED", "FINISHED"]


def test_env_uri_is_used_by_stage_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, temp_repo: Path
) -> None:
    # Reuse the module's database through the env var, from a cwd without dvc.yaml.
    uri = f"sqlite:///{temp_repo / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.chdir(tmp_path)
    with stage_run("evaluate", experiment="test-env") as run:
        pass
    assert MlflowClient(uri).get_run(run.info.run_id).data.tags["dvc.stage"] == "evaluate"
