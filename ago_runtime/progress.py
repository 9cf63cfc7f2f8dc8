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
