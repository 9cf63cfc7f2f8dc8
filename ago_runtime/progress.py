"""Progress bars (rich, which typer already brings). Quiet when AGO_NO_PROGRESS=1 or not a TTY in CI."""

from __future__ import annotations

import os
from typing import Iterable, Iterator, TypeVar

T = TypeVar("T")


def track(items: Iterable[T], description: str = "working", total: int | None = None) -> Iterator[T]:
    """Iterate `items` with a progress bar on stderr."""
    if os.environ.get("AGO_NO_PROGRESS") == "1":
        yield from items
        return
    from rich.console import Console
    from rich.progress import track as rich_track

    yield from rich_track(items, description=description, total=total, console=Console(stderr=True),
                          transient=False)


def track_rate(items: Iterable[T], description: str, total: int | None, unit: str) -> Iterator[T]:
    """`track` with a count and the mean rate so far ("0.42 images/s") beside the bar."""
    if os.environ.get("AGO_NO_PROGRESS") == "1":
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
