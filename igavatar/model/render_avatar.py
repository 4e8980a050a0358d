"""Render the posed avatar from any camera: per-frame posed occupancy, root finding, volume rendering.

    image = render_avatar_view(avatar, canonical_grid, bone_transforms, pose, K, w2c, 256, 256, posed_box)
    image.rgb, image.opacity, image.depth, image.normal        # (H, W, ...) maps

Used by validation renders, `animate` and `eval`. The posed grid is rebuilt for each call from the
canonical one, so every frame (and every novel pose) skips its own empty space.
"""

from __future__ import annotations

import torch

from igavatar.model.avatar import Avatar
from igavatar.model.posed_occupancy import posed_occupancy
from igavatar.render.occupancy import OccupancyGrid
from igavatar.render.volume import FieldOutput, ImageRender, render_image


def posed_field_fn(avatar: Avatar, frame, pose: torch.Tensor):
    """A renderer field callable on posed points: root finding, then the canonical fields.

    Points with no valid canonical root are empty (density 0).
    """

    def field_fn(x_posed: torch.Tensor) -> FieldOutput:
        x_canonical, found = avatar.correspond(x_posed, frame, pose)
        out = avatar.field_at(x_canonical, pose)
        return FieldOutput(
            sigma=torch.where(found, out.sigma, 0.0), rgb=out.rgb, gradient=out.gradient, sdf=out.sdf
        )

    return field_fn


@torch.no_grad()
def render_avatar_view(
    avatar: Avatar,
    canonical_grid: OccupancyGrid,
    bone_transforms: torch.Tensor,
    pose: torch.Tensor,
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
    """Render one view of the avatar in one pose (white background by default).

    Args:
        avatar: the trained Avatar; canonical_grid: its canonical occupancy grid.
        bone_transforms: (J, 4, 4) canonical -> posed world; pose: (P,) conditioning.
        K (3, 3), w2c (4, 4): camera; height, width: image size.
        posed_box: (2, 3) world box that bounds the posed avatar.
    Returns:
        ImageRender with rgb/opacity/depth/normal maps (normals in canonical space).
    """
    frame = avatar.deformer.prepare(bone_transforms)
    posed_grid = posed_occupancy(canonical_grid, avatar.deformer, frame, posed_box, occupancy_resolution)
    return render_image(
        K, w2c, height, width, posed_field_fn(avatar, frame, pose), posed_box[0], posed_box[1],
        occupied_fn=posed_grid.is_occupied, num_samples=num_samples, background=background,
        chunk_rays=chunk_rays,
    )
