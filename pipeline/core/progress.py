"""The one progress-bar factory of ftcal: transient rich bars on stderr, or nothing when disabled.

Stages show progress on long work when stderr is a terminal (``enabled=None``), never in logs or DVC's
captured output unless asked. ``bytes_=True`` shows sizes and time remaining (decoding files), otherwise
``done/total`` and time elapsed (logs, groups, trials).
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager
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


class ProgressLog:
    """Nested transient bars (e.g. trials, epochs) plus one printed line per finished step; or nothing.

    Use ``with log.running(): ...``; outside it (or disabled) `task` returns None and `update`/`remove`
    do nothing, so callers never test whether progress is shown.
    """

    def __init__(self, enabled: bool | None = None) -> None:
        self.enabled = show_progress(enabled)
        self._progress: Any = None

    @contextmanager
    def running(self) -> Iterator[ProgressLog]:
        if not self.enabled:
            yield self
            return
        with progress_bar(True) as progress:
            self._progress = progress
            try:
                yield self
            finally:
                self._progress = None

    def task(self, description: str, total: int) -> Any:
        return None if self._progress is None else self._progress.add_task(description, total=total)

    def update(self, task: Any, **kwargs: Any) -> None:
        if task is not None:
            self._progress.update(task, **kwargs)

    def remove(self, task: Any) -> None:
        if task is not None:
            self._progress.remove_task(task)

    def line(self, text: str) -> None:
        """Print one line above the bars (on stderr when no bar is shown)."""
        if self._progress is not None:
            self._progress.console.print(text, highlight=False)
        elif self.enabled:
            print(text, file=sys.stderr)
