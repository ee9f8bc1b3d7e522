"""Progress bars (rich) with items per second; a silent stand-in when disabled."""

from __future__ import annotations

from contextlib import contextmanager
from typing import Any, Iterator


class ProgressBar:
    """Advance with :meth:`advance`; shows count, rate (items/s), elapsed and remaining."""

    def __init__(self, progress: Any = None, task: Any = None):
        self._progress, self._task = progress, task

    def advance(self, n: int = 1) -> None:
        if self._progress is None:
            return
        self._progress.advance(self._task, n)
        speed = self._progress.tasks[self._task].speed
        if speed:
            self._progress.update(self._task, rate=f"{speed:6.2f} it/s")


@contextmanager
def progress_bar(description: str, total: int, enabled: bool = True) -> Iterator[ProgressBar]:
    if not enabled:
        yield ProgressBar()
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    columns = [TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
               TextColumn("{task.fields[rate]}"), TimeElapsedColumn(), TimeRemainingColumn()]
    with Progress(*columns) as progress:
        yield ProgressBar(progress, progress.add_task(description, total=total, rate=""))
