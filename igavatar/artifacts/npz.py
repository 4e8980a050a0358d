"""Arrays of an artifact's .npz file, read with a clear error when the file or a key is unusable.

    arrays = read_npz(path / "frames.npz", ("K", "w2c"), "the frames")   # {key: array}
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from igavatar.errors import ArtifactError


def read_npz(path: Path, keys: Sequence[str], what: str, remedy: str = "re-run `igavatar preprocess`") -> dict[str, np.ndarray]:
    """The arrays `keys` of `path`; ArtifactError naming the file, the missing keys and `remedy`."""
    try:
        with np.load(path) as stored:
            missing = [key for key in keys if key not in stored.files]
            if missing:
                raise ArtifactError(f"{path}: keys {', '.join(missing)} are missing; {remedy}")
            return {key: stored[key] for key in keys}
    except (OSError, ValueError) as error:
        raise ArtifactError(f"{path}: cannot read {what} ({error}); {remedy}") from error
