"""Progress bars (rich, which typer already brings), drawn only on a terminal: when stderr is not a TTY (a log
file, a pipe, CI) or AGO_NO_PROGRESS=1, nothing is drawn, so a failing verb's redirected stderr holds its one
`error:` line and nothing else. `quiet_library_bars` asks the libraries ago loads (transformers, Hugging Face
hub, tqdm) for the same."""

from __future__ import annotations

import os
import sys
from typing import Iterable, Iterator, TypeVar

T = TypeVar("T")


def progress_enabled() -> bool:
    """Whether bars are drawn: stderr is a terminal and AGO_NO_PROGRESS is not 1 (the one rule for every bar)."""
    if os.environ.get("AGO_NO_PROGRESS") == "1":
        return False
    isatty = getattr(sys.stderr, "isatty", None)
    try:
        return bool(isatty and isatty())
    except (ValueError, OSError):   # a closed or odd stream
        return False


def quiet_library_bars() -> None:
    """When bars are off, the libraries' own bars and advisory lines are off too (set before they load;
    a value the user set is kept)."""
    if progress_enabled():
        return
    for key, value in (("HF_HUB_DISABLE_PROGRESS_BARS", "1"), ("TQDM_DISABLE", "1"),
                       ("TRANSFORMERS_VERBOSITY", "error"), ("TRANSFORMERS_NO_ADVISORY_WARNINGS", "1")):
        os.environ.setdefault(key, value)


def track(items: Iterable[T], description: str = "working", total: int | None = None) -> Iterator[T]:
    """Iterate `items` with a progress bar on stderr (only when progress_enabled())."""
    if not progress_enabled():
        yield from items
        return
    from rich.console import Console
    from rich.progress import track as rich_track

    yield from rich_track(items, description=description, total=total, console=Console(stderr=True),
                          transient=False)


def track_rate(items: Iterable[T], description: str, total: int | None, unit: str) -> Iterator[T]:
    """`track` with a count and the mean rate so far ("0.42 images/s") beside the bar (only when progress_enabled())."""
    if not progress_enabled():
        yield from items
        return
    from rich.console import Console
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, ProgressColumn, TextColumn,
                               TimeElapsedColumn, TimeRemainingColumn)
    from rich.text import Text

    class RateColumn(ProgressColumn):
        def render(self, task) -> Text:
            elapsed = task.finished_time if task.finished else task.elapsed
            speed = task.completed / elapsed if elapsed and task.completed else None
            return Text(f"{speed:.2f} {unit}/s" if speed else f"- {unit}/s", style="progress.data.speed")

    with Progress(TextColumn("[progress.description]{task.description}"), BarColumn(), MofNCompleteColumn(),
                  RateColumn(), TimeElapsedColumn(), TimeRemainingColumn(), console=Console(stderr=True),
                  transient=False) as progress:
        yield from progress.track(items, total=total, description=description)
