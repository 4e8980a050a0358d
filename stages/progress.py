"""How a stage reports progress without knowing who listens (the CLI draws rich bars).

    def run(..., progress: ProgressSink = NULL_PROGRESS):
        with progress.task("rendering frames", total=n) as advance:
            for ...: advance(1)
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Protocol


class ProgressSink(Protocol):
    """Receives status lines and counted tasks from a stage."""

    def status(self, message: str) -> None:
        """A one-off line, e.g. 'building Anny cache (first run, ~1 min)'."""

    def task(self, description: str, total: int | None) -> "contextlib.AbstractContextManager[Callable[..., None]]":  # noqa: F821
        """A counted task; the context yields `advance(n=1, **fields)`."""


class _NullProgress:
    def status(self, message: str) -> None:
        pass

    @contextmanager
    def task(self, description: str, total: int | None) -> Iterator[Callable[..., None]]:
        yield lambda n=1, **fields: None


NULL_PROGRESS: ProgressSink = _NullProgress()
