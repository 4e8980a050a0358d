"""Image-space preprocessing: undistortion, resizing with the matching intrinsics change.

    scale, (h, w) = resize_plan(1080, 1080, max_size=512)
    rgb_small = resize_image(rgb, (h, w)); K_small = scale_intrinsics(K, scale_xy)
"""

from __future__ import annotations

import cv2
import numpy as np


def resize_plan(height: int, width: int, max_size: int) -> tuple[tuple[float, float], tuple[int, int]]:
    """Target size so that the longer side is at most `max_size` (never upscales).

    Returns ((scale_x, scale_y), (new_height, new_width)); the scales are exact ratios of the sizes.
    """
    factor = min(1.0, max_size / max(height, width))
    new_h, new_w = max(1, round(height * factor)), max(1, round(width * factor))
    return (new_w / width, new_h / height), (new_h, new_w)


def scale_intrinsics(K: np.ndarray, scale_xy: tuple[float, float]) -> np.ndarray:
    """Intrinsics (..., 3, 3) after resizing by (sx, sy), pixel centers at integer coordinates.

    A pixel center x maps to sx * (x + 0.5) - 0.5, hence the half-pixel terms on the principal point.
    """
    sx, sy = scale_xy
    K = np.array(K, dtype=np.float64, copy=True)
    K[..., 0, :] *= sx
    K[..., 1, :] *= sy
    K[..., 0, 2] += 0.5 * sx - 0.5
    K[..., 1, 2] += 0.5 * sy - 0.5
    return K


def resize_image(rgb: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    """Area-resample an (H, W, 3) uint8 image to size_hw."""
    if rgb.shape[:2] == tuple(size_hw):
        return rgb
    return cv2.resize(rgb, (size_hw[1], size_hw[0]), interpolation=cv2.INTER_AREA)


def resize_mask(mask: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    """Resize an (H, W) bool mask by area coverage, thresholded at one half."""
    if mask.shape[:2] == tuple(size_hw):
        return mask
    coverage = cv2.resize(mask.astype(np.float32), (size_hw[1], size_hw[0]), interpolation=cv2.INTER_AREA)
    return coverage >= 0.5


def undistort(rgb: np.ndarray, mask: np.ndarray, K: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Remove lens distortion (OpenCV 5-coefficient model) from an image and its mask, keeping K.

    The mask is remapped with nearest-neighbour sampling so it stays binary and aligned.
    """
    if dist is None or not np.any(dist):
        return rgb, mask
    h, w = rgb.shape[:2]
    map_x, map_y = cv2.initUndistortRectifyMap(K, dist, None, K, (w, h), cv2.CV_32FC1)
    rgb_u = cv2.remap(rgb, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    mask_u = cv2.remap(mask.astype(np.uint8), map_x, map_y, interpolation=cv2.INTER_NEAREST) > 0
    return rgb_u, mask_u


def project_points(K: np.ndarray, w2c: np.ndarray, x_world: np.ndarray) -> np.ndarray:
    """Pixel coordinates (P, 2) of world points (P, 3); points behind the camera get NaN."""
    x_cam = x_world @ w2c[:3, :3].T + w2c[:3, 3]
    z = x_cam[:, 2:3]
    uv = (x_cam @ K.T)[:, :2] / np.where(z > 1e-9, z, np.nan)
    return uv
