"""Rotation conversions (axis-angle <-> matrix <-> quaternion) and rigid 4x4 helpers, in torch.

    R = axis_angle_to_matrix(torch.tensor([0.0, 0.0, 1.5707963]))   # 90 degrees about +z
    rotvec = matrix_to_axis_angle(R)                                  # back to (3,)

Axis-angle vectors ("rotvecs") are what files hold; 3x3 matrices are what the library computes
with. Quaternions are (w, x, y, z) with w >= 0 where this module returns them. Every function
broadcasts over leading batch dimensions, keeps the input's dtype and device and is differentiable,
including at the zero rotation.
"""

from __future__ import annotations

import torch

# Below this angle (radians) the Rodrigues coefficients switch to their Taylor series: the closed
# forms lose all precision there (1 - cos is cancellation) and their autograd divides by zero.
_SMALL_ANGLE = 1e-3


def _skew(v: torch.Tensor) -> torch.Tensor:
    """Cross-product matrices [v]_x of vectors v (..., 3) -> (..., 3, 3)."""
    x, y, z = v.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack(
        (zero, -z, y, z, zero, -x, -y, x, zero), dim=-1
    ).reshape(v.shape[:-1] + (3, 3))


def axis_angle_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """Rotation matrices of axis-angle vectors (Rodrigues' formula).

    Args:
        rotvec: (..., 3) axis * angle in radians.
    Returns:
        (..., 3, 3) rotation matrices, exact to round-off for every angle and with finite
        gradients at the zero rotation (Taylor series below 1e-3 rad).
    """
    theta_sq = (rotvec * rotvec).sum(-1)
    small = theta_sq < _SMALL_ANGLE**2
    # Substitute a harmless angle where the closed form is not used so that the unused branch of
    # torch.where neither produces nor back-propagates NaNs.
    theta_sq_safe = torch.where(small, torch.ones_like(theta_sq), theta_sq)
    theta_safe = theta_sq_safe.sqrt()
    sin_over_theta = torch.where(
        small,
        1.0 - theta_sq / 6.0 + theta_sq * theta_sq / 120.0,
        torch.sin(theta_safe) / theta_safe,
    )
    one_minus_cos_over_theta_sq = torch.where(
        small,
        0.5 - theta_sq / 24.0 + theta_sq * theta_sq / 720.0,
        (1.0 - torch.cos(theta_safe)) / theta_sq_safe,
    )
    k = _skew(rotvec)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device)
    return (
        eye
        + sin_over_theta[..., None, None] * k
        + one_minus_cos_over_theta_sq[..., None, None] * (k @ k)
    )


def matrix_to_quaternion(matrix: torch.Tensor) -> torch.Tensor:
    """Unit quaternions (w, x, y, z), w >= 0, of rotation matrices.

    Shepperd's method: of the four algebraically equal formulas the one dividing by the largest of
    4w^2, 4x^2, 4y^2, 4z^2 is used per matrix, so 180-degree rotations stay accurate.

    Args:
        matrix: (..., 3, 3) rotation matrices.
    Returns:
        (..., 4) unit quaternions with a non-negative scalar part.
    """
    m = matrix
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    # 4 * (w^2, x^2, y^2, z^2), each from the trace and one diagonal entry.
    four_sq = torch.stack(
        (1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22),
        dim=-1,
    )
    # The off-diagonal sums and differences; candidate i is row i of this table divided by
    # 2 * sqrt(four_sq[i]) (i.e. by 4 * |q_i|).
    d21, d02, d10 = m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]
    s10, s02, s21 = m[..., 1, 0] + m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 2, 1] + m[..., 1, 2]
    table = torch.stack(
        (
            torch.stack((four_sq[..., 0], d21, d02, d10), -1),
            torch.stack((d21, four_sq[..., 1], s10, s02), -1),
            torch.stack((d02, s10, four_sq[..., 2], s21), -1),
            torch.stack((d10, s02, s21, four_sq[..., 3]), -1),
        ),
        dim=-2,
    )
    best = four_sq.argmax(dim=-1)
    row = torch.gather(table, -2, best[..., None, None].expand(best.shape + (1, 4))).squeeze(-2)
    denominator = 2.0 * torch.gather(four_sq, -1, best[..., None]).clamp_min(1e-12).sqrt()
    q = row / denominator
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def quaternion_to_axis_angle(quaternion: torch.Tensor) -> torch.Tensor:
    """Axis-angle vectors of unit quaternions (w, x, y, z); angles returned in [0, pi].

    Args:
        quaternion: (..., 4) unit quaternions (either sign).
    Returns:
        (..., 3) rotation vectors.
    """
    # q and -q are the same rotation; the one with w >= 0 gives the angle in [0, pi].
    q = torch.where(quaternion[..., :1] < 0, -quaternion, quaternion)
    xyz = q[..., 1:]
    sin_half_sq = (xyz * xyz).sum(-1)
    small = sin_half_sq < _SMALL_ANGLE**2
    sin_half = torch.where(small, torch.ones_like(sin_half_sq), sin_half_sq).sqrt()
    half_angle = torch.atan2(sin_half, q[..., 0])
    # angle / sin(angle/2) = 2 atan2(s, w) / s; near s = 0 its Taylor series is 2/w (1 - s^2/(3 w^2)).
    w = q[..., 0]
    scale = torch.where(
        small,
        2.0 / w * (1.0 - sin_half_sq / (3.0 * w * w)),
        2.0 * half_angle / sin_half,
    )
    return xyz * scale[..., None]


def matrix_to_axis_angle(matrix: torch.Tensor) -> torch.Tensor:
    """Axis-angle vectors of rotation matrices; angles in [0, pi].

    Args:
        matrix: (..., 3, 3) rotation matrices.
    Returns:
        (..., 3) rotation vectors (accurate near 0 and near pi, via the quaternion).
    """
    return quaternion_to_axis_angle(matrix_to_quaternion(matrix))


def rigid_matrix(rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """Homogeneous 4x4 matrices [R | t] from rotations (..., 3, 3) and translations (..., 3).

    The leading dimensions of the two inputs broadcast against each other.
    """
    batch = torch.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    top = torch.cat(
        (rotation.expand(batch + (3, 3)), translation.expand(batch + (3,))[..., None]), dim=-1
    )
    bottom = torch.zeros(batch + (1, 4), dtype=rotation.dtype, device=rotation.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat((top, bottom), dim=-2)


def invert_rigid(transform: torch.Tensor) -> torch.Tensor:
    """Inverses of rigid 4x4 transforms (..., 4, 4): [R^T | -R^T t] (exact, no matrix solve)."""
    rotation_t = transform[..., :3, :3].transpose(-1, -2)
    translation = -(rotation_t @ transform[..., :3, 3:4])[..., 0]
    return rigid_matrix(rotation_t, translation)


