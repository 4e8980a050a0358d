"""Ctrl-C and SIGTERM as exceptions that arrive only where the program can stop cleanly.

    with signals_as_interrupts():        # the CLI, around one command
        with deferred_interrupts():      # a training step, a multi-threaded native call
            ...                          # a signal here is held, then raised when the block ends
        raise_if_interrupted()           # a checkpoint where a swallowed interrupt resurfaces

Two failure modes make this necessary (issue 37):
- Native code with worker threads (scipy's cKDTree.query(workers=-1)) checks for signals in the
  main thread and returns while its workers still read the arrays: a KeyboardInterrupt raised
  there lets Python free them, and the process dies of a segmentation fault. Inside
  `deferred_interrupts` the handler only records the signal, so the call runs to its end.
- Libraries catch BaseException (trimesh around its optional imports and in several methods), so
  a KeyboardInterrupt raised inside them can vanish and the run goes on to replace its output.
  `signals_as_interrupts` remembers every signal until the command ends, and
  `raise_if_interrupted` (called per training step and before an artifact is renamed into place)
  raises it again.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

from igavatar.errors import Terminated

_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class _Received:
    """The signal received during the current command (None: none). Process-wide, as signals are."""

    signum: int | None = None


def _exception(signum: int) -> KeyboardInterrupt:
    return Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def _record_and_raise(signum, frame) -> None:
    _Received.signum = signum
    raise _exception(signum)


def _in_main_thread() -> bool:
    # Python only installs and runs signal handlers in the main thread.
    return threading.current_thread() is threading.main_thread()


@contextmanager
def signals_as_interrupts() -> Iterator[None]:
    """Within the block, Ctrl-C raises KeyboardInterrupt and SIGTERM raises Terminated, and both
    are remembered for `raise_if_interrupted`. The previous handlers return afterwards."""
    if not _in_main_thread():  # embedded use from a worker thread: leave signals alone
        yield
        return
    previous = {signum: signal.signal(signum, _record_and_raise) for signum in _SIGNALS}
    _Received.signum = None
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        _Received.signum = None


def raise_if_interrupted() -> None:
    """Raise the interrupt received during this command, if any (even one a library swallowed)."""
    if _Received.signum is not None:
        raise _exception(_Received.signum)


@contextmanager
def deferred_interrupts() -> Iterator[None]:
    """Hold Ctrl-C and SIGTERM until the block ends, then deliver the first one held.

    Delivery calls the handler that was in place before the block (ours, Python's default
    KeyboardInterrupt, an outer deferral's recorder), or re-raises the signal when that was the
    system default. Not in the main thread: a no-op, as signals are not delivered there.
    """
    if not _in_main_thread():
        yield
        return
    held: list[int] = []
    previous = {signum: signal.signal(signum, lambda signum, frame: held.append(signum)) for signum in _SIGNALS}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        if held and previous[held[0]] is _record_and_raise:
            _Received.signum = held[0]  # remembered even when the block ends in an exception
    if held:
        _deliver(held[0], previous[held[0]])


def _deliver(signum: int, handler) -> None:
    if callable(handler):
        handler(signum, None)
    elif handler == signal.SIG_DFL:
        signal.raise_signal(signum)
    # SIG_IGN: the signal was meant to be ignored.
