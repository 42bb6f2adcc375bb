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
