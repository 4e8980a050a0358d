"""The masks' visual hull carried into canonical space, and the free-space bound it gives the SDF.

    hull = canonical_visual_hull(deformer, data, box, cell_size=0.015)
    free = hull.free_distance(x_canonical)        # (P,) meters; 0 where the hull does not rule x out
    loss = free_space_loss(sdf_at_x, free)        # hinge: sdf(x) >= distance to the hull

Canonical space that no training ray reaches through root finding is otherwise never constrained
(between the thighs of a wide-legged canonical pose, beyond the hands), and training rays alone
let a thin limb fade (see METHOD notes in docs/DESIGN.md). Forward skinning needs no root finding: every
canonical grid point is pushed into every training frame by LBS and projected into its mask. A
point that a robust number of views see as background is free space. Since the subject lies inside
every mask, its surface lies inside the hull, so at a free point the true SDF is at least the
distance to the hull: a one-sided bound that carves webs and floaters but never pushes the surface
inside the silhouettes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from scipy import ndimage

from igavatar.capture.visual_hull import MaskViews, SkinFn, free_points, grid_points, grid_spacing, spread_views, vote_masks
from igavatar.model.deformer import FastSnarfDeformer
from igavatar.training.data import TrainingData


@dataclass(frozen=True)
class CanonicalHull:
    """Visual-hull votes on a canonical grid.

    Attributes:
        box_min, box_max: (3,) canonical box of the grid.
        seen: (D, H, W) int32 training views in which each cell center projects into the image.
        inside: (D, H, W) int32 views in which it falls inside the (slightly dilated) mask.
        free: (D, H, W) bool cells that at least `min_outside` views see as background.
        free_distance_grid: (D, H, W) float32 meters from each free cell to the nearest non-free
            cell (0 for non-free cells): a lower bound of the true SDF there.
    Index order D<->z, H<->y, W<->x (as the skinning grid and `grid_sample`).
    """

    box_min: torch.Tensor
    box_max: torch.Tensor
    seen: torch.Tensor
    inside: torch.Tensor
    free: torch.Tensor
    free_distance_grid: torch.Tensor

    @property
    def occupied_fraction(self) -> float:
        """Share of the box the hull keeps (not free)."""
        return float((~self.free).float().mean())

    def free_distance(self, x_canonical: torch.Tensor) -> torch.Tensor:
        """(P, 3) canonical points -> (P,) lower bound of the SDF (meters; 0 = no bound).

        Trilinear in the grid of distances; points outside the box get 0 (unconstrained).
        """
        grid = self.free_distance_grid.to(x_canonical.device)
        lo, hi = self.box_min.to(x_canonical), self.box_max.to(x_canonical)
        normalized = (x_canonical - lo) / (hi - lo) * 2.0 - 1.0
        value = F.grid_sample(
            grid[None, None], normalized[None, None, None], mode="bilinear", padding_mode="zeros", align_corners=True
        )
        return value.reshape(-1)


@torch.no_grad()
def canonical_visual_hull(
    deformer: FastSnarfDeformer,
    data: TrainingData,
    box: torch.Tensor,
    cell_size: float = 0.015,
    max_views: int = 64,
    mask_dilation_px: int = 2,
    min_outside_fraction: float = 0.1,
    min_outside: int = 2,
    chunk_size: int = 262144,
) -> CanonicalHull:
    """Vote every canonical grid point in or out of the training frames' masks.

    Args:
        deformer: the avatar's deformer (forward LBS through its skinning grid).
        data: training frames (masks, cameras, bone transforms); only `train_indices` vote.
        box: (2, 3) canonical box of the grid (the SDF's box).
        cell_size: grid spacing in meters.
        max_views: at most this many training frames vote (evenly spaced), which bounds the cost.
        mask_dilation_px, min_outside_fraction, min_outside, chunk_size: see
            igavatar.capture.visual_hull.vote_masks and free_points.
    Returns:
        CanonicalHull on the CPU.
    """
    box = box.detach().float().cpu()
    points, shape = grid_points(box[0], box[1], cell_size)
    votes = vote_masks(points, training_skin(deformer, data), voting_views(data, max_views), mask_dilation_px, chunk_size)
    seen, inside = votes.seen, votes.inside
    free = free_points(seen, inside, min_outside_fraction, min_outside).reshape(shape)
    # Distance from each free cell to the nearest kept one: the SDF there is at least this much
    # (the surface is inside the hull). Anisotropic spacing: the grid's cells need not be cubes.
    distance = ndimage.distance_transform_edt(free.numpy(), sampling=grid_spacing(box[0], box[1], shape)).astype(np.float32)
    return CanonicalHull(
        box_min=box[0].clone(), box_max=box[1].clone(),
        seen=seen.reshape(shape), inside=inside.reshape(shape), free=free,
        free_distance_grid=torch.from_numpy(distance),
    )


def voting_views(data: TrainingData, max_views: int = 64) -> MaskViews:
    """The training frames that vote on canonical points: at most `max_views`, evenly spaced."""
    frames = spread_views(data.train_indices.tolist(), max_views)
    return MaskViews(masks=[data.masks[i].numpy() for i in frames], K=data.K[frames].numpy(),
                     w2c=data.w2c[frames].numpy(), frames=frames)


def training_skin(deformer: FastSnarfDeformer, data: TrainingData) -> SkinFn:
    """Forward LBS of canonical points into training frame `index`'s world space, through the
    deformer's skinning grid (no root finding); a frame's preparation is kept for its chunks."""
    device = deformer.weights_grid.device
    prepared: dict[int, object] = {}

    def skin(index: int, x_canonical: torch.Tensor) -> torch.Tensor:
        if index not in prepared:
            prepared.clear()
            prepared[index] = deformer.prepare(data.bone_transforms[index].to(device))
        return deformer.forward_skinning(x_canonical.to(device), prepared[index])

    return skin


def free_space_loss(sdf: torch.Tensor, free_distance: torch.Tensor, slack: float = 0.0) -> torch.Tensor:
    """Hinge on the hull's lower bound: mean of relu(free_distance - slack - sdf) over free points.

    Args:
        sdf: (P,) predicted signed distance at the points.
        free_distance: (P,) the hull's bound there (0 = unconstrained; such points are left out).
        slack: meters subtracted from the bound (tolerance for the grid's resolution).
    Returns:
        scalar tensor (0 when no point is constrained).
    """
    constrained = free_distance > slack
    if not bool(constrained.any()):
        return sdf.sum() * 0.0
    return torch.relu(free_distance[constrained] - slack - sdf[constrained]).mean()
