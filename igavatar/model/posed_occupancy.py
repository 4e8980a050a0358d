"""Per-frame posed occupancy by forward-skinning the canonical occupancy grid (no root finding).

    posed_grid = posed_occupancy(canonical_grid, deformer, frame, posed_box, resolution=64)
    samples = sample_along_rays(rays, 256, posed_grid.is_occupied)

The canonical grid is refreshed from the canonical density (cheap: no deformer). Each frame's posed
grid is then the set of posed cells reached by the centers of its occupied canonical cells pushed
through forward LBS, dilated by `dilation` cells: neighbouring canonical centers land about a cell
apart, so the dilation closes the gaps between them (and covers small non-rigid offsets). Rebuilding it is
a few milliseconds, so every frame (training or animation) gets its own, never the first one's.
"""

from __future__ import annotations

import torch

from igavatar.model.deformer import FastSnarfDeformer, PreparedFrame
from igavatar.render.occupancy import OccupancyGrid, max_filter_3d


@torch.no_grad()
def posed_occupancy(
    canonical_grid: OccupancyGrid,
    deformer: FastSnarfDeformer,
    frame: PreparedFrame,
    posed_box: torch.Tensor,
    resolution: int = 64,
    dilation: int = 1,
) -> OccupancyGrid:
    """A posed-space occupancy grid of one frame.

    Args:
        canonical_grid: the canonical OccupancyGrid (its `occupied` field is used).
        deformer: the avatar's deformer; frame: its PreparedFrame for this frame.
        posed_box: (2, 3) world box of the posed subject (padded).
        resolution: cells per axis of the posed grid.
        dilation: cells added around every reached cell (max-pool radius).
    Returns:
        an OccupancyGrid over posed_box whose `occupied` marks reachable cells.
    """
    device = canonical_grid.box_min.device
    posed = OccupancyGrid(posed_box[0].to(device), posed_box[1].to(device), resolution=resolution)
    occupied = canonical_grid.occupied
    iz, iy, ix = torch.nonzero(occupied, as_tuple=True)
    if iz.numel() == 0:
        posed.occupied.zero_()
        return posed
    cell = canonical_grid.cell_size()
    base = torch.stack((ix, iy, iz), dim=-1).to(cell.dtype)  # (C, 3) as (x, y, z) indices
    x_canonical = canonical_grid.box_min + (base + 0.5) * cell
    x_posed = deformer.forward_skinning(x_canonical, frame)
    ijk, inside = posed.cell_indices(x_posed.to(posed.box_min.dtype))
    ijk = ijk[inside]
    grid = torch.zeros_like(posed.occupied, dtype=torch.float32)
    grid[ijk[:, 2], ijk[:, 1], ijk[:, 0]] = 1.0
    grid = max_filter_3d(grid, dilation)
    posed.occupied.copy_(grid > 0)
    return posed
