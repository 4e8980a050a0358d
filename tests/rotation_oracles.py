"""Rotation helpers the tests use as oracles for igavatar.body.rotations (the library has no use for them).

    torch.testing.assert_close(quaternion_to_matrix(axis_angle_to_quaternion(v)), axis_angle_to_matrix(v))
"""

from __future__ import annotations

import torch

from igavatar.body.rotations import _SMALL_ANGLE, matrix_to_axis_angle


def quaternion_to_matrix(quaternion: torch.Tensor) -> torch.Tensor:
    """Rotation matrices of quaternions (w, x, y, z), normalized first.

    Args:
        quaternion: (..., 4), any non-zero norm.
    Returns:
        (..., 3, 3) rotation matrices.
    """
    q = quaternion / quaternion.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        (
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ),
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def axis_angle_to_quaternion(rotvec: torch.Tensor) -> torch.Tensor:
    """Unit quaternions (w, x, y, z) of axis-angle vectors (..., 3) -> (..., 4)."""
    theta_sq = (rotvec * rotvec).sum(-1)
    small = theta_sq < _SMALL_ANGLE**2
    theta = torch.where(small, torch.ones_like(theta_sq), theta_sq).sqrt()
    sin_half_over_theta = torch.where(
        small, 0.5 - theta_sq / 48.0, torch.sin(0.5 * theta) / theta
    )
    cos_half = torch.where(small, 1.0 - theta_sq / 8.0, torch.cos(0.5 * theta))
    return torch.cat((cos_half[..., None], rotvec * sin_half_over_theta[..., None]), dim=-1)


def rotation_angle(matrix: torch.Tensor) -> torch.Tensor:
    """Rotation angles in [0, pi] of rotation matrices (..., 3, 3) -> (...,)."""
    return matrix_to_axis_angle(matrix).norm(dim=-1)


def transform_points(transform: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply 4x4 transforms (..., 4, 4) to points (..., 3) -> (..., 3), leading dims broadcast."""
    return (transform[..., :3, :3] @ points[..., None])[..., 0] + transform[..., :3, 3]
