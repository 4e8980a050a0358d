"""A contact sheet: frames with the mask tinted and the projected skeleton drawn, to check alignment.

    sheet = contact_sheet([(rgb, mask, joints_uv, label), ...], parents, columns=4)   # (H, W, 3) uint8
"""

from __future__ import annotations

import cv2
import numpy as np


def _thumbnail(rgb: np.ndarray, mask: np.ndarray, joints_uv: np.ndarray, parents: np.ndarray, label: str, size: int) -> np.ndarray:
    image = rgb.astype(np.float32)
    tint = np.array([0, 255, 0], np.float32)
    image[mask] = 0.8 * image[mask] + 0.2 * tint
    # The mask boundary in magenta makes small misalignments visible at thumbnail size.
    edges = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0
    image[edges] = (255, 0, 255)
    image = image.clip(0, 255).astype(np.uint8)
    scale = size / max(image.shape[:2])
    thumb = cv2.resize(image, (round(image.shape[1] * scale), round(image.shape[0] * scale)), interpolation=cv2.INTER_AREA)
    uv = joints_uv * scale
    for child, parent in enumerate(parents):
        if parent < 0 or not (np.all(np.isfinite(uv[child])) and np.all(np.isfinite(uv[parent]))):
            continue
        p0 = tuple(int(round(v)) for v in uv[parent])
        p1 = tuple(int(round(v)) for v in uv[child])
        cv2.line(thumb, p0, p1, (255, 200, 0), 1, cv2.LINE_AA)
    for point in uv:
        if np.all(np.isfinite(point)):
            cv2.circle(thumb, tuple(int(round(v)) for v in point), 2, (255, 40, 40), -1, cv2.LINE_AA)
    canvas = np.full((size + 18, size, 3), 255, np.uint8)
    canvas[: thumb.shape[0], : thumb.shape[1]] = thumb
    cv2.putText(canvas, label[:28], (3, size + 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return canvas


def contact_sheet(
    items: list[tuple[np.ndarray, np.ndarray, np.ndarray, str]],
    parents: np.ndarray,
    columns: int = 4,
    thumb_size: int = 256,
) -> np.ndarray:
    """Tile thumbnails of (rgb (H,W,3) uint8, mask (H,W) bool, joints_uv (J,2) pixels, label).

    Returns an RGB uint8 image; the mask is tinted green with a magenta outline and the skeleton
    (bones from `parents` (J,)) is drawn over it.
    """
    tiles = [_thumbnail(rgb, mask, uv, parents, label, thumb_size) for rgb, mask, uv, label in items]
    rows = (len(tiles) + columns - 1) // columns
    tile_h, tile_w = tiles[0].shape[:2]
    sheet = np.full((rows * tile_h, columns * tile_w, 3), 255, np.uint8)
    for index, tile in enumerate(tiles):
        r, c = divmod(index, columns)
        sheet[r * tile_h : (r + 1) * tile_h, c * tile_w : (c + 1) * tile_w] = tile
    return sheet
