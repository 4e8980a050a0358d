"""Pinhole cameras: world points to pixels, camera centers (OpenCV: x right, y down, z forward).

    uv, z = project_points(K, w2c, x_world)     # (P, 2) pixels, (P,) camera depths
"""

from __future__ import annotations

import numpy as np


def project_points(K: np.ndarray, w2c: np.ndarray, x_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (P, 2) and camera depths z (P,) of world points (P, 3).

    Args:
        K: (3, 3) intrinsics; w2c: (4, 4) world -> camera.
    Points on or behind the camera plane (z <= 1e-9) get NaN pixel coordinates.
    """
    x_camera = x_world @ w2c[:3, :3].T + w2c[:3, 3]
    z = x_camera[:, 2]
    uv = (x_camera @ K.T)[:, :2] / np.where(z > 1e-9, z, np.nan)[:, None]
    return uv, z


def camera_center(w2c: np.ndarray) -> np.ndarray:
    """(3,) world position of the camera center of a (4, 4) world-to-camera matrix."""
    return -w2c[:3, :3].T @ w2c[:3, 3]


def filled_silhouette(K: np.ndarray, w2c: np.ndarray, vertices_world: np.ndarray, faces: np.ndarray,
                      height: int, width: int) -> np.ndarray:
    """(height, width) bool: a mesh's projected triangles (V, 3) world vertices, (F, 3) faces, filled."""
    import cv2

    uv, z = project_points(K, w2c, vertices_world)
    silhouette = np.zeros((height, width), np.uint8)
    visible = np.isfinite(uv).all(axis=1) & (z > 0)
    # One call per triangle: fillPoly's even-odd rule would cancel overlapping triangles.
    for triangle in np.round(uv[faces[visible[faces].all(axis=1)]] * 4).astype(np.int32):
        cv2.fillConvexPoly(silhouette, triangle, 1, lineType=cv2.LINE_8, shift=2)
    # Rounding leaves one-pixel cracks between neighbouring triangles; close them.
    return cv2.morphologyEx(silhouette, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)) > 0
