"""Where the colour loss may shape the surface through the compositing weights: near the mask's outline.

    on_band = outline_rays(mask_hw, pixels_xy, width_px=4)    # (R,) bool, what training uses
    band = outline_band(mask_hw, width_px=4)                  # (H, W) bool, the plain reference
    scale = weights_gradient_scale(on_band, 0.0)              # (R,) 1 on the band, 0.0 elsewhere
    edge_xy = outline_pixels(mask_hw)                         # (N, 2) the person's edge pixels, for patch centres

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


def outline_rays(mask_hw: torch.Tensor, pixels_xy: torch.Tensor, width_px: int) -> torch.Tensor:
    """(R,) bool: whether each ray's pixel lies on `outline_band(mask_hw, width_px)`: its
    (2 width_px + 1)^2 window, clipped to the image, holds both person and background. It reads
    only the rays' windows (R (2 width_px + 1)^2 pixels), not the whole frame: about 2 ms for 1024
    rays at width 4, where the two poolings over a 512 px frame take ~50-100 ms on 2 cores.

    Args:
        mask_hw: (H, W) the person's mask (bool, or numbers where > 0.5 is the person).
        pixels_xy: (R, 2) integer pixel coordinates (x, y) of the rays.
        width_px: half-width of the band in pixels, >= 1.
    """
    if width_px < 1:
        raise ValueError(f"outline band width {width_px}: expected >= 1 pixel")
    height, width = mask_hw.shape
    offsets = torch.arange(-width_px, width_px + 1)
    xs = pixels_xy[:, 0].long()[:, None, None] + offsets[None, None, :]     # (R, 1, K)
    ys = pixels_xy[:, 1].long()[:, None, None] + offsets[None, :, None]     # (R, K, 1)
    in_image = ((xs >= 0) & (xs < width) & (ys >= 0) & (ys < height)).flatten(1)
    values = mask_hw[ys.clamp(0, height - 1), xs.clamp(0, width - 1)].flatten(1)   # (R, K * K)
    person = values if values.dtype == torch.bool else values.float() > 0.5
    return (person & in_image).any(dim=1) & (~person & in_image).any(dim=1)


def weights_gradient_scale(on_band: torch.Tensor, inside: float) -> torch.Tensor:
    """(R,) float32: 1 for the rays on the band, `inside` for the others.

    Args:
        on_band: (R,) bool, from `outline_rays`.
        inside: the scale away from the outline, in [0, 1].
    """
    return torch.where(on_band, torch.tensor(1.0), torch.tensor(float(inside)))


def outline_pixels(mask_hw: torch.Tensor) -> torch.Tensor:
    """(N, 2) long (x, y): the person's pixels with a background pixel among their 8 neighbours (the
    mask's inner edge, `outline_band(mask_hw, 1)` within the mask), row by row. Patches centred on
    them straddle the outline, where most of the held-out image error lies
    (tests/benchmarks/results/image-error-regions.md).

    Args:
        mask_hw: (H, W) the person's mask (bool, or numbers where > 0.5 is the person).
    """
    person = mask_hw.float() > 0.5
    edge = outline_band(mask_hw, 1) & person
    ys, xs = torch.nonzero(edge, as_tuple=True)
    return torch.stack((xs, ys), dim=1).long()
