"""Stratified samples along rays, kept only in occupied space, in a padded (R, S) layout.

    samples = sample_along_rays(rays, num_samples=256, occupied_fn=grid.is_occupied, generator=g)
    out = render_rays(samples, field_fn, background)

Each ray's [near, far] is cut into ``num_samples`` equal bins. A sample is one bin: its interval
``[t_starts, t_ends]`` (whose length ``deltas`` enters alpha compositing) and a point ``t`` inside it
(uniformly jittered in training, the bin midpoint at eval); with equal bins the interval length
is the spacing of consecutive samples, the paper's delta_i. A sample is *valid* when the ray hits
its box (far > near) and the point lies in an occupied cell. With ``compact=True`` each ray's valid
samples are moved to the front (order along the ray kept) and S is truncated to the largest valid
count, so the padded layout wastes little compute while consecutive valid samples stay adjacent,
as the along-ray smoothness loss (paper Eq. 9) needs.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from igavatar.render.rays import RayBundle

__all__ = ["OccupiedFn", "RaySamples", "compact_samples", "sample_along_rays"]

OccupiedFn = Callable[[Tensor], Tensor]
"""x (P, 3) -> (P,) bool, True where the point may hold density (e.g. OccupancyGrid.is_occupied)."""


@dataclass(frozen=True)
class RaySamples:
    """Samples of R rays in a padded layout with S slots per ray.

    Attributes:
        positions: (R, S, 3) sample points ``o + t * d`` (meaningless where not valid).
        t: (R, S) distance of the point along its ray.
        t_starts, t_ends: (R, S) the interval the sample stands for; ``deltas = t_ends - t_starts``.
        valid: (R, S) bool; invalid slots must contribute nothing. Valid samples of a ray are
            sorted by ``t``; after compaction they occupy the first slots of the row.
        directions: (R, 3) unit ray directions (for view-dependent fields).
    """

    positions: Tensor
    t: Tensor
    t_starts: Tensor
    t_ends: Tensor
    valid: Tensor
    directions: Tensor

    @property
    def deltas(self) -> Tensor:
        """(R, S) interval lengths, zero on invalid slots."""
        return torch.where(self.valid, self.t_ends - self.t_starts, torch.zeros_like(self.t))

    @property
    def num_valid(self) -> int:
        return int(self.valid.sum())

    def valid_positions(self) -> Tensor:
        """(M, 3) positions of the valid samples, row-major order (ray, then slot)."""
        return self.positions[self.valid]


def sample_along_rays(
    rays: RayBundle,
    num_samples: int,
    occupied_fn: OccupiedFn | None = None,
    *,
    stratified: bool = True,
    generator: torch.Generator | None = None,
    compact: bool = True,
) -> RaySamples:
    """Up to ``num_samples`` samples per ray between near and far, in occupied space only.

    Args:
        rays: R rays with near/far (far <= near: no samples).
        num_samples: S, bins per ray (official 256 in training).
        occupied_fn: x (P, 3) -> (P,) bool; None keeps every sample in [near, far].
        stratified: jitter each point uniformly inside its bin (training); False puts it at the
            bin midpoint (eval, deterministic).
        generator: RNG for the jitter, on the rays' device; makes stratified sampling repeatable.
        compact: move valid samples to the front of each row and truncate S to the max count.

    Returns:
        RaySamples with S = num_samples (or the max valid count, at least 1, when compacted).
    """
    if num_samples < 1:
        raise ValueError(f"sample_along_rays: num_samples must be >= 1, got {num_samples}")
    near, far = rays.near, rays.far
    r = rays.num_rays
    device, dtype = near.device, near.dtype
    span = (far - near).clamp_min(0.0)
    edges = torch.linspace(0.0, 1.0, num_samples + 1, device=device, dtype=dtype)
    t_starts = near[:, None] + span[:, None] * edges[None, :-1]
    t_ends = near[:, None] + span[:, None] * edges[None, 1:]
    if stratified:
        u = torch.rand((r, num_samples), generator=generator, device=device, dtype=dtype)
    else:
        u = torch.full((r, num_samples), 0.5, device=device, dtype=dtype)
    t = t_starts + (t_ends - t_starts) * u
    positions = rays.origins[:, None, :] + t[..., None] * rays.directions[:, None, :]
    valid = (far > near)[:, None].expand(r, num_samples)
    if occupied_fn is not None:
        occ = occupied_fn(positions.reshape(-1, 3))
        if occ.shape != (r * num_samples,):
            raise ValueError(
                f"sample_along_rays: occupied_fn returned shape {tuple(occ.shape)}, "
                f"expected ({r * num_samples},)"
            )
        valid = valid & occ.reshape(r, num_samples).bool()
    samples = RaySamples(positions, t, t_starts, t_ends, valid.contiguous(), rays.directions)
    return compact_samples(samples) if compact else samples


def compact_samples(samples: RaySamples) -> RaySamples:
    """Move each row's valid samples to its front (keeping their order) and drop empty columns.

    Invalid slots are zero-filled. S becomes max(1, max valid count per ray) so downstream code
    never meets a zero-width tensor.
    """
    valid = samples.valid
    r, s = valid.shape
    counts = valid.sum(dim=1)
    s_new = max(1, int(counts.max())) if r > 0 else 1
    # Slot of each valid sample in its packed row = number of valid samples before it; invalid
    # samples are scattered into a spare column s_new that is cut off afterwards.
    dest = torch.where(valid, torch.cumsum(valid, dim=1) - 1, s_new)
    valid_new = torch.arange(s_new, device=valid.device)[None, :] < counts[:, None]

    def take(x: Tensor) -> Tensor:
        if x.ndim == 3:
            index = dest[..., None].expand(r, s, x.shape[-1])
            return x.new_zeros((r, s_new + 1, x.shape[-1])).scatter(1, index, x)[:, :s_new]
        return x.new_zeros((r, s_new + 1)).scatter(1, dest, x)[:, :s_new]

    return RaySamples(
        positions=take(samples.positions),
        t=take(samples.t),
        t_starts=take(samples.t_starts),
        t_ends=take(samples.t_ends),
        valid=valid_new,
        directions=samples.directions,
    )
