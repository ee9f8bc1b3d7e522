"""Progress bars (rich) with items per second; a silent stand-in when disabled."""

from __future__ import annotations

from contextlib import contextmanager
from typing import Any, Iterator


class ProgressBar:
    """Advance with :meth:`advance`; shows count, rate (items/s), elapsed and remaining."""

    def __init__(self, progress: Any = None, task: Any = None):
        self._progress, self._task = progress, task

    def set_total(self, total: int) -> None:
        """Change the number of items (when it is known only once work has started)."""
        if self._progress is not None:
            self._progress.update(self._task, total=total)

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


class StepTimer:
    """A status line per step with its duration (rich, on stderr); silent when disabled.

    ``with steps("render templates"):`` shows a spinner while the step runs, then
    ``✓ render templates  3.21 s``; the durations are kept in ``timings`` (s).
    """

    def __init__(self, enabled: bool = True, console: Any = None):
        self.enabled = enabled
        self.timings: dict[str, float] = {}
        self._console = console
        if enabled and console is None:
            from rich.console import Console

            self._console = Console(stderr=True)

    def note(self, text: str) -> None:
        if self.enabled:
            self._console.print(f"  [dim]{text}[/]")

    def warn(self, text: str) -> None:
        if self.enabled:
            self._console.print(f"  [yellow]warning:[/] {text}")

    def line(self, text: str) -> None:
        """``text`` as one line, never wrapped and without markup (it may hold a command
        to copy, or brackets)."""
        if self.enabled:
            self._console.print(f"  {text}", soft_wrap=True, markup=False, highlight=False)

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        import time

        t0 = time.perf_counter()
        if not self.enabled:
            yield
            self.timings[name] = time.perf_counter() - t0
            return
        with self._console.status(f"{name} ..."):
            yield
        dt = time.perf_counter() - t0
        self.timings[name] = dt
        self._console.print(f"[green]✓[/] {name:<38} {dt:7.2f} s")
