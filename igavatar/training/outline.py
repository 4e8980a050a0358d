"""Where the colour loss may shape the surface through the compositing weights: near the mask's outline.

    on_band = outline_rays(mask_hw, pixels_xy, width_px=4)    # (R,) bool, what training uses
    band = outline_band(mask_hw, width_px=4)                  # (H, W) bool, the plain reference
    scale = weights_gradient_scale(on_band, 0.0)              # (R,) 1 on the band, 0.0 elsewhere
    on_edge = texture_edge_rays(image_hw3, mask_hw, pixels_xy, 4, contrast=0.2)  # (R,) a pattern's edge
    scale = weights_gradient_scale(on_band, 0.3, on_edge)     # (R,) 1 on the band, 0 on an edge, 0.3 elsewhere
    edge_xy = outline_pixels(mask_hw)                         # (N, 2) the person's edge pixels, for patch centres

The colour loss's gradient through the volume-rendering weights helps where the images shape the
silhouette (a loose garment's edge, the gap between the legs), and carves where a bold pattern lies
inside it: a dark stripe is explained by tilting the surface instead of by colour (issue 36).
Passing it in full only on a thin band around the outline keeps the first and drops the second
(docs/RESEARCH.md, "the colour's pull through the weights only at the outline"). Inside the outline
a pattern carves only where its colour changes (in a flat stripe moving the surface changes no
colour), so the rays whose window on the person spans a luminance contrast above a threshold can
pass none of it, while the plain cloth and skin keep theirs (`texture_edge_rays`).
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


def _ray_windows(pixels_xy: torch.Tensor, width_px: int, height: int, width: int
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each ray's (2 width_px + 1)^2 window: row indices (R, K, 1) and column indices (R, 1, K),
    clamped into the image so that they index it, and (R, K * K) bool, whether each cell lies in it."""
    offsets = torch.arange(-width_px, width_px + 1)
    xs = pixels_xy[:, 0].long()[:, None, None] + offsets[None, None, :]     # (R, 1, K)
    ys = pixels_xy[:, 1].long()[:, None, None] + offsets[None, :, None]     # (R, K, 1)
    in_image = ((xs >= 0) & (xs < width) & (ys >= 0) & (ys < height)).flatten(1)
    return ys.clamp(0, height - 1), xs.clamp(0, width - 1), in_image


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
    ys, xs, in_image = _ray_windows(pixels_xy, width_px, *mask_hw.shape)
    values = mask_hw[ys, xs].flatten(1)   # (R, K * K)
    person = values if values.dtype == torch.bool else values.float() > 0.5
    return (person & in_image).any(dim=1) & (~person & in_image).any(dim=1)


#: Rec. 601 luma weights of (R, G, B), for the contrast of a pattern's edge.
LUMA_RGB = (0.299, 0.587, 0.114)


def texture_edge_rays(image_hw3: torch.Tensor, mask_hw: torch.Tensor, pixels_xy: torch.Tensor, width_px: int,
                      contrast: float) -> torch.Tensor:
    """(R,) bool: whether each ray's (2 width_px + 1)^2 window, clipped to the image, spans a luma
    range above `contrast` over the person's pixels in it (a stripe's or a checker's edge, a logo,
    the eyes); the background in the window is left out, so the outline itself is no edge.

    Args:
        image_hw3: (H, W, 3) RGB, uint8 (0-255) or float in [0, 1].
        mask_hw: (H, W) the person's mask (bool, or numbers where > 0.5 is the person).
        pixels_xy: (R, 2) integer pixel coordinates (x, y) of the rays.
        width_px: half-width of the window in pixels, >= 1.
        contrast: luma range in (0, 1].
    """
    if width_px < 1:
        raise ValueError(f"texture edge window {width_px}: expected >= 1 pixel")
    if not 0.0 < contrast <= 1.0:
        raise ValueError(f"texture edge contrast {contrast}: expected a luma range in (0, 1]")
    height, width = mask_hw.shape
    if tuple(image_hw3.shape) != (height, width, 3):
        raise ValueError(f"texture edges: image of shape {tuple(image_hw3.shape)}, expected ({height}, {width}, 3) "
                         "like its mask")
    ys, xs, in_image = _ray_windows(pixels_xy, width_px, height, width)
    values = mask_hw[ys, xs].flatten(1)                                      # (R, K * K)
    person = (values if values.dtype == torch.bool else values.float() > 0.5) & in_image
    scale = 1.0 / 255.0 if image_hw3.dtype == torch.uint8 else 1.0
    luma = (image_hw3[ys, xs].float() @ torch.tensor(LUMA_RGB)).flatten(1) * scale   # (R, K * K)
    high = torch.where(person, luma, torch.tensor(-1.0)).amax(dim=1)
    low = torch.where(person, luma, torch.tensor(2.0)).amin(dim=1)
    return person.any(dim=1) & (high - low > contrast)


def weights_gradient_scale(on_band: torch.Tensor, inside: float, on_edge: torch.Tensor | None = None) -> torch.Tensor:
    """(R,) float32: 1 for the rays on the band, 0 for the others on a pattern's edge, `inside` for the rest.

    Args:
        on_band: (R,) bool, from `outline_rays`.
        inside: the scale away from the outline, in [0, 1].
        on_edge: (R,) bool from `texture_edge_rays`, or None (no ray is on an edge).
    """
    scale = torch.where(on_band, torch.tensor(1.0), torch.tensor(float(inside)))
    if on_edge is not None:
        scale = torch.where(on_edge & ~on_band, torch.tensor(0.0), scale)
    return scale


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
