"""The `ftcal` command: one subcommand per pipeline stage (added with each stage), plus inspection tools.

Errors the user can fix (`FtcalError`) print one line, ``ftcal: error: <message>``, on stderr and
exit with status 2; so does any exception inside a step's forked jobs (`pipeline.core.parallel`: the line
names the job's file or name and the file holding the traceback). Ctrl-C exits with 130, SIGTERM with 143;
either way, and after any error, every worker process a step forked is ended and reaped before the command
returns (`pipeline.core.parallel`). Anything else raised by a step itself is a bug and shows its traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import importlib
import logging
import os
import signal
import sys
import traceback
from collections.abc import Sequence
from typing import NoReturn

from pipeline import __version__
from pipeline.core.cliargs import add_params_option
from pipeline.core.errors import FtcalError

EXIT_OK = 0
EXIT_USAGE = 2  # as argparse: bad arguments or bad input the user can fix
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as shells report Ctrl-C
EXIT_TERMINATED = 143  # 128 + SIGTERM
THEN = "+"  # between two commands run one after the other, in one stage (`main`)

# Commands, in pipeline order: name -> (module, one-line help). A command's module defines
# ``add_cli(subparsers)``, which adds its subcommand (a step of a DVC stage, named as the step) with
# ``set_defaults(func=...)``. Only the module of the command being run is imported (stages import torch,
# pinocchio, mlflow): `ftcal --help` lists the commands from this table alone.
COMMANDS: dict[str, tuple[str, str]] = {
    "params": ("pipeline.tools.params", "the effective configuration and where each value came from"),
    "simulate": ("pipeline.stages.simulate", "simulate experiment logs (MCAP) of the robot with known truth"),
    "ingest": ("pipeline.stages.ingest", "decode MCAP and .mat logs into aligned Parquet tables"),
    "smooth": ("pipeline.stages.smooth", "Savitzky-Golay joint positions, velocities, accelerations"),
    "label": ("pipeline.stages.label", "contacts, expected wrenches and exact-label switches per sensor"),
    "identify": ("pipeline.stages.identify", "identify the robot's inertial parameters with the FT sensors"),
    "train": ("pipeline.stages.train", "baselines and neural networks of one sensor group"),
    "evaluate": ("pipeline.stages.evaluate", "error tables, figures and noise check of one group's models"),
    "report": ("pipeline.stages.report", "assemble the report page of every group's evaluation"),
    "export": ("pipeline.stages.export", "the recommended models as ONNX graphs with a manifest"),
    "calibrate": ("pipeline.tools.calibrate", "copy a log adding the exported calibration's wrenches"),
    "rezero": (
        "pipeline.tools.rezero",
        "re-zero the exported calibration from a still stretch (no retraining)",
    ),
    "deploy-prepare": ("pipeline.stages.deploy_prepare", "ingest, smooth and label a deployment day's logs"),
    "deploy-test": ("pipeline.stages.deploy_test", "deployment tests A, B, C of one sensor group"),
    "deploy-report": (
        "pipeline.stages.deploy_report",
        "the deployment page and verdict of every group's tests",
    ),
    "convert-mat": ("pipeline.tools.convert_mat", "convert a robot-logger .mat file to a contract MCAP"),
    "convert-dumper": ("pipeline.tools.convert_dumper", "convert a YARP dataDumper run to a contract MCAP"),
    "worker": ("pipeline.tools.worker", "run Optuna trials of a group's search beside the stage (database)"),
    "db": ("pipeline.tools.db", "start or stop a local PostgreSQL server (shared studies, MLflow server)"),
}


def _cmd_robot(args: argparse.Namespace) -> int:
    """Print the robot's FT sensors (and which foot each belongs to) as a table."""
    from rich.console import Console
    from rich.table import Table

    from pipeline.core.config import load_params, repo_root, resolve_urdf
    from pipeline.physics.robot import load_robot  # deferred: imports pinocchio

    params = load_params(args.params)
    # --urdf is typed by the user: relative to the working directory; params' urdf: to the repo root.
    urdf = args.urdf if args.urdf is not None else resolve_urdf(params.robot.urdf, repo_root())
    robot = load_robot(urdf)

    from pipeline.physics.feet import derive_feet

    # the feet as params name them (robot.foot_pairs), else as the URDF has them (one or two sensors each)
    feet = params.robot.foot_pairs
    named = (
        [(p.name, p.sensors) for p in feet]
        if feet is not None
        else [(f.name, f.sensors) for f in derive_feet(robot)]
    )
    pair_of = {}
    for name, sensors in named:
        for sensor, part in zip(
            sensors, (" (front)", " (rear)") if len(sensors) == 2 else ("",), strict=True
        ):
            pair_of[sensor] = name + part

    table = Table(title=f"{robot.name}: {len(robot.sensors)} FT sensors", title_justify="left")
    for header in ("sensor", "joint", "parent link", "child link", "frame", "direction", "foot"):
        table.add_column(header, no_wrap=True)
    for sensor in robot.sensors.values():
        table.add_row(
            sensor.name,
            sensor.joint,
            sensor.parent_link,
            sensor.child_link,
            sensor.frame,
            sensor.direction,
            pair_of.get(sensor.name, ""),
        )
    # Wide enough not to fold link names when the output is piped (rich would assume 80 columns).
    console = Console(width=None if sys.stdout.isatty() else 200)
    console.print(table)
    console.print(f"URDF: {robot.urdf_path}  ({len(robot.joint_names)} movable joints)")

    missing = sorted(name for name in pair_of if name not in robot.sensors)
    if missing:
        Console(stderr=True).print(
            f"[yellow]warning:[/] robot.foot_pairs names sensors that {robot.name} does not have: "
            + ", ".join(missing)
        )
    return EXIT_OK


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The argument parser of `ftcal`: every command listed, the arguments of `command` only (None: all)."""
    parser = argparse.ArgumentParser(
        prog="ftcal",
        description="In-situ calibration of 6-axis force/torque sensors on humanoid robots.",
        epilog="The full pipeline runs with `dvc repro`; these commands run or inspect single steps.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    robot = sub.add_parser("robot", help="print the robot's FT sensors", description=_cmd_robot.__doc__)
    add_params_option(robot)
    robot.add_argument(
        "--urdf",
        default=None,
        metavar="PATH_OR_NAME",
        help="URDF file or icub-models robot name (default: robot.urdf from params)",
    )
    robot.set_defaults(func=_cmd_robot)

    for name, (module_name, help_text) in COMMANDS.items():
        if command is None or name == command:
            importlib.import_module(module_name).add_cli(sub)
        else:
            sub.add_parser(name, help=help_text)  # listed; its arguments are built when it runs
    return parser


def _command(argv: Sequence[str]) -> str | None:
    """The command named on the command line (its first word that is a command), if any."""
    return next((a for a in argv if a in COMMANDS), None)


def split_commands(argv: list[str]) -> list[list[str]]:
    """The commands of a command line, cut at every standalone `THEN`."""
    parts: list[list[str]] = [[]]
    for arg in argv:
        if arg == THEN:
            parts.append([])
        else:
            parts[-1].append(arg)
    return parts


def _run(argv: list[str]) -> int:
    """Run one command; return its exit status."""
    command = _command(argv)
    parser = build_parser(command if command is not None else "")
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, usage errors: argparse has printed what to say
        if exc.code is None:
            return EXIT_OK
        return exc.code if isinstance(exc.code, int) else EXIT_USAGE
    from pipeline.core.parallel import Terminated, end_workers

    try:
        return args.func(args)
    except FtcalError as exc:
        message = " ".join(str(exc).split("\n")).strip() or type(exc).__name__
        print(f"ftcal: error: {message}", file=sys.stderr)
        return EXIT_USAGE
    except Terminated:
        print("ftcal: terminated", file=sys.stderr)
        return EXIT_TERMINATED
    except KeyboardInterrupt:
        print("ftcal: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        end_workers()  # those of results an error left unread


# The heavy libraries the steps import, in import order. When a stage runs several steps, those its steps
# import (`STEP_LIBRARIES`) are imported once before the first: each step runs in a process forked from this
# one (`_run_forked`), so it starts with them imported but with no thread pool or open file a step before it
# left behind (onnxruntime's and OpenMP's pools do not survive a fork). Every step imports numpy, pandas,
# pyarrow and mlflow (whose runs import IPython, when installed, to look for Databricks).
LIBRARIES = (
    "numpy",
    "pandas",
    "pyarrow.parquet",
    "scipy.signal",
    "matplotlib.pyplot",
    "torch",
    "onnx",
    "onnxruntime",
    "pinocchio",
    "mlflow",
    "mlflow.store.tracking.sqlalchemy_store",
    "IPython",
)
_EVERY_STEP = frozenset(
    {"numpy", "pandas", "pyarrow.parquet", "mlflow", "mlflow.store.tracking.sqlalchemy_store", "IPython"}
)
# what each command imports beyond those (measured by running it: `sys.modules` after the step); a library
# missing here is imported by the step itself, a little later, so this only saves time
STEP_LIBRARIES: dict[str, frozenset[str]] = {
    name: _EVERY_STEP | frozenset(extra)
    for name, extra in {
        "simulate": ("scipy.signal", "pinocchio"),  # its plots import matplotlib (not on deployment days)
        "ingest": (),
        "smooth": ("scipy.signal",),
        "label": ("pinocchio",),
        "identify": ("pinocchio", "matplotlib.pyplot"),
        "train": ("torch",),
        "evaluate": ("scipy.signal", "matplotlib.pyplot"),
        "report": ("matplotlib.pyplot",),
        "export": ("torch", "onnx", "onnxruntime"),
        "calibrate": ("onnx", "onnxruntime"),
        "deploy-prepare": ("scipy.signal", "pinocchio"),
        "deploy-test": ("matplotlib.pyplot", "torch", "onnxruntime", "pinocchio"),
        "deploy-report": (),
    }.items()
}


def shared_libraries(commands: Sequence[str | None]) -> list[str]:
    """The libraries of `LIBRARIES` the steps `commands` import (`STEP_LIBRARIES`; unknown command: all)."""
    wanted: set[str] = set()
    for command in commands:
        wanted |= STEP_LIBRARIES.get(command, frozenset(LIBRARIES)) if command else set(LIBRARIES)
    return [name for name in LIBRARIES if name in wanted]


def _preload(names: Sequence[str]) -> None:
    """Import `names` (those installed) and the params validators before the steps are forked."""
    if "matplotlib.pyplot" in names:  # matplotlib itself takes half a second: only for steps that draw
        import matplotlib

        matplotlib.use("Agg")  # figures are written to files: no display, as in every step
    for name in names:
        with contextlib.suppress(ImportError):  # a step that needs it says so itself
            importlib.import_module(name)
    from pipeline.core.config import SECTIONS

    for ref in SECTIONS.values():  # every step first validates all of params.yaml (`load_params`)
        importlib.import_module(ref.split(":")[0])
    # the objects of these libraries live as long as the process: out of the collector's reach, so that a
    # step's collections neither scan them nor copy their pages from this process (seconds a step)
    gc.freeze()


def _run_forked(argv: list[str]) -> int:
    """Run one command in a forked child process; return its exit status (130 after Ctrl-C, 143 after a
    SIGTERM, which this process passes on to the child)."""
    from pipeline.core.parallel import stop_on_sigterm

    sys.stdout.flush()
    sys.stderr.flush()
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})  # until each side has its handler
    pid = os.fork()
    if pid == 0:  # the child: the command, then out without unwinding into the parent's loop
        stop_on_sigterm()
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
        status = EXIT_USAGE
        try:
            status = _run(argv)
        except BaseException:  # a bug: its traceback, as a process of its own would print it
            traceback.print_exc()
            status = 1
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(status)
    previous = signal.signal(signal.SIGTERM, lambda *_: os.kill(pid, signal.SIGTERM))
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
    try:
        while True:
            try:
                _, wait = os.waitpid(pid, 0)
                break
            except KeyboardInterrupt:  # Ctrl-C reaches the child too: wait for it to stop
                continue
    finally:
        signal.signal(signal.SIGTERM, previous)
    code = os.waitstatus_to_exitcode(wait)
    return 128 - code if code < 0 else code  # killed by signal s: 128 + s, as shells report it


def main(argv: Sequence[str] | None = None) -> int:
    """Run `ftcal` with `argv` (default: the command line); return the exit status.

    Commands joined by a standalone ``+`` run one after the other, each in a process forked from this one
    after the libraries they import are imported (`shared_libraries`): a DVC stage of several steps starts
    Python and those libraries once. The first command that fails stops the others.
    """
    parts = split_commands(list(sys.argv[1:] if argv is None else argv))
    if len(parts) == 1:
        return _run(parts[0])
    if not all(parts):
        print(f"ftcal: error: an empty command before or after {THEN!r}", file=sys.stderr)
        return EXIT_USAGE
    forking = hasattr(os, "fork")
    if forking:
        _preload(shared_libraries([_command(part) for part in parts]))
    for part in parts:
        status = _run_forked(part) if forking else _run(part)
        if status != EXIT_OK:
            return status
    return EXIT_OK


def entry() -> NoReturn:
    """The `ftcal` console script: `main`, then out with its status, without Python's teardown.

    Every file a command writes is closed (and moved into place) and every MLflow run ended before `main`
    returns; tearing torch, MLflow and the other libraries down would then only take time, about 1.5 s a
    process, which every DVC stage pays (its steps' forked processes leave the same way, `_run_forked`).
    A bug's exception still unwinds and prints its traceback. SIGTERM unwinds as Ctrl-C does (temporary
    files removed, forked workers ended).
    """
    from pipeline.core.parallel import stop_on_sigterm

    stop_on_sigterm()
    status = main()
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


if __name__ == "__main__":
    entry()
