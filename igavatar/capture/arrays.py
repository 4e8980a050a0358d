"""Checked reading of the array files importers meet (.npz, .npy, dicts of arrays).

    data = read_npz(root / "cameras.npz")
    K = array_of(root / "cameras.npz", data, "intrinsic", (3, 3))           # float64, finite
    betas = array_of(path, data, "betas", (10,), (1, 10)).reshape(10)

Every error names the file, the key and the shape found and expected, so a user can tell a wrong
file from a damaged one.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from igavatar.errors import InputError


def read_npz(path: Path) -> dict[str, np.ndarray]:
    """Every array of an .npz (pickled objects refused); InputError if missing or unreadable."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: missing")
    with path.open("rb") as file:
        magic = file.read(6)
    # np.load takes anything that is neither a zip nor an .npy for a pickle: tell them apart first.
    if magic == b"\x93NUMPY":
        raise InputError(f"{path}: is a single .npy array, expected an .npz of named arrays")
    if not magic.startswith(b"PK"):
        raise InputError(f"{path}: not a readable .npz file (not a zip archive)")
    try:
        with np.load(path, allow_pickle=False) as data:
            return {key: data[key] for key in data.files}
    except ValueError as exc:
        raise InputError(f"{path}: holds pickled objects, which igavatar never loads; save plain arrays") from exc
    except Exception as exc:  # zipfile.BadZipFile, OSError: not an npz
        raise InputError(f"{path}: not a readable .npz file ({exc})") from exc


def read_npy(path: Path) -> np.ndarray:
    """The array of an .npy file (pickled objects refused)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: missing")
    try:
        return np.load(path, allow_pickle=False)
    except Exception as exc:  # ValueError (pickled / not npy), OSError
        raise InputError(f"{path}: not a readable .npy array ({exc})") from exc


def _shape_text(shape: tuple) -> str:
    inner = ", ".join("N" if s is None else str(s) for s in shape)
    return f"({inner},)" if len(shape) == 1 else f"({inner})"


def array_of(path: Path, data: Mapping[str, object], key: str, *shapes: tuple) -> np.ndarray:
    """`data[key]` as a finite float64 array with one of `shapes` (None: any size >= 1).

    Raises:
        InputError: the key is missing, not numeric, of another shape, or holds NaN/inf.
    """
    if key not in data:
        present = ", ".join(sorted(map(str, data))) or "none"
        raise InputError(f"{path}: key '{key}' missing (keys present: {present})")
    raw = np.asarray(data[key])
    expected = " or ".join(_shape_text(s) for s in shapes)
    if raw.dtype.kind not in "fiub":
        raise InputError(f"{path}: key '{key}' has dtype {raw.dtype}, expected numbers of shape {expected}")
    fits = any(
        raw.ndim == len(shape) and all(dim >= 1 if want is None else dim == want for dim, want in zip(raw.shape, shape))
        for shape in shapes
    )
    if not fits:
        raise InputError(f"{path}: key '{key}' has shape {tuple(raw.shape)}, expected {expected}")
    array = raw.astype(np.float64)
    if not np.all(np.isfinite(array)):
        raise InputError(f"{path}: key '{key}' holds NaN or infinite values")
    return array


def scalar_of(path: Path, data: Mapping[str, object], key: str) -> float:
    """`data[key]` as one finite number (shape () or any shape of size 1)."""
    if key not in data:
        present = ", ".join(sorted(map(str, data))) or "none"
        raise InputError(f"{path}: key '{key}' missing (keys present: {present})")
    raw = np.asarray(data[key])
    if raw.dtype.kind not in "fiu" or raw.size != 1 or not np.isfinite(raw).all():
        raise InputError(f"{path}: key '{key}' has shape {tuple(raw.shape)} and dtype {raw.dtype}, expected one number")
    return float(raw.reshape(()))


def bad_intrinsics(K: np.ndarray, height: int, width: int) -> tuple[np.ndarray, str] | None:
    """The frames whose intrinsics cannot be a pinhole camera's for this image size, and why.

    Args:
        K: (N, 3, 3) intrinsics in pixels; height, width: the image size they are for.
    Returns:
        None when every frame's K is fine, else ((N,) bool of the bad frames, the reason). A
        negative focal length would mirror the image: preprocessing would still run and silently
        take the subject for loose clothing (issue 37). A principal point more than half the image
        outside it is a K for another image size.
    """
    K = np.asarray(K, dtype=np.float64)
    if not np.all(np.isfinite(K)):
        return ~np.all(np.isfinite(K), axis=(-2, -1)), "intrinsics hold NaN or infinite values"
    focal = K[:, [0, 1], [0, 1]]
    if np.any(focal <= 0):
        return np.any(focal <= 0, axis=-1), "a focal length K[0, 0] or K[1, 1] is not positive (it must be > 0 pixels)"
    last_row = ~np.all(np.isclose(K[:, 2], [0, 0, 1], atol=1e-6), axis=-1)
    if last_row.any():
        return last_row, "the last row of K is not [0, 0, 1]"
    cx, cy = K[:, 0, 2], K[:, 1, 2]
    outside = (cx < -0.5 * width) | (cx > 1.5 * width) | (cy < -0.5 * height) | (cy > 1.5 * height)
    if outside.any():
        return outside, (f"the principal point (K[0, 2], K[1, 2]) lies far outside the {width}x{height} image: "
                         "K is for another image size")
    return None
