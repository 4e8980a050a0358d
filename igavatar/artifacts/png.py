"""PNG files of artifacts: one encoder and one writer, with one failure behaviour.

    write_png(tmp / "images" / "f000.png", rgb)        # (H, W, 3) uint8 RGB, or (H, W) uint8/bool gray
    data = png_bytes(rgb)                                # the same encoding, for embedding (GLB textures)

OpenCV's imwrite returns False on failure (a full disk, a bad path) and writes nothing, which
stages used to ignore; here the bytes are encoded first (ValueError: not an image we make) and
written through atomic_write_bytes (StorageError naming the path when the disk refuses).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from igavatar.artifacts.atomic import atomic_write_bytes


def png_bytes(image: np.ndarray) -> bytes:
    """PNG encoding of an (H, W, 3) uint8 RGB image or an (H, W) uint8 / bool gray one (bool: 0/255)."""
    image = np.asarray(image)
    if image.dtype == bool:
        image = image.astype(np.uint8) * 255
    if image.dtype != np.uint8 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)) or image.size == 0:
        raise ValueError(f"png_bytes: expected (H, W, 3) or (H, W) uint8, got {image.shape} {image.dtype}")
    bgr = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2BGR) if image.ndim == 3 else np.ascontiguousarray(image)
    ok, encoded = cv2.imencode(".png", bgr)
    if not ok:
        raise ValueError(f"png_bytes: OpenCV could not encode a {image.shape} image")
    return encoded.tobytes()


def write_png(path: Path, image: np.ndarray) -> None:
    """Write `image` (see png_bytes) to `path` whole or not at all; parent folders are made."""
    atomic_write_bytes(Path(path), png_bytes(image))
