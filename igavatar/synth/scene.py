"""Staging of the synthetic capture: a static camera that frames the subject, a light, subject yaw.

    K, w2c = frame_static_camera(x_world_all_frames, height=512, width=512, distance=3.0)
    light = light_position(w2c)                                   # above and right of the camera

World frame = Anny's: +Z up, the subject faces -Y at rest, its left is +X. Cameras are OpenCV
(x right, y down, z forward), pixel centers at integer coordinates.
"""

from __future__ import annotations

import numpy as np
import torch

from igavatar.body.rotations import axis_angle_to_matrix
from igavatar.errors import InputError

UP = np.array([0.0, 0.0, 1.0])


def look_w2c(camera_center: np.ndarray, forward: np.ndarray, up: np.ndarray = UP) -> np.ndarray:
    """(4, 4) world-to-camera matrix of an OpenCV camera at `camera_center` looking along `forward`.

    The image's "down" is the component of -up orthogonal to forward, so a horizontal `forward`
    gives an upright, level image.
    """
    forward = np.asarray(forward, dtype=np.float64)
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        raise InputError("camera: viewing direction is parallel to the up axis")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])  # rows: camera axes in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3] = rotation
    w2c[:3, 3] = -rotation @ np.asarray(camera_center, dtype=np.float64)
    return w2c


def frame_static_camera(
    x_world: np.ndarray,
    height: int,
    width: int,
    *,
    distance: float = 3.0,
    view_direction: np.ndarray = np.array([0.0, 1.0, 0.0]),
    margin: float = 0.06,
) -> tuple[np.ndarray, np.ndarray]:
    """A level pinhole camera `distance` meters from the center of the points, zoomed to fit them all.

    Args:
        x_world: (P, 3) every point that must be visible (e.g. all posed vertices of all frames).
        height, width: image size in pixels.
        distance: horizontal distance from the camera to the center of the points' bounding box.
        view_direction: horizontal viewing direction (default +Y: the camera faces the subject's front).
        margin: free border on each side, as a fraction of the image size.
    Returns:
        K (3, 3) with square pixels and the principal point at the image center, and w2c (4, 4).
    """
    x_world = np.asarray(x_world, dtype=np.float64).reshape(-1, 3)
    low, high = x_world.min(axis=0), x_world.max(axis=0)
    center = 0.5 * (low + high)
    forward = np.asarray(view_direction, dtype=np.float64).copy()
    forward[2] = 0.0
    forward /= np.linalg.norm(forward)
    w2c = look_w2c(center - distance * forward, forward)
    x_camera = x_world @ w2c[:3, :3].T + w2c[:3, 3]
    if np.any(x_camera[:, 2] < 0.1):
        raise InputError(
            f"camera: the subject comes closer than 0.1 m to a camera {distance} m away; increase the distance"
        )
    # Largest tangent on each axis decides the focal length that still fits with the margin.
    tan_x = np.abs(x_camera[:, 0] / x_camera[:, 2]).max()
    tan_y = np.abs(x_camera[:, 1] / x_camera[:, 2]).max()
    focal = min((0.5 - margin) * width / max(tan_x, 1e-9), (0.5 - margin) * height / max(tan_y, 1e-9))
    K = np.array([[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return K, w2c


def light_position(w2c: np.ndarray, offset_camera: tuple[float, float, float] = (0.6, -0.9, 0.0)) -> np.ndarray:
    """(3,) world position of a point light near the camera, `offset_camera` in camera axes (x right, y down)."""
    rotation = w2c[:3, :3]
    center = -rotation.T @ w2c[:3, 3]
    return center + rotation.T @ np.asarray(offset_camera, dtype=np.float64)


def lambert_shading(
    albedo: np.ndarray,
    normals: np.ndarray,
    x_world: np.ndarray,
    light: np.ndarray,
    *,
    ambient: float = 0.4,
) -> np.ndarray:
    """Ambient + Lambert diffuse: albedo * (ambient + (1 - ambient) * max(n . l, 0)).

    Args:
        albedo: (P, 3) RGB in [0, 1]; normals: (P, 3) unit surface normals; x_world: (P, 3).
        light: (3,) point-light position.
    Returns:
        (P, 3) shaded RGB.
    """
    to_light = light[None, :] - x_world
    to_light /= np.maximum(np.linalg.norm(to_light, axis=1, keepdims=True), 1e-12)
    diffuse = np.clip((normals * to_light).sum(axis=1), 0.0, 1.0)
    return albedo * (ambient + (1.0 - ambient) * diffuse)[:, None]


def yaw_about_vertical(
    local_rotations: torch.Tensor, root_translation: torch.Tensor, yaw: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Turn a whole pose sequence by `yaw` radians about the vertical (+Z) axis through the rest root.

    With G_root = [R_root | rest_root + t], rotating the world by Rz about that axis gives
    R_root' = Rz R_root and t' = Rz t; the other joints' local rotations are unchanged.

    Args:
        local_rotations: (N, J, 3, 3); root_translation: (N, 3).
    Returns:
        the turned (local_rotations, root_translation), same dtype and device.
    """
    like = local_rotations
    rz = axis_angle_to_matrix(torch.tensor([0.0, 0.0, float(yaw)], dtype=like.dtype, device=like.device))
    rotations = local_rotations.clone()
    rotations[:, 0] = rz @ local_rotations[:, 0]
    return rotations, root_translation @ rz.T
