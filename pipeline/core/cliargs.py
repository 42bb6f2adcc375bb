"""Command-line options every `ftcal` command shares (light: imported when the parser is built)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_params_option(parser: argparse.ArgumentParser, what: str = "") -> None:
    """``--params PATH``: the params file (default: params.yaml at the repo root). `what`: what it is for."""
    purpose = f"{what}; " if what else ""
    parser.add_argument(
        "--params",
        type=Path,
        default=None,
        metavar="PATH",
        help=f"params file ({purpose}default: params.yaml at the repo root)",
    )


DEFAULT_MODELS = "exported"  # the export stage's output directory, at the repo root (dvc.yaml)


def add_models_option(parser: argparse.ArgumentParser) -> None:
    """``--models DIR``: an export directory (default: `DEFAULT_MODELS` at the repo root; `models_dir`)."""
    parser.add_argument(
        "--models",
        type=Path,
        default=None,
        metavar="DIR",
        help=f"export directory with manifest.json (default: {DEFAULT_MODELS}/ at the repo root)",
    )


def models_dir(models: Path | None) -> Path:
    """The export directory `--models` names, or the repo root's `DEFAULT_MODELS`."""
    from pipeline.core.config import repo_root

    return models if models is not None else repo_root() / DEFAULT_MODELS


RUNTIMES = ("onnxruntime", "c")  # what runs an export: its ONNX graphs, or its generated C calibrators


def add_runtime_option(parser: argparse.ArgumentParser) -> None:
    """``--runtime {onnxruntime,c}``: what runs the export (`pipeline.export.cbuild.using`)."""
    parser.add_argument(
        "--runtime",
        choices=RUNTIMES,
        default=RUNTIMES[0],
        help="run the export's ONNX graphs with onnxruntime (default), or its generated C calibrators "
        "compiled with cc",
    )
