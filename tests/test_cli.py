"""The `ftcal` command: one-line errors with exit 2, --version, and the robot table."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline import __version__
from pipeline.cli import main

ROOT = Path(__file__).resolve().parent.parent


def _env() -> dict[str, str]:
    """The environment of a subprocess that imports this checkout's `pipeline`."""
    return {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    }


def test_bad_params_path_is_a_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    missing = tmp_path / "missing_params.yaml"
    assert main(["robot", "--params", str(missing)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith("ftcal: error: ")
    assert str(missing) in err


def test_invalid_params_value_names_file_and_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "params.yaml"
    bad.write_text("seed: 42\nrobot:\n  urdf: iCubGenova09\n  gravity: -1\n  foot_pairs: {}\n")
    assert main(["robot", "--params", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err == f"ftcal: error: {bad}: robot.gravity must be a positive number, got -1\n"


def test_python_m_entry_point(tmp_path: Path) -> None:
    bad = tmp_path / "broken.yaml"
    bad.write_text("seed: [42\n")
    env = _env()
    result = subprocess.run(
        [sys.executable, "-m", "pipeline.cli", "robot", "--params", str(bad)],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=60,
    )
    assert result.returncode == 2
    assert result.stdout == ""
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr
    # The file is shown relative to the working directory, as the user would type it.
    assert lines[0].startswith("ftcal: error: broken.yaml: invalid YAML at line 2")


def test_the_console_script_leaves_without_teardown_and_loses_no_output(tmp_path: Path) -> None:
    """`ftcal` (`pipeline.cli:entry`) ends with os._exit: what a command printed into a pipe (block-buffered)
    still arrives, and its status is the exit status."""
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert 'ftcal = "pipeline.cli:entry"' in pyproject
    env = _env()
    env.pop("PYTHONUNBUFFERED", None)  # the pipe block-buffered, as under DVC
    run = [sys.executable, "-c", "import sys; from pipeline.cli import entry; sys.argv[0] = 'ftcal'; entry()"]
    result = subprocess.run([*run, "--version"], capture_output=True, text=True, env=env, timeout=60)
    assert (result.returncode, result.stdout) == (0, f"ftcal {__version__}\n"), result.stderr
    missing = tmp_path / "missing_params.yaml"
    result = subprocess.run(
        [*run, "robot", "--params", str(missing)], capture_output=True, text=True, env=env, timeout=60
    )
    assert result.returncode == 2 and result.stderr.startswith("ftcal: error: ")
    assert str(missing) in result.stderr


def test_the_steps_of_a_stage_start_with_the_preloaded_libraries_frozen() -> None:
    """`_preload` freezes what it imported (`gc.freeze`), so that the forked steps' collections neither scan
    nor copy it; and it imports the params validators every step runs first."""
    code = (
        "import gc, sys; from pipeline.cli import _preload; n = gc.get_freeze_count(); _preload(['numpy']); "
        "assert n == 0 and gc.get_freeze_count() > 10000, gc.get_freeze_count(); "
        "assert 'pipeline.calib.params' in sys.modules and 'pipeline.deploy.params' in sys.modules"
    )
    env = _env()
    result = subprocess.run(
        [sys.executable, "-P", "-c", code], capture_output=True, text=True, env=env, timeout=120
    )
    assert result.returncode == 0, result.stderr


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"ftcal {__version__}"


def test_no_command_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 2
    assert "usage: ftcal" in capsys.readouterr().err


def test_robot_prints_ft_sensors(capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("pipeline.physics.robot")
    assert main(["robot"]) == 0
    out = capsys.readouterr().out
    for sensor in ("l_leg_ft", "r_leg_ft", "l_arm_ft", "r_arm_ft", "l_foot_front_ft", "r_foot_rear_ft"):
        assert sensor in out
    assert "child_to_parent" in out and "parent_to_child" in out
    assert "l_foot (front)" in out


def test_robot_bad_urdf_is_a_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("pipeline.physics.robot")
    missing = tmp_path / "nope.urdf"
    assert main(["robot", "--urdf", str(missing)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("ftcal: error: ")


def test_commands_joined_by_plus_run_in_order_and_the_first_failure_stops_them(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    # a DVC stage of several steps: `ftcal A ... + B ...`, each step in a process forked from this one
    pytest.importorskip("pipeline.physics.robot")
    assert main(["robot", "+", "robot", "--urdf", "iCubGenova09"]) == 0
    assert capfd.readouterr().out.count("l_foot (front)") == 2
    missing = tmp_path / "nope.urdf"
    assert main(["robot", "--urdf", str(missing), "+", "robot"]) == 2
    captured = capfd.readouterr()
    assert "l_foot (front)" not in captured.out and str(missing) in captured.err
    for argv in (["robot", "+"], ["+", "robot"], ["robot", "+", "+", "robot"]):
        assert main(argv) == 2
        assert capfd.readouterr().err.startswith("ftcal: error: an empty command")


def test_a_stage_of_several_steps_imports_beforehand_what_its_steps_import() -> None:
    import shlex

    import yaml

    from pipeline.cli import COMMANDS, LIBRARIES, STEP_LIBRARIES, _command, shared_libraries, split_commands

    stages = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]

    def chain(stage: str) -> list[str]:
        entry = stages[stage]
        cmd = (entry.get("do") or entry)["cmd"]
        return shared_libraries([_command(p) for p in split_commands(shlex.split(cmd)[1:])])

    days, evaluate, report = chain("deploy_days"), chain("evaluate"), chain("report")
    # the deployment days simulate and label: no network, no onnxruntime (seconds of import saved)
    assert {"pinocchio", "scipy.signal", "mlflow"} <= set(days)
    assert not {"torch", "onnxruntime", "matplotlib.pyplot"} & set(days)
    assert {"torch", "onnx", "onnxruntime", "pinocchio", "scipy.signal", "matplotlib.pyplot"} <= set(evaluate)
    assert {"torch", "onnx", "onnxruntime", "matplotlib.pyplot"} <= set(report)
    assert not {"pinocchio", "scipy.signal"} & set(report)
    assert set(STEP_LIBRARIES) <= set(COMMANDS)
    assert all(set(libs) <= set(LIBRARIES) for libs in STEP_LIBRARIES.values())
    assert shared_libraries(["no-such-command"]) == list(LIBRARIES)  # unknown: everything, in order
