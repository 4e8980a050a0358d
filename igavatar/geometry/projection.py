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
