"""Arrays of an artifact's .npz file, read with a clear error when the file, a key, a shape or a
dtype is unusable.

    arrays = read_npz(path / "frames.npz", {"K": ("N", 3, 3), "w2c": ("N", 4, 4)}, "the frames")

Shapes name their free sizes ("N", "J"): every key that names a size must agree on it, and a size
given in `sizes` is fixed beforehand. A file whose hash matches its manifest can still be of the
wrong shape (an edited file, re-hashed); the stages would then fail deep inside, with a traceback.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from igavatar.errors import ArtifactError

#: A shape: fixed sizes (int) and named free ones (str); None: any shape (no check).
Shape = tuple[int | str, ...] | None

#: dtype kinds accepted: numbers and booleans, or text (names).
_NUMERIC, _TEXT = "fiub", "US"


def _shape_text(shape: tuple) -> str:
    return "(" + ", ".join(str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"


def _check_array(path: Path, key: str, array: np.ndarray, shape: tuple, sizes: dict[str, int], remedy: str) -> None:
    """ArtifactError unless `array` has `shape` (binding named sizes in `sizes`) and a usable dtype."""
    if array.dtype.kind not in _NUMERIC + _TEXT:
        raise ArtifactError(f"{path}: key '{key}' has dtype {array.dtype}, expected numbers; {remedy}")
    fits = array.ndim == len(shape)
    for found, want in zip(array.shape, shape) if fits else ():
        if isinstance(want, str):
            fits = fits and sizes.setdefault(want, found) == found
        else:
            fits = fits and found == want
    if not fits:
        named = ", ".join(f"{k}={v}" for k, v in sizes.items() if k in shape)
        raise ArtifactError(f"{path}: key '{key}' has shape {tuple(array.shape)}, expected {_shape_text(shape)}"
                            + (f" with {named}" if named else "") + f"; {remedy}")
    if array.dtype.kind == "f" and not np.all(np.isfinite(array)):
        raise ArtifactError(f"{path}: key '{key}' holds NaN or infinite values; {remedy}")


def read_npz(path: Path, shapes: Mapping[str, Shape], what: str, remedy: str = "re-run `igavatar preprocess`",
             sizes: Mapping[str, int] | None = None) -> dict[str, np.ndarray]:
    """The arrays `shapes` names, from `path`, each checked against its shape.

    Args:
        path: the .npz file.
        shapes: key -> expected shape (see `Shape`).
        what: what the file holds, for messages ("the frames").
        remedy: what the user should do, for messages.
        sizes: named sizes already known (e.g. {"J": 24}).
    Raises:
        ArtifactError naming the file, the key, the shape found and expected, and `remedy`.
    """
    try:
        with np.load(path) as stored:
            missing = [key for key in shapes if key not in stored.files]
            if missing:
                raise ArtifactError(f"{path}: keys {', '.join(missing)} are missing; {remedy}")
            arrays = {key: stored[key] for key in shapes}
    except (OSError, ValueError) as error:
        raise ArtifactError(f"{path}: cannot read {what} ({error}); {remedy}") from error
    bound = dict(sizes or {})
    for key, shape in shapes.items():
        if shape is not None:
            _check_array(path, key, arrays[key], shape, bound, remedy)
    return arrays
