"""Occupancy grid for empty-space skipping, over a box that may change every frame.

    grid = OccupancyGrid(box_min, box_max, resolution=64)
    grid.update(density_fn, box_min=posed_min, box_max=posed_max)   # every 16 training steps

The grid stores, per cell, a decayed running maximum of the density seen at jittered points in
the cell (``cached``) and a boolean ``occupied`` field derived from it (METHOD.md section 3, as
in the released InstantAvatar/InstantGeoAvatar code):

    cached   <- max(decay * cached, sigma(jittered point in the cell))      decay = 0.8
    occ      = 1 - exp(-0.01 * cached)            (opacity of a 1 cm step through the cell)
    occ      = max_pool3d(occ, 3x3x3, stride 1)   (dilate by one cell so thin parts survive)
    occupied = occ > min(mean(occ), 0.01)         (mean over the pooled field, all cells)

``density_fn`` is any callable ``x (P, 3) -> sigma (P,)`` in the grid's frame (for a posed grid it
warps the points to canonical space itself). It is evaluated in chunks under ``torch.no_grad()``;
a density function that needs autograd internally (e.g. analytic gradients) must re-enable it.

The box is an argument of :meth:`update` and :meth:`rebuild`, never frozen to the first frame.
When it changes, the cached densities are resampled (trilinearly, zero outside the old box) from
the old box onto the new one so the running maximum keeps its meaning in space, not in cell index.
Layout follows docs/DESIGN.md: fields are (D, H, W) with D <-> z, H <-> y, W <-> x.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from igavatar.geometry.boxes import check_box

__all__ = ["DensityFn", "OccupancyGrid", "max_filter_3d"]

DensityFn = Callable[[Tensor], Tensor]
"""x (P, 3) -> sigma (P,) non-negative density, in the grid's frame."""


def max_filter_3d(values: Tensor, radius: int = 1) -> Tensor:
    """Maximum over the (2 radius + 1)^3 cube around every cell, cells outside ignored.

    Equal to ``F.max_pool3d(values[None, None], 2 r + 1, stride=1, padding=r)[0, 0]`` (its
    reference), computed as three 1-D passes of shifted maxima: O(r) per cell and axis instead of
    the pool's (2r + 1)^3 window, ~10x faster on a 64^3 grid on CPU.

    Args:
        values: (D, H, W) float or bool.
        radius: cells on each side (0: unchanged).
    Returns:
        (D, H, W) of the same dtype.
    """
    if radius <= 0:
        return values
    out = values
    for axis in range(3):
        size = out.shape[axis]
        result = out.clone()
        for shift in range(1, min(radius, size - 1) + 1):
            # result[i] = max(result[i], out[i + shift]) and max(..., out[i - shift]) along the axis.
            ahead = result.narrow(axis, 0, size - shift)
            torch.maximum(ahead, out.narrow(axis, shift, size - shift), out=ahead)
            behind = result.narrow(axis, shift, size - shift)
            torch.maximum(behind, out.narrow(axis, 0, size - shift), out=behind)
        out = result
    return out


