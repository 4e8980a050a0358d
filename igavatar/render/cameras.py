"""Camera helpers: look-at extrinsics, turntable orbits, intrinsics that frame a box, resizing.

    K, w2c = turntable_cameras(box_min, box_max, n_frames=60, height=256, width=256, up=up, front=front)
    K_small = resize_intrinsics(K_dataset, (512, 512), (256, 256))

Conventions (docs/DESIGN.md): OpenCV cameras (x right, y down, z forward), ``w2c`` (4, 4)
world-to-camera, ``K`` (3, 3) in pixels with pixel centers at integer coordinates, so the image
center is ``((W - 1) / 2, (H - 1) / 2)``. Every function is device-agnostic and returns float32
tensors on the device of its first tensor argument (arithmetic is done in float64).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from igavatar.errors import InputError

__all__ = [
    "box_corners",
    "camera_centers",
    "fit_intrinsics",
    "look_at_w2c",
    "orbit_w2c",
    "resize_intrinsics",
    "turntable_cameras",
]


def _vector(value: Tensor | tuple[float, ...], like: Tensor | None = None) -> Tensor:
    tensor = torch.as_tensor(value, dtype=torch.float64, device=None if like is None else like.device)
    return tensor.to(torch.float64)


def look_at_w2c(eye: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """World-to-camera (4, 4) of OpenCV cameras at `eye` looking at `target`.

    The image's "down" is the component of -up orthogonal to the viewing direction, so a camera
    whose viewing direction is horizontal gives an upright, level image.

    Args:
        eye: (..., 3) camera centers; target: (..., 3) points looked at; up: (3,) world up.
    Returns:
        (..., 4, 4) float32 w2c.
    Raises:
        InputError: the viewing direction is zero or parallel to `up`.
    """
    eye64, target64 = _vector(eye), _vector(target, eye)
    up64 = _vector(up, eye)
    forward = target64 - eye64
    forward_norm = torch.linalg.vector_norm(forward, dim=-1, keepdim=True)
    if bool((forward_norm < 1e-9).any()):
        raise InputError("camera: the camera center coincides with the point it looks at")
    forward = forward / forward_norm
    right = torch.linalg.cross(forward, up64.expand_as(forward), dim=-1)
    right_norm = torch.linalg.vector_norm(right, dim=-1, keepdim=True)
    if bool((right_norm < 1e-9).any()):
        raise InputError("camera: the viewing direction is parallel to the up axis; move the camera")
    right = right / right_norm
    down = torch.linalg.cross(forward, right, dim=-1)
    rotation = torch.stack((right, down, forward), dim=-2)  # rows: camera axes in world coordinates
    w2c = torch.zeros((*rotation.shape[:-2], 4, 4), dtype=torch.float64, device=eye64.device)
    w2c[..., :3, :3] = rotation
    w2c[..., :3, 3] = -(rotation @ eye64[..., None])[..., 0]
    w2c[..., 3, 3] = 1.0
    return w2c.to(torch.float32)


def camera_centers(w2c: Tensor) -> Tensor:
    """World positions (..., 3) of the centers of cameras w2c (..., 4, 4): -R^T t."""
    rotation, translation = w2c[..., :3, :3], w2c[..., :3, 3:]
    return -(rotation.transpose(-1, -2) @ translation)[..., 0]


def orbit_w2c(
    center: Tensor,
    radius: float,
    azimuths: Tensor,
    *,
    up: Tensor,
    front: Tensor,
    elevation: float = 0.0,
) -> Tensor:
    """Cameras on a circle about the vertical through `center`, all looking at `center`.

    Azimuth 0 puts the camera on the `front` side (e.g. in front of the subject's face); positive
    azimuths turn it counter-clockwise seen from above (right-handed about `up`).

    Args:
        center: (3,) point looked at; radius: distance from the camera to `center` (meters).
        azimuths: (N,) angles in radians; elevation: angle above the horizontal plane (radians).
        up: (3,) world up; front: (3,) direction from `center` towards the camera at azimuth 0
            (its component along `up` is ignored).
    Returns:
        (N, 4, 4) float32 w2c.
    """
    if not radius > 0:
        raise InputError(f"camera orbit: radius = {radius}, expected a positive distance")
    center64 = _vector(center)
    up64 = _vector(up, center64)
    up64 = up64 / torch.linalg.vector_norm(up64)
    front64 = _vector(front, center64)
    front64 = front64 - (front64 @ up64) * up64
    if float(torch.linalg.vector_norm(front64)) < 1e-9:
        raise InputError("camera orbit: the front direction is parallel to the up axis")
    front64 = front64 / torch.linalg.vector_norm(front64)
    side64 = torch.linalg.cross(up64, front64, dim=-1)  # front rotated by +90 degrees about up
    angles = torch.as_tensor(azimuths, dtype=torch.float64, device=center64.device).reshape(-1, 1)
    horizontal = torch.cos(angles) * front64 + torch.sin(angles) * side64
    offset = radius * (math.cos(elevation) * horizontal + math.sin(elevation) * up64)
    return look_at_w2c(center64 + offset, center64.expand_as(offset), up64)


def box_corners(box_min: Tensor, box_max: Tensor) -> Tensor:
    """The 8 corners (8, 3) of an axis-aligned box (3,), (3,)."""
    low, high = _vector(box_min), _vector(box_max, box_min)
    bits = torch.tensor(
        [[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=torch.float64, device=low.device
    )
    return (low + bits * (high - low)).to(torch.float32)


def fit_intrinsics(
    x_world: Tensor, w2c: Tensor, height: int, width: int, *, margin: float = 0.05
) -> Tensor:
    """Intrinsics (3, 3) that keep every point inside every view, principal point at the center.

    The focal length (square pixels) is the largest one for which all points project at least
    `margin` x the image size away from the border in all views, so one K fits a whole sequence.

    Args:
        x_world: (P, 3) points seen by every view, or (N, P, 3) one set per view (e.g. the
            subject's points in each frame of an animation).
        w2c: (4, 4) or (N, 4, 4) cameras.
        height, width: image size in pixels; margin: free border on each side, fraction of size.
    Raises:
        InputError: a point lies behind or within 1 cm of a camera's image plane.
    """
    if not 0.0 <= margin < 0.5:
        raise InputError(f"camera framing: margin = {margin}, expected a fraction in [0, 0.5)")
    w2c64 = w2c.to(torch.float64).reshape(-1, 4, 4)
    x64 = x_world.to(device=w2c64.device, dtype=torch.float64)
    if x64.ndim == 3 and x64.shape[0] != w2c64.shape[0]:
        raise InputError(
            f"camera framing: {x64.shape[0]} point sets for {w2c64.shape[0]} cameras; give one per camera"
        )
    x64 = x64.reshape(-1 if x64.ndim == 3 else 1, x64.shape[-2], 3)
    tan_x = tan_y = 0.0
    for view in range(w2c64.shape[0]):  # one view at a time: N x P can be large
        points = x64[view if x64.shape[0] > 1 else 0]
        x_camera = points @ w2c64[view, :3, :3].T + w2c64[view, :3, 3]
        depth = x_camera[:, 2]
        if bool((depth < 0.01).any()):
            raise InputError(
                "camera framing: part of the subject is behind a camera or closer than 1 cm to it; "
                "move the camera further away"
            )
        tan_x = max(tan_x, float((x_camera[:, 0] / depth).abs().max()))
        tan_y = max(tan_y, float((x_camera[:, 1] / depth).abs().max()))
    focal = min((0.5 - margin) * width / max(tan_x, 1e-9), (0.5 - margin) * height / max(tan_y, 1e-9))
    return torch.tensor(
        [[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]],
        dtype=torch.float32, device=w2c.device,
    )


def turntable_cameras(
    box_min: Tensor,
    box_max: Tensor,
    n_frames: int,
    height: int,
    width: int,
    *,
    up: Tensor,
    front: Tensor,
    revolutions: float = 1.0,
    elevation: float = math.radians(10.0),
    distance_factor: float = 3.0,
    margin: float = 0.05,
    fit_points: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """An orbit around a box (e.g. the union of a sequence's posed boxes) with one K framing it.

    Frame i sees the box center from azimuth ``2 pi * revolutions * i / n_frames`` (0 = `front`),
    at `distance_factor` x the box's half diagonal; `revolutions` = 0 gives a static front camera.

    Args:
        box_min, box_max: (3,) world box to orbit around.
        n_frames: N cameras; height, width: image size; up, front: (3,) as in :func:`orbit_w2c`.
        elevation: camera height angle above the horizontal (radians); margin: see fit_intrinsics.
        fit_points: what K must keep in view, (P, 3) or (N, P, 3) per frame (see
            fit_intrinsics); None frames the box's corners in every view (looser: a box's near
            corners project larger than the body inside it).
    Returns:
        K (3, 3) and w2c (N, 4, 4), float32.
    """
    if n_frames < 1:
        raise InputError(f"turntable camera: n_frames = {n_frames}, expected >= 1")
    if not distance_factor > 1.0:
        raise InputError(f"turntable camera: distance_factor = {distance_factor}, expected > 1 (outside the box)")
    low, high = _vector(box_min), _vector(box_max, box_min)
    center = 0.5 * (low + high)
    half_diagonal = max(0.5 * float(torch.linalg.vector_norm(high - low)), 1e-3)
    azimuths = 2.0 * math.pi * revolutions * torch.arange(n_frames, dtype=torch.float64) / n_frames
    w2c = orbit_w2c(center, distance_factor * half_diagonal, azimuths, up=up, front=front, elevation=elevation)
    points = box_corners(low, high) if fit_points is None else fit_points
    K = fit_intrinsics(points, w2c, height, width, margin=margin)
    return K, w2c


def resize_intrinsics(K: Tensor, size_hw: tuple[int, int], new_size_hw: tuple[int, int]) -> Tensor:
    """Intrinsics (..., 3, 3) of the same camera rendering at `new_size_hw` instead of `size_hw`.

    Pixel centers sit at integer coordinates, so a center x maps to s * (x + 0.5) - 0.5.
    """
    (h, w), (new_h, new_w) = size_hw, new_size_hw
    sx, sy = new_w / w, new_h / h
    K = K.clone()
    K[..., 0, :] *= sx
    K[..., 1, :] *= sy
    K[..., 0, 2] += 0.5 * sx - 0.5
    K[..., 1, 2] += 0.5 * sy - 0.5
    return K
