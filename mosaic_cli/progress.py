"""Progress of long work on stderr: rich bars (frames, frames per second, ETA) on a terminal;
plain lines where stderr is a file or a pipe, where redrawn bars would pile up and wrap.

In line mode each stage writes one line when it ends (count, time, rate, last status), and
a stage that runs longer than :data:`LINE_EVERY_SECONDS` also writes a line that often, so
that a log of an hour-long run still shows it moving.

A stream, whose length nobody knows (a live input), has :func:`stream_progress`: frames so far,
frames per second, elapsed."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    ProgressColumn,
    SpinnerColumn,
    Task,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.text import Text

# soft_wrap: a summary line written to a file stays one line (not broken at 80 columns).
console = Console(stderr=True, soft_wrap=True)
LINE_EVERY_SECONDS = 60.0


def note(message: str) -> None:
    """One line on stderr, beside the progress bars."""
    console.print(f"mosaic: {message}", markup=False, highlight=False, soft_wrap=True)


class RateColumn(ProgressColumn):
    """Items per second, with a unit ("fr/s", "it/s")."""

    def __init__(self, unit: str = "fr/s"):
        super().__init__()
        self.unit = unit

    def render(self, task: Task) -> Text:
        speed = task.finished_speed or task.speed
        return Text("-" if speed is None else f"{speed:6.1f} {self.unit}", style="progress.data.speed")


def advancer(progress: Progress, task) -> Callable[..., None]:
    """``advance(n=1, status=None)`` for one task of a rich ``progress``."""

    def advance(n: int = 1, status: str | None = None) -> None:
        if status is None:
            progress.advance(task, n)
        else:
            progress.update(task, advance=n, status=status)

    return advance


def make_progress(unit: str = "fr/s", disable: bool = False) -> Progress:
    return Progress(
        SpinnerColumn(),
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        RateColumn(unit),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        TextColumn("{task.fields[status]}"),
        console=console,
        transient=False,
        disable=disable,
    )


class LineProgress:
    """One stage's progress as plain text lines (see the module docstring)."""

    def __init__(self, description: str, total: int | None, unit: str, every: float = LINE_EVERY_SECONDS,
                 clock=time.monotonic):
        self.description, self.total, self.unit, self.every, self.clock = description, total, unit, every, clock
        self.done = 0
        self.status = ""
        self.start = self.last_line = clock()

    def advance(self, n: int = 1, status: str | None = None) -> None:
        self.done += n
        if status is not None:
            self.status = status
        if self.clock() - self.last_line >= self.every:
            self._write(self.line(final=False))

    def line(self, final: bool) -> str:
        elapsed = max(self.clock() - self.start, 1e-9)
        count = f"{self.done}/{self.total}" if self.total is not None else f"{self.done}"
        rate = self.done / elapsed
        text = f"{self.description}: {count} in {_clock(elapsed)} ({rate:.1f} {self.unit})"
        if not final and self.total and rate > 0:
            text += f", ETA {_clock(max(self.total - self.done, 0) / rate)}"
        return text + (f"; {self.status}" if self.status else "")

    def _write(self, text: str) -> None:
        self.last_line = self.clock()
        console.file.write(text + "\n")
        console.file.flush()


def _clock(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


@contextlib.contextmanager
def progress_task(description: str, total: int | None, unit: str = "fr/s", disable: bool = False) -> Iterator:
    """A context manager yielding ``advance(n=1, status=None)`` for one progress task: a rich bar
    on a terminal, plain lines otherwise (nothing when ``disable``).  A stage cut short by an
    error writes no line: the error's own line is the one to read."""
    if not disable and not console.is_terminal:
        lines = LineProgress(description, total, unit)
        yield lines.advance
        lines._write(lines.line(final=True))
        return
    if _shared and not disable:  # a stage running beside others: one more bar in their display
        yield advancer(_shared[-1], _shared[-1].add_task(description, total=total, status=""))
        return
    with make_progress(unit, disable) as progress:
        yield advancer(progress, progress.add_task(description, total=total, status=""))


_shared: list[Progress] = []


@contextlib.contextmanager
def progress_group(disable: bool = False) -> Iterator[None]:
    """One display for the stages that run at the same time inside it, each stage's
    :func:`progress_task` a bar of its own (rich allows one live display at a time; its
    progress is safe to advance from several threads)."""
    if disable or not console.is_terminal:
        yield
        return
    with make_progress() as progress:
        _shared.append(progress)
        try:
            yield
        finally:
            _shared.remove(progress)


@contextlib.contextmanager
def stream_progress(description: str, disable: bool = False) -> Iterator:
    """Yields ``advance(n=1, status=None)`` like :func:`progress_task`, for a stream of unknown
    length; when stderr is not a terminal, it is that task (plain lines: frames so far, rate, elapsed)."""
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
