"""Where the colour loss may shape the surface through the compositing weights: near the mask's outline.

    band = outline_band(mask_hw, width_px=4)                  # (H, W) bool
    scale = weights_gradient_scale(band, pixels_xy, 0.0)      # (R,) 1 on the band, 0.0 elsewhere

The colour loss's gradient through the volume-rendering weights helps where the images shape the
silhouette (a loose garment's edge, the gap between the legs), and carves where a bold pattern lies
inside it: a dark stripe is explained by tilting the surface instead of by colour (issue 36).
Passing it in full only on a thin band around the outline keeps the first and drops the second
(docs/RESEARCH.md, "the colour's pull through the weights only at the outline").
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def outline_band(mask_hw: torch.Tensor, width_px: int) -> torch.Tensor:
    """(H, W) bool: the pixels within `width_px` (Chebyshev distance) of the mask's outline, on both
    sides: the mask dilated minus the mask eroded by a (2 width_px + 1)^2 square.

    The image's border is not an outline: a mask cut by the frame edge is not eroded there.

    Args:
        mask_hw: (H, W) the person's mask (bool, or numbers where > 0.5 is the person).
        width_px: half-width of the band in pixels, >= 1.
    """
    if width_px < 1:
        raise ValueError(f"outline band width {width_px}: expected >= 1 pixel")
    person = (mask_hw.float() > 0.5).float()[None, None]
    size = 2 * width_px + 1
    # max_pool2d pads with -inf, so neither pooling sees the outside of the image as person or background.
    dilated = F.max_pool2d(person, size, stride=1, padding=width_px)
    eroded = -F.max_pool2d(-person, size, stride=1, padding=width_px)
    return (dilated - eroded)[0, 0] > 0.5


def weights_gradient_scale(band_hw: torch.Tensor, pixels_xy: torch.Tensor, inside: float) -> torch.Tensor:
    """(R,) float32: 1 for the rays whose pixel lies on the band, `inside` for the others.

    Args:
        band_hw: (H, W) bool, from `outline_band`.
        pixels_xy: (R, 2) integer pixel coordinates (x, y) of the rays.
        inside: the scale away from the outline, in [0, 1].
    """
    on_band = band_hw[pixels_xy[:, 1].long(), pixels_xy[:, 0].long()]
    return torch.where(on_band, torch.tensor(1.0), torch.tensor(float(inside)))
