"""Shading of the posed surface: the clip's light as a second-order spherical-harmonic function of
the world-space normal, multiplying the canonical colour (albedo).

    shading = WorldShading()                                   # (9, 3) coefficients, starts at 1
    n_world = posed_normals(frame.blended_grid, frame.box_min, frame.box_max, x_rigid, normal_canonical)
    rgb = albedo * shading(n_world)                            # (P, 3); n_world (P, 3) unit, world frame

Why: the canonical colour cannot change as a body part turns toward or away from a light, so a
person turning in a fixed light (a phone on a tripod, the synthetic captures' light beside the
camera) is averaged into a flat colour, and its held-out frames miss by the shading. Nine
coefficients a channel hold a distant light's diffuse shading to a few percent (Ramamoorthi and
Hanrahan 2001) and cannot hold texture, so the colour field keeps the pattern.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from igavatar.skinning.grid import sample_blended_transforms

#: Shading models: "none" (the paper: colour alone) or "sh9" (WorldShading).
SHADINGS: tuple[str, ...] = ("none", "sh9")


def sh9_basis(normal: torch.Tensor) -> torch.Tensor:
    """(P, 3) unit normals -> (P, 9) real spherical harmonics up to order 2 (unnormalized:
    1, x, y, z, xy, xz, yz, x^2 - y^2, 3z^2 - 1; the scale of each is the coefficient's)."""
    x, y, z = normal.unbind(dim=-1)
    return torch.stack([torch.ones_like(x), x, y, z, x * y, x * z, y * z, x * x - y * y, 3 * z * z - 1], dim=-1)


class WorldShading(nn.Module):
    """Per-channel shading factor of a world-space normal: max(0, sh9(n) @ coefficients).

    `coefficients` (9, 3) start at a constant 1 (no shading), so a model starts as the paper's.
    """

    def __init__(self) -> None:
        super().__init__()
        start = torch.zeros(9, 3)
        start[0] = 1.0
        self.coefficients = nn.Parameter(start)

    def forward(self, normal_world: torch.Tensor) -> torch.Tensor:
        """(P, 3) unit world normals -> (P, 3) non-negative factors."""
        return (sh9_basis(normal_world) @ self.coefficients.to(normal_world.dtype)).clamp_min(0.0)


def posed_normals(blended_grid: torch.Tensor, box_min: torch.Tensor, box_max: torch.Tensor,
                  x_rigid: torch.Tensor, normal_canonical: torch.Tensor) -> torch.Tensor:
    """World unit normals of the posed surface at rigid canonical points.

    Args:
        blended_grid, box_min, box_max: a PreparedFrame's blended transform grid and its box.
        x_rigid: (P, 3) rigid canonical correspondences (the skinning's input).
        normal_canonical: (P, 3) unit canonical normals.
    Returns:
        (P, 3): the inverse transpose of the blended linear part applied to each normal,
        normalized. The cofactor matrix is that inverse transpose times the determinant, whose
        positive scale the normalization removes, so a near-singular blend needs no inverse.
    """
    a = sample_blended_transforms(blended_grid, box_min, box_max, x_rigid.to(blended_grid.dtype))[:, :, :3]
    # Row i of the cofactor matrix is row i+1 x row i+2 of A; A^-1 has these rows as columns over
    # det(A), so A^-T n = cof(A) n / det(A).
    cofactor = torch.cross(a.roll(-1, dims=1), a.roll(-2, dims=1), dim=-1)
    world = (cofactor @ normal_canonical.to(a.dtype)[:, :, None])[:, :, 0]
    return F.normalize(world, dim=-1, eps=1e-12).to(normal_canonical.dtype)
