"""Camera rays in the world frame (OpenCV pinhole) and their near/far bounds from a box.

    origins, directions = pixel_rays(K, w2c, pixel_grid(H, W, device=K.device))
    rays = rays_in_box(origins, directions, box_min, box_max)   # RayBundle with near/far

Conventions (docs/DESIGN.md): OpenCV camera (x right, y down, z forward), ``K`` (3, 3) in pixels,
``w2c`` (4, 4) world-to-camera, pixel centers at integer coordinates (pixel (u, v) covers
[u - 0.5, u + 0.5]). Directions are unit length, so the ray parameter ``t`` is a distance in
meters, and ``near``/``far`` are distances along the ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["RayBundle", "pixel_grid", "pixel_rays", "ray_box_intersection", "rays_in_box"]


@dataclass(frozen=True)
class RayBundle:
    """R rays in one frame (world or root frame, as the caller chose).

    Attributes:
        origins: (R, 3) ray origins.
        directions: (R, 3) unit ray directions.
        near: (R,) distance along the ray where sampling starts.
        far: (R,) distance where sampling stops; ``far <= near`` marks a ray that gets no samples.
    """

    origins: Tensor
    directions: Tensor
    near: Tensor
    far: Tensor

    def __post_init__(self) -> None:
        r = self.origins.shape[0]
        if self.origins.shape != (r, 3) or self.directions.shape != (r, 3):
            raise ValueError(
                f"RayBundle: origins {tuple(self.origins.shape)} and directions "
                f"{tuple(self.directions.shape)} must both be (R, 3)"
            )
        if self.near.shape != (r,) or self.far.shape != (r,):
            raise ValueError(
                f"RayBundle: near {tuple(self.near.shape)} and far {tuple(self.far.shape)} "
                f"must both be ({r},)"
            )

    @property
    def num_rays(self) -> int:
        return int(self.origins.shape[0])

    def slice(self, start: int, stop: int) -> RayBundle:
        """Rays ``start:stop`` as a new bundle (views, no copy); used to render in chunks."""
        return RayBundle(
            self.origins[start:stop],
            self.directions[start:stop],
            self.near[start:stop],
            self.far[start:stop],
        )


def pixel_grid(height: int, width: int, device: torch.device | str | None = None) -> Tensor:
    """All pixel centers of an image, row-major.

    Returns:
        (H * W, 2) float32 ``(x, y)`` = (column, row); index ``y * W + x`` is pixel (x, y).
    """
    ys, xs = torch.meshgrid(
        torch.arange(height, device=device, dtype=torch.float32),
        torch.arange(width, device=device, dtype=torch.float32),
        indexing="ij",
    )
    return torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1)


def pixel_rays(K: Tensor, w2c: Tensor, pixels_xy: Tensor) -> tuple[Tensor, Tensor]:
    """Rays through pixel centers of an OpenCV pinhole camera, in the frame ``w2c`` maps from.

    Args:
        K: (3, 3) intrinsics in pixels.
        w2c: (4, 4) world-to-camera rigid transform.
        pixels_xy: (R, 2) float pixel coordinates ``(x, y)``; integer values are pixel centers.

    Returns:
        origins (R, 3) (all equal to the camera center) and unit directions (R, 3), world frame.
    """
    if K.shape != (3, 3):
        raise ValueError(f"pixel_rays: K has shape {tuple(K.shape)}, expected (3, 3)")
    if w2c.shape != (4, 4):
        raise ValueError(f"pixel_rays: w2c has shape {tuple(w2c.shape)}, expected (4, 4)")
    if pixels_xy.ndim != 2 or pixels_xy.shape[-1] != 2:
        raise ValueError(f"pixel_rays: pixels_xy has shape {tuple(pixels_xy.shape)}, expected (R, 2)")
    dtype = torch.promote_types(K.dtype, torch.float32)
    K = K.to(dtype)
    w2c = w2c.to(dtype)
    pixels_xy = pixels_xy.to(dtype)
    ones = torch.ones_like(pixels_xy[:, :1])
    # Back-project with K^-1 (solve, not an explicit inverse, for skewed K too).
    d_camera = torch.linalg.solve(K, torch.cat([pixels_xy, ones], dim=-1).T).T  # (R, 3), z = 1
    rot_w2c = w2c[:3, :3]
    trans_w2c = w2c[:3, 3]
    # c2w = [R^T | -R^T t]: camera center and rotated directions without inverting a 4x4.
    center_world = -rot_w2c.T @ trans_w2c
    d_world = d_camera @ rot_w2c  # row-vector form of R^T d
    directions = d_world / torch.linalg.vector_norm(d_world, dim=-1, keepdim=True)
    origins = center_world.expand_as(directions).contiguous()
    return origins, directions


def ray_box_intersection(
    origins: Tensor, directions: Tensor, box_min: Tensor, box_max: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Slab test of R rays against one axis-aligned box.

    Args:
        origins: (R, 3); directions: (R, 3) (need not be unit; t is in units of |direction|).
        box_min, box_max: (3,) box corners in the rays' frame.

    Returns:
        t_near (R,), t_far (R,), hit (R,) bool. ``t_near`` is clamped to >= 0 so a ray starting
        inside the box begins at its origin; ``hit`` is ``t_far > t_near`` (box ahead of the
        origin, non-empty overlap). Rays that miss get ``t_near = t_far = 0``.
    """
    if origins.shape != directions.shape or origins.ndim != 2 or origins.shape[-1] != 3:
        raise ValueError(
            f"ray_box_intersection: origins {tuple(origins.shape)} and directions "
            f"{tuple(directions.shape)} must both be (R, 3)"
        )
    if box_min.shape != (3,) or box_max.shape != (3,):
        raise ValueError(
            f"ray_box_intersection: box_min {tuple(box_min.shape)} and box_max "
            f"{tuple(box_max.shape)} must both be (3,)"
        )
    box_min = box_min.to(origins)
    box_max = box_max.to(origins)
    # Axis-parallel rays: the slab is either the whole line (origin between the planes, faces
    # included) or empty; dividing by ~0 instead would give nan when the origin lies on a plane.
    parallel = directions.abs() < 1e-12
    inv_d = 1.0 / torch.where(parallel, torch.ones_like(directions), directions)
    t_lo = (box_min - origins) * inv_d
    t_hi = (box_max - origins) * inv_d
    in_slab = (origins >= box_min) & (origins <= box_max)
    inf = torch.full_like(t_lo, float("inf"))
    t_enter = torch.where(parallel, torch.where(in_slab, -inf, inf), torch.minimum(t_lo, t_hi))
    t_exit = torch.where(parallel, torch.where(in_slab, inf, -inf), torch.maximum(t_lo, t_hi))
    t_near = t_enter.amax(dim=-1).clamp_min(0.0)
    t_far = t_exit.amin(dim=-1)
    hit = t_far > t_near
    zero = torch.zeros_like(t_near)
    return torch.where(hit, t_near, zero), torch.where(hit, t_far, zero), hit


def rays_in_box(origins: Tensor, directions: Tensor, box_min: Tensor, box_max: Tensor) -> RayBundle:
    """Bundle rays with near/far = their overlap with the box (misses get near = far = 0).

    Args:
        origins, directions: (R, 3) (unit directions); box_min, box_max: (3,).
    """
    t_near, t_far, _ = ray_box_intersection(origins, directions, box_min, box_max)
    return RayBundle(origins, directions, t_near, t_far)
