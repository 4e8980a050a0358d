"""File-system failures as one clear line: which path, what happened, what to do.

    with storage_errors(Path("run/model")):
        np.savez(path, **arrays)        # OSError(ENOSPC) -> StorageError("...: no space left ...")

Only the failures a user can fix (read-only, permission, no space, quota, path or name too long)
are translated; any other OSError is a bug or a hardware fault and keeps its traceback.
"""

from __future__ import annotations

import errno
import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from igavatar.errors import StorageError

#: errno -> (what happened, how to fix it).
_FIXABLE: dict[int, tuple[str, str]] = {
    errno.ENOSPC: ("no space left on the device", "free some space or write to another disk (another --out or --run-dir)"),
    errno.EDQUOT: ("disk quota exceeded", "free some space or write to another disk (another --out or --run-dir)"),
    errno.EROFS: ("the file system is read-only", "write to a writable location (another --out or --run-dir)"),
    errno.EACCES: ("permission denied", "fix the permissions, or use a location you can write to (another --out or --run-dir)"),
    errno.EPERM: ("operation not permitted", "fix the permissions, or use a location you can write to (another --out or --run-dir)"),
    errno.ENAMETOOLONG: ("the path or a name in it is too long", "choose a shorter path"),
}


def storage_message(exc: OSError, where: Path) -> str | None:
    """The one-line message for a fixable OSError (naming its file, else `where`), or None."""
    if exc.errno not in _FIXABLE:
        return None
    what, fix = _FIXABLE[exc.errno]
    path = where if exc.filename is None else _as_final_path(str(exc.filename))
    return f"{path}: {what}; {fix}"


#: A temporary sibling's name as igavatar.artifacts.atomic makes it: `.NAME.tmp-<pid>-<random>`.
_TEMPORARY = re.compile(r"^\.(.+)\.(?:tmp|old)-(?:\d+-)?[A-Za-z0-9_]+$")


def _as_final_path(filename: str) -> str:
    """A path inside an artifact's temporary directory, named as it would be once in place: the
    user knows `run/mesh/canonical.ply`, not `run/.mesh.tmp-4121-x8a2/canonical.ply`."""
    parts = Path(filename).parts
    return str(Path(*(_TEMPORARY.sub(r"\1", part) for part in parts))) if parts else filename


@contextmanager
def storage_errors(where: Path) -> Iterator[None]:
    """Re-raise fixable OSErrors inside the block as StorageError; `where` is named when the OSError names no file."""
    try:
        yield
    except StorageError:
        raise
    except OSError as exc:
        message = storage_message(exc, Path(where))
        if message is None:
            raise
        raise StorageError(message) from exc
