"""Training frames in memory, and the patch sampler that draws rays from them.

    data = TrainingData(images=..., masks=..., K=..., w2c=..., bone_transforms=..., ...)
    pixels = sample_patch_pixels(data.mask_pixels(i), data.masks.shape[1:], 4, 32, 0.9, generator)
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from igavatar.training.outline import outline_pixels


@dataclass(frozen=True)
class TrainingData:
    """Per-frame tensors of a dataset (CPU; images stay uint8 to save memory).

    Attributes:
        frame_names: N names.
        images: (N, H, W, 3) uint8 RGB.
        masks: (N, H, W) bool.
        K: (N, 3, 3); w2c: (N, 4, 4).
        bone_transforms: (N, J, 4, 4) canonical -> posed world.
        pose_condition: (N, pose_dim) non-rigid conditioning.
        posed_boxes: (N, 2, 3) padded world boxes of the posed subject.
        train_indices: (T,) long, frames used for training.
    """

    frame_names: list[str]
    images: torch.Tensor
    masks: torch.Tensor
    K: torch.Tensor
    w2c: torch.Tensor
    bone_transforms: torch.Tensor
    pose_condition: torch.Tensor
    posed_boxes: torch.Tensor
    train_indices: torch.Tensor
    _mask_pixels: dict = field(default_factory=dict, repr=False, compare=False)
    _edge_pixels: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def image_size(self) -> tuple[int, int]:
        return int(self.images.shape[1]), int(self.images.shape[2])

    def mask_pixels(self, index: int) -> torch.Tensor:
        """(M, 2) long (x, y) of the frame's mask pixels (computed once per frame)."""
        if index not in self._mask_pixels:
            ys, xs = torch.nonzero(self.masks[index], as_tuple=True)
            self._mask_pixels[index] = torch.stack((xs, ys), dim=-1)
        return self._mask_pixels[index]

    def edge_pixels(self, index: int) -> torch.Tensor:
        """(E, 2) long (x, y) of the frame's mask edge (igavatar.training.outline.outline_pixels; computed
        once per frame); the mask's own pixels when it has no edge in the image (all person)."""
        if index not in self._edge_pixels:
            edge = outline_pixels(self.masks[index])
            self._edge_pixels[index] = edge if edge.shape[0] > 0 else self.mask_pixels(index)
        return self._edge_pixels[index]


def sample_patch_pixels(
    mask_pixels: torch.Tensor,
    image_size: tuple[int, int],
    n_patches: int,
    patch_size: int,
    in_mask_fraction: float,
    generator: torch.Generator,
    steered_centres: torch.Tensor | None = None,
) -> torch.Tensor:
    """Pixels of `n_patches` square patches, most centerd on the subject.

    Args:
        mask_pixels: (M, 2) (x, y) of the subject's pixels (M >= 1).
        image_size: (H, W).
        n_patches, patch_size: patches and their edge in pixels.
        in_mask_fraction: share of patches centerd on a mask pixel; the others are centerd
            uniformly in the mask's bounding box grown by half its size (background context).
        generator: CPU RNG.
        steered_centres: (E, 2) centres chosen elsewhere (an error map's), taking E of the
            subject-centred patches' places; None or E = 0 draws them all uniformly.
    Returns:
        (n_patches * patch_size^2, 2) long pixel coordinates (x, y), patch by patch, row-major.
    """
    height, width = image_size
    size = min(patch_size, height, width)
    n_in = int(round(n_patches * in_mask_fraction))
    steered = 0 if steered_centres is None else min(int(steered_centres.shape[0]), n_in)
    centers = mask_pixels[torch.randint(0, mask_pixels.shape[0], (n_in - steered,), generator=generator)].float()
    if steered:
        centers = torch.cat((steered_centres[:steered].float(), centers))
    if n_patches > n_in:
        lo, hi = mask_pixels.amin(0).float(), mask_pixels.amax(0).float()
        grow = 0.5 * (hi - lo)
        lo, hi = lo - grow, hi + grow
        u = torch.rand((n_patches - n_in, 2), generator=generator)
        centers = torch.cat((centers, lo + u * (hi - lo)))
    limit = torch.tensor([width - size, height - size], dtype=torch.float32)
    top_left = (centers - size // 2).round().clamp(min=torch.zeros(2), max=limit).long()
    offsets = torch.stack(
        torch.meshgrid(torch.arange(size), torch.arange(size), indexing="xy"), dim=-1
    ).reshape(-1, 2)
    return (top_left[:, None, :] + offsets[None]).reshape(-1, 2)
