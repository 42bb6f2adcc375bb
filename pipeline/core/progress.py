"""The one progress-bar factory of ftcal: transient rich bars on stderr, or nothing when disabled.

Stages show progress on long work when stderr is a terminal (``enabled=None``), never in logs or DVC's
captured output unless asked. ``bytes_=True`` shows sizes and time remaining (decoding files), otherwise
``done/total`` and time elapsed (logs, groups, trials).
"""

from __future__ import annotations

import sys
from typing import Any


def show_progress(enabled: bool | None) -> bool:
    """Whether to show bars: `enabled` if given, else whether stderr is a terminal."""
    return sys.stderr.isatty() if enabled is None else bool(enabled)


def progress_bar(enabled: bool | None = None, *, bytes_: bool = False) -> Any:
    """A ``rich.progress.Progress`` context (disabled, it draws nothing and costs nothing)."""
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        DownloadColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    counts = (
        (DownloadColumn(), TimeRemainingColumn()) if bytes_ else (MofNCompleteColumn(), TimeElapsedColumn())
    )
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        *counts,
        console=Console(stderr=True),
        transient=True,
        disable=not show_progress(enabled),
    )
