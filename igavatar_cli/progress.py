"""Rich progress bars for stages: implements `stages.progress.ProgressSink`.

    with RichProgress(console, quiet=False) as sink:
        run_preprocess(options, progress=sink)
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn


class RichProgress:
    """Draws one bar per stage task on stderr; prints nothing in quiet mode."""

    def __init__(self, console: Console, quiet: bool = False):
        self._console = console
        self._quiet = quiet
        self._progress = Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[info]}"),
            TimeElapsedColumn(),
            TextColumn("eta"),
            TimeRemainingColumn(),
            console=console,
            disable=quiet,
            transient=False,
        )

    def __enter__(self) -> "RichProgress":
        self._progress.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self._progress.__exit__(*exc)

    def status(self, message: str) -> None:
        if not self._quiet:
            self._progress.console.print(f"[dim]{message}[/]")

    @contextmanager
    def task(self, description: str, total: int | None) -> Iterator[Callable[..., None]]:
        task_id = self._progress.add_task(description, total=total, info="")

        def advance(n: int = 1, **fields) -> None:
            info = "  ".join(f"{k} {v}" for k, v in fields.items())
            self._progress.update(task_id, advance=n, info=info)

        yield advance
        self._progress.update(task_id, completed=total if total is not None else None)
