"""A lab's params.yaml over pipeline/defaults.yaml: what it sets replaces the default key by key, its
collections whole; unknown keys and bad values are still refused with their dotted path; ``ftcal params``
shows the effective values and where each came from, and writes the file dvc.yaml's stages track."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from pipeline.cli import main
from pipeline.core.config import load_params
from pipeline.core.defaults import DEFAULTS_FILE, RESOLVED_FILE, read_defaults
from pipeline.core.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]
REQUIRED = {"ingest": {"source": "data/sim"}, "deploy": {"real_logs": "data/deploy/raw"}}
GROUPS = {"train": {"groups": {"arm": {"sensor": "l_arm_ft"}}}}


def _lab(tmp_path: Path, data: dict) -> Path:
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _merged(*parts: dict) -> dict:
    out: dict = {}
    for part in parts:
        for key, value in part.items():
            out[key] = {**out.get(key, {}), **value} if isinstance(value, dict) else value
    return out


def test_the_shipped_params_are_a_lab_s_few_lines_and_the_default_pipeline_is_the_defaults() -> None:
    lines = (REPO / "params.yaml").read_text().splitlines()
    assert len(lines) <= 60, len(lines)
    effective = {k: v for k, v in load_params(REPO / "params.yaml").raw.items() if k != "__file__"}
    assert effective == read_defaults()  # the values it sets are the defaults' own: nothing else changes
    assert DEFAULTS_FILE.is_file() and DEFAULTS_FILE.parent.name == "pipeline"


def test_a_key_the_lab_sets_replaces_its_default_and_a_collection_is_replaced_whole(tmp_path: Path) -> None:
    path = _lab(tmp_path, _merged(REQUIRED, GROUPS, {"train": {"defaults": {"lr": 0.003}}}))
    train = load_params(path).raw["train"]
    defaults = read_defaults()["train"]
    assert train["defaults"]["lr"] == 0.003
    assert {k: v for k, v in train["defaults"].items() if k != "lr"} == {
        k: v for k, v in defaults["defaults"].items() if k != "lr"
    }
    assert train["groups"] == {"arm": {"sensor": "l_arm_ft"}}  # not the defaults' three groups plus this one
    assert train["folds"] == defaults["folds"]


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"train": {"defaults": {"lrr": 0.1}}}, "train.defaults.lrr"),
        ({"smooth": 5}, "smooth must be a mapping"),
        ({"smooth": {"window": 4}}, "smooth.window"),
        ({"colour": "red"}, "unknown key colour"),
    ],
)
def test_unknown_keys_and_bad_values_are_refused_with_their_dotted_path(
    tmp_path: Path, data: dict, message: str
) -> None:
    path = _lab(tmp_path, _merged(REQUIRED, data))
    with pytest.raises(ConfigError, match=message.replace(".", r"\.")) as info:
        load_params(path)
    assert str(info.value).startswith(str(path)) or "params.yaml" in str(info.value)


def test_ftcal_params_shows_each_value_and_where_it_came_from(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _lab(tmp_path, _merged(REQUIRED, GROUPS, {"train": {"defaults": {"lr": 0.003}}}))
    assert main(["params", "train.defaults", "--params", str(path)]) == 0
    rows = {line.split()[0]: line.split() for line in capsys.readouterr().out.splitlines()}
    assert rows["train.defaults.lr"][1:] == ["0.003", "params.yaml"]
    default_epochs = read_defaults()["train"]["defaults"]["epochs"]
    assert rows["train.defaults.epochs"][1:] == [str(default_epochs), "default"]
    assert all(key.startswith("train.defaults.") for key in rows)
    assert main(["params", "--set-only", "--params", str(path)]) == 0
    shown = [line.split()[0] for line in capsys.readouterr().out.splitlines()]
    assert shown == ["ingest.source", "train.defaults.lr", "train.groups", "deploy.real_logs"]


def test_ftcal_params_writes_what_the_stages_track_and_needs_what_dvc_yaml_templates(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _lab(tmp_path, _merged(REQUIRED, GROUPS))
    out = tmp_path / RESOLVED_FILE
    assert main(["params", "--write", str(out), "--params", str(path)]) == 0
    written = yaml.safe_load(out.read_text())
    assert written == {k: v for k, v in load_params(path).raw.items() if k != "__file__"}
    partial = _lab(tmp_path, GROUPS)  # no ingest.source: dvc.yaml's `ftcal ingest ${ingest.source}` needs it
    assert main(["params", "--write", str(out), "--params", str(partial)]) == 2
    assert "ingest.source must be set in this file" in capsys.readouterr().err


def test_the_committed_resolved_params_are_those_of_the_shipped_params(tmp_path: Path) -> None:
    """What dvc.lock's stages were run with: `dvc repro` rewrites it, a commit must carry it."""
    out = tmp_path / RESOLVED_FILE
    assert main(["params", "--write", str(out), "--params", str(REPO / "params.yaml")]) == 0
    assert yaml.safe_load((REPO / RESOLVED_FILE).read_text()) == yaml.safe_load(out.read_text())
