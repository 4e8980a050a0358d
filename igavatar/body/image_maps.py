"""Per-frame image maps read at projected body points, shared by the fit's image terms.

    scale, size = shrunk_size(height, width, side=512)        # frame px per map px, (w, h) of the map
    grid = frame_px_grid(uv, scale, map_height, map_width)     # for grid_sample(..., align_corners=True)
    penalty = huber_px(distance_px, delta_px)

The silhouette's distance maps (igavatar.body.silhouette_fit) and the optical flow
(igavatar.body.flow_fit) are kept smaller than large frames and sampled, bilinearly and
differentiably, at the body's projected points given in the frame's pixels.
"""

from __future__ import annotations

import torch


def shrunk_size(height: int, width: int, side: int) -> tuple[float, tuple[int, int]]:
    """Frame px per map px (>= 1) and the map's (width, height) so that neither side exceeds `side`."""
    scale = max(1.0, max(height, width) / side)
    return scale, (max(1, round(width / scale)), max(1, round(height / scale)))


def frame_px_grid(uv: torch.Tensor, map_scale: float, map_height: int, map_width: int) -> torch.Tensor:
    """(..., 2) grid_sample coordinates in [-1, 1] of frame pixels uv (..., 2) on a map shrunk by
    map_scale. Pixel centres sit at integers in both; align_corners=True maps -1..1 onto 0..size-1."""
    map_uv = (uv + 0.5) / map_scale - 0.5
    return torch.stack((2 * map_uv[..., 0] / (map_width - 1) - 1, 2 * map_uv[..., 1] / (map_height - 1) - 1), dim=-1)


def huber_px(distance_px: torch.Tensor, delta_px: float) -> torch.Tensor:
    """Quadratic below delta_px, linear beyond, in px (slope 1 for large distances)."""
    return torch.where(distance_px < delta_px, 0.5 * distance_px**2 / delta_px, distance_px - 0.5 * delta_px)
