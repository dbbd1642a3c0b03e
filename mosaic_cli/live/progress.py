"""Progress of a stream, whose length nobody knows: frames so far, frames per second, elapsed."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

from mosaic_cli.progress import RateColumn, advancer, console, progress_task


@contextlib.contextmanager
def stream_progress(description: str, disable: bool = False) -> Iterator:
    """Yields ``advance(n=1, status=None)`` like :func:`mosaic_cli.progress.progress_task`; when
    stderr is not a terminal, it is that task (plain lines: frames so far, rate, elapsed)."""
    if disable or not console.is_terminal:
        with progress_task(description, None, disable=disable) as advance:
            yield advance
        return
    progress = Progress(
        SpinnerColumn(),
        TextColumn("[bold]{task.description}"),
        TextColumn("{task.completed:>7.0f} frames"),
        RateColumn("fr/s"),
        TimeElapsedColumn(),
        TextColumn("{task.fields[status]}"),
        console=console,
        transient=False,
        disable=disable,
    )
    with progress:
        yield advancer(progress, progress.add_task(description, total=None, status=""))
