"""Render the posed avatar from any camera: per-frame posed occupancy, root finding, volume rendering.

    image = render_avatar_view(avatar, canonical_grid, bone_transforms, pose, K, w2c, 256, 256, posed_box)
    image = render_posed_view(posed, canonical_grid, K, w2c, 256, 256, posed_box)   # a PosedAvatar
    image.rgb, image.opacity, image.depth, image.normal        # (H, W, ...) maps

Used by validation renders, `animate` and `eval`. The posed grid is rebuilt for each call from the
canonical one, so every frame (and every novel pose) skips its own empty space.
"""

from __future__ import annotations

import torch

from igavatar.model.avatar import Avatar
from igavatar.model.posed import PosedAvatar
from igavatar.render.occupancy import OccupancyGrid
from igavatar.render.volume import ImageRender, render_image


@torch.no_grad()
def render_posed_view(
    posed: PosedAvatar,
    canonical_grid: OccupancyGrid,
    K: torch.Tensor,
    w2c: torch.Tensor,
    height: int,
    width: int,
    posed_box: torch.Tensor,
    *,
    num_samples: int = 128,
    background: torch.Tensor | None = None,
    occupancy_resolution: int = 64,
    chunk_rays: int = 4096,
) -> ImageRender:
    """Render one view of a posed avatar (white background by default).

    Args:
        posed: the avatar in the frame; canonical_grid: its canonical occupancy grid.
        K (3, 3), w2c (4, 4): camera; height, width: image size.
        posed_box: (2, 3) world box that bounds the posed avatar.
    Returns:
        ImageRender with rgb/opacity/depth/normal maps (normals in canonical space).
    """
    posed_grid = posed.occupancy(canonical_grid, posed_box, occupancy_resolution)
    return render_image(
        K, w2c, height, width, posed.field_fn, posed_box[0], posed_box[1],
        occupied_fn=posed_grid.is_occupied, num_samples=num_samples, background=background,
        chunk_rays=chunk_rays,
    )


def render_avatar_view(
    avatar: Avatar,
    canonical_grid: OccupancyGrid,
    bone_transforms: torch.Tensor,
    pose_condition: torch.Tensor,
    K: torch.Tensor,
    w2c: torch.Tensor,
    height: int,
    width: int,
    posed_box: torch.Tensor,
    **settings,
) -> ImageRender:
    """render_posed_view of `avatar` posed by (J, 4, 4) bone transforms and (pose_dim,) conditioning."""
    return render_posed_view(PosedAvatar.of(avatar, bone_transforms, pose_condition), canonical_grid, K, w2c, height, width,
                             posed_box, **settings)
