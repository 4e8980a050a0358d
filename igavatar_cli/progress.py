"""Progress for stages: implements `stages.progress.ProgressSink`.

    with progress_sink(console, quiet=False) as sink:    # bars on a terminal, plain lines otherwise
        run_preprocess(options, progress=sink)

On a terminal, rich bars. Without one (`igavatar demo > log.txt`, nohup, CI, a pipe to tee) bars
would print nothing until the end, so `PlainProgress` writes one line when a task starts and ends
(with its elapsed time) and a line every few percent of its steps with the step's fields
(loss, PSNR, it/s) and an ETA.
"""

from __future__ import annotations

import time
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


def _duration(seconds: float) -> str:
    """12.3 s, 4 min 05 s, 1 h 02 min."""
    if seconds < 60:
        return f"{seconds:.1f} s"
    minutes, secs = divmod(int(round(seconds)), 60)
    if minutes < 60:
        return f"{minutes} min {secs:02d} s"
    return f"{minutes // 60} h {minutes % 60:02d} min"


class PlainProgress:
    """One plain line per task start, end and every `1/lines_per_task` of its steps (no TTY needed)."""

    def __init__(self, console: Console, quiet: bool = False, lines_per_task: int = 20):
        self._console = console
        self._quiet = quiet
        self._lines_per_task = lines_per_task

    def __enter__(self) -> "PlainProgress":
        return self

    def __exit__(self, *exc) -> None:
        pass

    def _print(self, line: str) -> None:
        if not self._quiet:
            # markup off: paths and messages may contain [brackets]; no wrapping so logs grep well.
            self._console.print(line, markup=False, highlight=False, soft_wrap=True)

    def status(self, message: str) -> None:
        self._print(message)

    @contextmanager
    def task(self, description: str, total: int | None) -> Iterator[Callable[..., None]]:
        started = time.perf_counter()
        every = max(1, (total or 0) // self._lines_per_task) if total else 50
        state = {"done": 0, "first": None}
        self._print(f"{description}: started" + (f" ({total} steps)" if total else ""))

        def advance(n: int = 1, **fields) -> None:
            before = state["done"]
            state["done"] += n
            if state["first"] is None:
                # The rate counts from the first call: a resumed run's jump to its step is not speed.
                state["first"] = (state["done"], time.perf_counter())
                if before == 0 and n > 1:
                    return
            if state["done"] // every == before // every and state["done"] != total:
                return
            line = f"{description}: {state['done']}" + (f"/{total}" if total else "")
            line += "".join(f"  {k} {v}" for k, v in fields.items())
            first_done, first_time = state["first"]
            elapsed = time.perf_counter() - first_time
            if total and elapsed > 0 and state["done"] > first_done:
                rate = (state["done"] - first_done) / elapsed
                line += f"  eta {_duration((total - state['done']) / rate)}"
            self._print(line)

        yield advance
        self._print(f"{description}: done in {_duration(time.perf_counter() - started)}")


def progress_sink(console: Console, quiet: bool = False) -> RichProgress | PlainProgress:
    """Rich bars when `console` is a terminal, plain lines when it is a file, a pipe or CI's log."""
    if console.is_terminal:
        return RichProgress(console, quiet=quiet)
    return PlainProgress(console, quiet=quiet)
