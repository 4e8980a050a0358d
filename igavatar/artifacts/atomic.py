"""Write a directory so that it appears complete or not at all, replacing only what may be replaced.

    with atomic_directory(Path("runs/dataset"), kind="dataset", inputs=[capture]) as tmp:
        (tmp / "frames.npz").write_bytes(...)      # renamed to runs/dataset on success

A crash, an exception or Ctrl-C inside the block removes the temporary directory and leaves any
earlier artifact at the target untouched. The target is checked by `check_output_target` (only
an artifact of the same kind, never an input) before anything is written and again just before
the rename. Fixable file-system failures (read-only, permission, no space, name too long) become
`StorageError`s naming the path.

Temporary names carry the writing process's id (`.NAME.tmp-<pid>-<random>`), so a run can tell
the leftovers of a killed run (their process is gone) from those of a run still going, and
removes the former before it starts.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from igavatar.artifacts.storage import storage_errors
from igavatar.artifacts.targets import check_output_target
from igavatar.interrupts import deferred_interrupts, raise_if_interrupted


def _prefix(name: str, role: str) -> str:
    """Name prefix of this process's temporary siblings of `name` (role 'tmp' or 'old')."""
    return f".{name}.{role}-{os.getpid()}-"


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, but another user's
        return True
    return True


def clean_stale_temporaries(target: Path) -> list[Path]:
    """Remove the temporary siblings of `target` left by killed igavatar runs; return what was removed.

    Only names this module makes are touched: `.NAME.tmp-<pid>-*` and `.NAME.old-<pid>-*` whose
    process no longer runs, and the pid-less `.NAME.tmp-XXXXXXXX` / `.NAME.old-XXXXXXXX` of earlier
    igavatar versions (tempfile's 8-character suffix).
    """
    target = Path(target)
    parent = target.parent
    if not parent.is_dir():
        return []
    name = re.escape(target.name)
    with_pid = re.compile(rf"^\.{name}\.(?:tmp|old)-(\d+)-[A-Za-z0-9_]+$")
    legacy = re.compile(rf"^\.{name}\.(?:tmp|old)-[a-z0-9_]{{8}}$")
    removed = []
    for entry in parent.iterdir():
        match = with_pid.match(entry.name)
        stale = (match is not None and not _process_alive(int(match.group(1)))) or legacy.match(entry.name) is not None
        if not stale:
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)
        removed.append(entry)
    return removed


@contextmanager
def atomic_directory(target: Path, *, kind: str, inputs: Iterable[Path] = ()) -> Iterator[Path]:
    """Yield a fresh sibling temporary directory that replaces `target` when the block succeeds.

    Args:
        target: the artifact directory to write.
        kind: the artifact kind written; `target` may only be replaced if it is one of this kind.
        inputs: the paths the command reads; `target` may not be, contain or lie inside any of them.

    The old target (if any) is first renamed aside and only deleted after the new directory has
    been renamed into place, so at every instant either the old or the new artifact exists whole.
    Raises UnsafeOutputError (nothing written) or StorageError (temporary directory removed).
    """
    target = Path(target)
    inputs = [Path(p) for p in inputs if p is not None]
    check_output_target(target, kind, inputs)
    with storage_errors(target):
        target.parent.mkdir(parents=True, exist_ok=True)
        clean_stale_temporaries(target)
        tmp = Path(tempfile.mkdtemp(prefix=_prefix(target.name, "tmp"), dir=target.parent))
    try:
        with storage_errors(target):
            # mkdtemp makes the directory private (0700); an artifact gets the usual permissions.
            os.chmod(tmp, 0o777 & ~current_umask())
            yield tmp
        # The block may have run for minutes: check again that nobody put something else there.
        check_output_target(target, kind, inputs)
        # A Ctrl-C that a library swallowed inside the block still means "do not replace".
        raise_if_interrupted()
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    # The renames and the removal of the old artifact are not split by Ctrl-C (held until done).
    with deferred_interrupts():
        _replace(tmp, target)


def _replace(tmp: Path, target: Path) -> None:
    """Rename `tmp` to `target`, setting any old target aside first and removing it after."""
    old = None
    try:
        with storage_errors(target):
            if target.exists():
                old = Path(tempfile.mkdtemp(prefix=_prefix(target.name, "old"), dir=target.parent))
                os.rmdir(old)
                os.replace(target, old)
            os.replace(tmp, target)
    except BaseException:
        if old is not None and old.exists() and not target.exists():
            os.replace(old, target)
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def current_umask() -> int:
    """The process's umask (read by setting and restoring it: there is no getter)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write a single file via a temporary sibling and rename (same guarantee for one file).

    Fixable file-system failures become a StorageError naming `path`; the temporary file is removed.
    """
    path = Path(path)
    with storage_errors(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=_prefix(path.name, "tmp"), dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp's file is private (0600)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
