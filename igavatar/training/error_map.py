"""A running map of where the renders are wrong, to spend rays there (Instant-NGP's error map).

    errors = ErrorMap(n_frames, image_size_hw, cell_px=16)
    index = errors.draw_frame(train_indices, generator, share=0.5)          # a frame, by its error
    centres = errors.draw_centres(index, mask_pixels, n, generator)        # (n, 2) pixels, by error
    errors.record(index, pixels, per_ray_error)                            # after the step's render

Each frame's image is cut into square cells of `cell_px` pixels; a cell holds a running mean
(exponential, weight `rate` for each new batch) of the colour error of the rays rendered in it.
Cells start at `initial`, above any error a render makes, so that every cell is visited before
the map steers. Patch centres are drawn from the subject's pixels with probability proportional
to their cell's error plus `floor` times the frame's mean (some rays keep going everywhere); a
frame is drawn with probability proportional to its mean error, mixed with the uniform choice.
"""

from __future__ import annotations

import torch


class ErrorMap:
    """Per-frame error grids (N, H_cells, W_cells) float32, and the draws they steer.

    Args:
        n_frames: frames of the dataset (indexed as the dataset's frames).
        image_size: (H, W) pixels.
        cell_px: edge of a cell in pixels.
        rate: weight of a new batch in a cell's running mean.
        initial: a cell's value before any ray was rendered in it.
        floor: share of the frame's mean error every cell gets on top of its own.
    """

    def __init__(self, n_frames: int, image_size: tuple[int, int], cell_px: int = 16, rate: float = 0.3,
                 initial: float = 1.0, floor: float = 0.25) -> None:
        height, width = image_size
        self.cell_px = int(cell_px)
        self.shape = (-(-height // self.cell_px), -(-width // self.cell_px))
        self.cells = torch.full((n_frames, *self.shape), float(initial))
        self.rate, self.floor = float(rate), float(floor)
        self._cell_of: dict[int, torch.Tensor] = {}

    def _cell_index(self, pixels: torch.Tensor) -> torch.Tensor:
        """(P,) flat cell index of (P, 2) (x, y) pixels."""
        row = pixels[:, 1].long() // self.cell_px
        column = pixels[:, 0].long() // self.cell_px
        return row * self.shape[1] + column

    def pixel_weights(self, index: int, mask_pixels: torch.Tensor) -> torch.Tensor:
        """(M,) draw weights of the frame's subject pixels: cell error + floor x the frame's mean."""
        if index not in self._cell_of:
            self._cell_of[index] = self._cell_index(mask_pixels)
        flat = self.cells[index].reshape(-1)
        return flat[self._cell_of[index]] + self.floor * flat.mean()

    def draw_centres(self, index: int, mask_pixels: torch.Tensor, n: int, generator: torch.Generator) -> torch.Tensor:
        """(n, 2) patch centres among `mask_pixels` (M, 2) (x, y) of frame `index`, drawn by error."""
        if n == 0:
            return mask_pixels[:0].float()
        pick = torch.multinomial(self.pixel_weights(index, mask_pixels), n, replacement=True, generator=generator)
        return mask_pixels[pick].float()

    def draw_frame(self, frames: torch.Tensor, generator: torch.Generator, share: float) -> int:
        """One of `frames` (T,) dataset indices: by mean error with probability `share`, else uniformly."""
        if float(torch.rand((), generator=generator)) >= share:
            return int(frames[int(torch.randint(0, len(frames), (1,), generator=generator))])
        means = self.cells[frames].flatten(1).mean(dim=1)
        return int(frames[int(torch.multinomial(means, 1, generator=generator))])

    def record(self, index: int, pixels: torch.Tensor, errors: torch.Tensor) -> None:
        """Fold the step's per-ray errors (P,) at `pixels` (P, 2) (x, y) into frame `index`'s cells."""
        cells = self._cell_index(pixels.cpu())
        errors = errors.detach().float().cpu()
        total = torch.zeros(self.shape[0] * self.shape[1]).index_add_(0, cells, errors)
        count = torch.zeros_like(total).index_add_(0, cells, torch.ones_like(errors))
        seen = count > 0
        flat = self.cells[index].view(-1)
        flat[seen] = (1 - self.rate) * flat[seen] + self.rate * total[seen] / count[seen]

    def state_dict(self) -> dict:
        return {"cells": self.cells.clone()}

    def load_state_dict(self, state: dict) -> None:
        self.cells.copy_(state["cells"])