class OccupancyGrid(nn.Module):
    """A resolution^3 occupancy grid over an axis-aligned box (buffers move with ``.to()``).

    Args:
        box_min, box_max: (3,) initial box; every cell starts occupied, so nothing is skipped
            before the first :meth:`update` / :meth:`rebuild`.
        resolution: cells per axis (official 64).
        decay: factor applied to the cached density at each update (official 0.8).
        density_scale: the 0.01 in ``1 - exp(-0.01 * cached)``.
        threshold_cap: upper bound of the adaptive threshold ``min(mean(occ), 0.01)``.
        chunk_size: points per density_fn call.
    """

    cached: Tensor
    occupied: Tensor
    box_min: Tensor
    box_max: Tensor

    def __init__(
        self,
        box_min: Tensor,
        box_max: Tensor,
        resolution: int = 64,
        decay: float = 0.8,
        density_scale: float = 0.01,
        threshold_cap: float = 0.01,
        chunk_size: int = 65536,
    ) -> None:
        super().__init__()
        box_min = torch.as_tensor(box_min, dtype=torch.float32)
        box_max = torch.as_tensor(box_max, dtype=torch.float32).to(box_min.device)
        check_box(box_min, box_max, "OccupancyGrid", ValueError)
        if resolution < 1:
            raise ValueError(f"OccupancyGrid: resolution must be >= 1, got {resolution}")
        if not 0.0 <= decay <= 1.0:
            raise ValueError(f"OccupancyGrid: decay must be in [0, 1], got {decay}")
        self.resolution = int(resolution)
        self.decay = float(decay)
        self.density_scale = float(density_scale)
        self.threshold_cap = float(threshold_cap)
        self.chunk_size = int(chunk_size)
        shape = (self.resolution,) * 3
        self.register_buffer("box_min", box_min.clone())
        self.register_buffer("box_max", box_max.clone())
        self.register_buffer("cached", torch.zeros(shape, device=box_min.device))
        self.register_buffer("occupied", torch.ones(shape, dtype=torch.bool, device=box_min.device))

    # ------------------------------------------------------------------ queries
    @property
    def occupied_fraction(self) -> float:
        """Fraction of cells marked occupied (for logging)."""
        return float(self.occupied.float().mean())

    def cell_size(self) -> Tensor:
        """(3,) edge lengths of one cell (x, y, z)."""
        return (self.box_max - self.box_min) / self.resolution

    def cell_indices(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Cell of each point.

        Args:
            x: (P, 3) points in the grid's frame.

        Returns:
            ijk (P, 3) long ``(ix, iy, iz)`` clamped to the grid, and inside (P,) bool (point in
            the box, faces included).
        """
        rel = (x - self.box_min) / (self.box_max - self.box_min)
        inside = ((rel >= 0) & (rel <= 1)).all(dim=-1)
        ijk = (rel * self.resolution).floor().long().clamp(0, self.resolution - 1)
        return ijk, inside

    def is_occupied(self, x: Tensor) -> Tensor:
        """Whether each point lies in an occupied cell (points outside the box are free).

        Args:
            x: (P, 3) points in the grid's frame.

        Returns:
            (P,) bool.
        """
        if x.ndim != 2 or x.shape[-1] != 3:
            raise ValueError(f"OccupancyGrid.is_occupied: x has shape {tuple(x.shape)}, expected (P, 3)")
        ijk, inside = self.cell_indices(x.to(self.box_min))
        occ = self.occupied[ijk[:, 2], ijk[:, 1], ijk[:, 0]]
        return occ & inside

    def cell_centers(self) -> Tensor:
        """(D, H, W, 3) world-frame centers of all cells, ``[iz, iy, ix] -> (x, y, z)``."""
        return self._cell_points(torch.full((1, 1, 1, 3), 0.5, device=self.box_min.device))

    # ------------------------------------------------------------------ updates
    @torch.no_grad()
    def update(
        self,
        density_fn: DensityFn,
        box_min: Tensor | None = None,
        box_max: Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> None:
        """One training refresh: decay, take the max with fresh jittered densities, re-binarise.

        Args:
            density_fn: x (P, 3) -> sigma (P,), in the frame of the (new) box.
            box_min, box_max: (3,) box of this frame (e.g. the posed body's padded bounds); when
                given and different from the current box, the cache is resampled onto it first.
            generator: RNG for the jitter (on the grid's device); None uses the global RNG.
        """
        if (box_min is None) != (box_max is None):
            raise ValueError("OccupancyGrid.update: give both box_min and box_max, or neither")
        if box_min is not None and box_max is not None:
            self._move_box(box_min, box_max)
        density = self._jittered_density(density_fn, generator)
        self.cached.copy_(torch.maximum(self.cached * self.decay, density))
        self._binarise()

    @torch.no_grad()
    def rebuild(
        self,
        density_fn: DensityFn,
        box_min: Tensor,
        box_max: Tensor,
        num_passes: int = 5,
        generator: torch.Generator | None = None,
    ) -> None:
        """Test-time per-frame rebuild: reset the cache, fill it from ``num_passes`` jittered passes.

        The binarisation rule is the training one (``occ > min(mean, 0.01)`` after max-pool); the
        released code uses ``occ > 0`` here, which on a Laplace density (positive everywhere)
        marks nearly the whole box occupied and so skips little.

        Args:
            density_fn: x (P, 3) -> sigma (P,), in this frame.
            box_min, box_max: (3,) this frame's box.
            num_passes: jittered points per cell (official 5).
            generator: RNG for the jitter; None uses the global RNG.
        """
        if num_passes < 1:
            raise ValueError(f"OccupancyGrid.rebuild: num_passes must be >= 1, got {num_passes}")
        box_min = torch.as_tensor(box_min).to(self.box_min)
        box_max = torch.as_tensor(box_max).to(self.box_min)
        check_box(box_min, box_max, "OccupancyGrid.rebuild", ValueError)
        self.box_min.copy_(box_min)
        self.box_max.copy_(box_max)
        self.cached.zero_()
        for _ in range(num_passes):
            self.cached.copy_(torch.maximum(self.cached, self._jittered_density(density_fn, generator)))
        self._binarise()

    # ------------------------------------------------------------------ internals
    def _cell_points(self, offsets: Tensor) -> Tensor:
        """Points at ``offsets`` (D, H, W, 3) or broadcastable, in [0, 1) cell units, -> (D, H, W, 3)."""
        r = self.resolution
        idx = torch.arange(r, device=self.box_min.device, dtype=torch.float32)
        iz, iy, ix = torch.meshgrid(idx, idx, idx, indexing="ij")
        ijk = torch.stack([ix, iy, iz], dim=-1)  # (D, H, W, 3) in (x, y, z) order
        return self.box_min + (ijk + offsets) / r * (self.box_max - self.box_min)

    def _jittered_density(self, density_fn: DensityFn, generator: torch.Generator | None) -> Tensor:
        r = self.resolution
        offsets = torch.rand(
            (r, r, r, 3), generator=generator, device=self.box_min.device, dtype=torch.float32
        )
        points = self._cell_points(offsets).reshape(-1, 3)
        out = torch.empty(points.shape[0], device=points.device, dtype=torch.float32)
        for start in range(0, points.shape[0], self.chunk_size):
            chunk = points[start : start + self.chunk_size]
            sigma = density_fn(chunk)
            if sigma.shape != (chunk.shape[0],):
                raise ValueError(
                    f"OccupancyGrid: density_fn returned shape {tuple(sigma.shape)} for "
                    f"{chunk.shape[0]} points, expected ({chunk.shape[0]},)"
                )
            out[start : start + self.chunk_size] = sigma.detach().to(out.dtype)
        # Negative densities (e.g. from training noise) would make the decayed max meaningless.
        return out.clamp_min(0.0).reshape(r, r, r)

    def _binarise(self) -> None:
        occ = 1.0 - torch.exp(-self.density_scale * self.cached)
        occ = max_filter_3d(occ, 1)
        threshold = occ.mean().clamp(max=self.threshold_cap)
        self.occupied.copy_(occ > threshold)

    def _move_box(self, box_min: Tensor, box_max: Tensor) -> None:
        box_min = torch.as_tensor(box_min).to(self.box_min)
        box_max = torch.as_tensor(box_max).to(self.box_min)
        check_box(box_min, box_max, "OccupancyGrid.update", ValueError)
        if torch.equal(box_min, self.box_min) and torch.equal(box_max, self.box_max):
            return
        old_min, old_max = self.box_min.clone(), self.box_max.clone()
        self.box_min.copy_(box_min)
        self.box_max.copy_(box_max)
        centers = self.cell_centers()  # (D, H, W, 3) in the new box
        # grid_sample with align_corners=False maps -1/+1 to the outer faces of the old box,
        # i.e. cell centers of the old grid sit where its cached values were measured.
        grid = (centers - old_min) / (old_max - old_min) * 2.0 - 1.0
        resampled = F.grid_sample(
            self.cached[None, None],
            grid[None],
            mode="bilinear",
            padding_mode="zeros",
            align_corners=False,
        )[0, 0]
        self.cached.copy_(resampled)
