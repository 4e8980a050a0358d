"""Canonical skinning-weight voxel grid (Fast-SNARF style) and per-frame blended transforms.

    box_min, box_max = canonical_grid_box(vertices_canonical, squeeze_axis=1)
    weights_grid = build_skinning_grid(vertices_canonical, lbs_weights, box_min, box_max, (64, 16, 64))

The grid is `weights (J, D, H, W)` over the axis-aligned box `[box_min, box_max]`; index order
D<->z, H<->y, W<->x as in `torch.nn.functional.grid_sample`, whose `align_corners=True` convention
puts voxel (0, 0, 0) exactly on `box_min` and voxel (D-1, H-1, W-1) exactly on `box_max`.

Because linear blend skinning is linear in the weights, trilinear interpolation of the per-voxel
blended transform `T = sum_j w_j B_j` equals `sum_j w_j(x) B_j` with trilinearly interpolated
weights: one 12-channel lookup per point replaces a J-channel lookup plus a J-term blend
(Fast-SNARF's per-frame precomputation).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree

from igavatar.errors import InputError
from igavatar.geometry.boxes import check_box

__all__ = [
    "canonical_grid_box",
    "grid_point_positions",
    "build_skinning_grid",
    "smooth_weights_grid",
    "distance_adaptive_weights",
    "sample_grid",
    "sample_skinning_weights",
    "inside_grid",
    "blended_transform_grid",
    "sample_blended_transforms",
    "apply_affine",
]


def _as_tensor(value: torch.Tensor | np.ndarray, name: str) -> torch.Tensor:
    """Return `value` as a torch tensor (numpy arrays become CPU tensors, dtype kept)."""
    if isinstance(value, torch.Tensor):
        return value
    if isinstance(value, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(value))
    raise InputError(f"{name}: expected a torch.Tensor or numpy array, got {type(value).__name__}")


def _check_points(x: torch.Tensor, name: str) -> None:
    if x.ndim != 2 or x.shape[1] != 3:
        raise InputError(f"{name}: shape {tuple(x.shape)}, expected (P, 3)")


def canonical_grid_box(
    vertices_canonical: torch.Tensor | np.ndarray,
    scale: float = 1.2,
    squeeze_axis: int | None = None,
    squeeze: float = 4.0,
    margin: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Axis-aligned box around a canonical body, as Fast-SNARF/InstantAvatar size their grid.

    A cube centerd on the body's bounding-box center with half-size `scale` x the body's largest
    half-extent; the depth axis `squeeze_axis` (igavatar's body frame is +Z up and faces -Y, so
    depth is axis 1 = Y; SMPL's is 2 = Z) has its half-size divided by `squeeze`, which spends the
    voxels where the body is, a thin slab in depth. Every half-size is then at least the body's
    half-extent plus `margin`: the squeezed slab of a deep body (a heavy belly with the feet ahead
    of it) otherwise ends a centimetre or two behind its back, and clothes there are cut off.

    Args:
        vertices_canonical: (V, 3) canonical template vertices.
        scale: half-size over the largest half-extent (1.2 in Fast-SNARF).
        squeeze_axis: 0, 1 or 2 to squeeze that axis, None for a cube.
        squeeze: factor dividing the squeezed half-size (4 in Fast-SNARF).
        margin: meters the box keeps beyond the vertices' bounds on every side (>= 0).
    Returns:
        box_min (3,), box_max (3,) float32 on the vertices' device (CPU for numpy input).
    """
    vertices = _as_tensor(vertices_canonical, "vertices_canonical")
    _check_points(vertices, "vertices_canonical")
    if vertices.shape[0] == 0:
        raise InputError("vertices_canonical: shape (0, 3), expected at least one vertex")
    if squeeze_axis is not None and squeeze_axis not in (0, 1, 2):
        raise InputError(f"squeeze_axis: {squeeze_axis!r}, expected None, 0, 1 or 2")
    if scale <= 0 or squeeze <= 0 or margin < 0:
        raise InputError(f"scale={scale}, squeeze={squeeze}, margin={margin}: scale and squeeze must be positive, margin >= 0")
    vertices = vertices.to(torch.float32)
    lower = vertices.min(dim=0).values
    upper = vertices.max(dim=0).values
    center = 0.5 * (lower + upper)
    half = 0.5 * (upper - lower).max() * scale
    half_sizes = half.expand(3).clone()
    if squeeze_axis is not None:
        half_sizes[squeeze_axis] = half / squeeze
    half_sizes = torch.maximum(half_sizes, 0.5 * (upper - lower) + margin)
    if not bool((half_sizes > 0).all()):
        raise InputError("vertices_canonical: all vertices coincide; the box would be empty")
    return center - half_sizes, center + half_sizes


def grid_point_positions(
    box_min: torch.Tensor, box_max: torch.Tensor, resolution: Sequence[int]
) -> torch.Tensor:
    """Canonical positions of the grid's voxel samples (align_corners=True convention).

    Args:
        box_min, box_max: (3,) box corners (x, y, z).
        resolution: (D, H, W) voxel counts along z, y, x, each >= 2.
    Returns:
        (D, H, W, 3) positions (x, y, z), dtype/device of box_min.
    """
    depth, height, width = (int(n) for n in resolution)
    if min(depth, height, width) < 2:
        raise InputError(f"resolution: {tuple(resolution)}, expected (D, H, W) with each >= 2")
    axes = [
        torch.linspace(float(box_min[a]), float(box_max[a]), n, dtype=box_min.dtype, device=box_min.device)
        for a, n in ((2, depth), (1, height), (0, width))
    ]
    z, y, x = torch.meshgrid(*axes, indexing="ij")
    return torch.stack([x, y, z], dim=-1)


def smooth_weights_grid(weights_grid: torch.Tensor, iterations: int) -> torch.Tensor:
    """Blur a (J, D, H, W) weight grid with `iterations` 3x3x3 box filters, re-normalized.

    Replicate padding keeps the border voxels from being pulled towards zero; an average of
    points of the probability simplex stays on it, and the re-normalization removes float drift.
    """
    if iterations <= 0:
        return weights_grid
    volume = weights_grid.unsqueeze(0)
    for _ in range(iterations):
        volume = F.avg_pool3d(F.pad(volume, (1, 1, 1, 1, 1, 1), mode="replicate"), 3, stride=1)
        volume = volume.clamp_min(0.0)
        volume = volume / volume.sum(dim=1, keepdim=True)
    return volume.squeeze(0)


#: Nearest vertices blended per voxel by the distance-adaptive kernel, and its width at the body.
SPREAD_NEIGHBORS = 256
SPREAD_SIGMA0_M = 0.01
#: Distances to the body (meters) between which the kernel's weights hand over to the blurred grid's.
SPREAD_NEAR_M = 0.05
SPREAD_FAR_M = 0.15


def build_skinning_grid(
    vertices_canonical: torch.Tensor | np.ndarray,
    weights: torch.Tensor | np.ndarray,
    box_min: torch.Tensor,
    box_max: torch.Tensor,
    resolution: Sequence[int],
    k: int = 30,
    smoothing_iterations: int = 30,
    spread: float | None = None,
) -> torch.Tensor:
    """Skinning-weight grid from template vertices: k-NN inverse-distance weights, then blur.

    InstantAvatar's recipe (30 nearest vertices weighted by 1/distance, 30 smoothing passes);
    every voxel's weights are non-negative and sum to 1.

    With `spread`, voxels near the body instead blend their SPREAD_NEIGHBORS nearest vertices with a
    Gaussian whose width grows with the voxel's distance d to the nearest vertex, sigma =
    SPREAD_SIGMA0_M + spread * d (`distance_adaptive_weights`), so the body and the clothes on it
    keep the template's own weights; from SPREAD_NEAR_M to SPREAD_FAR_M away they hand over to the
    blurred grid, which keeps far space a smooth mix. The blur alone drags every weight across the
    gaps (the thighs share weights, the arms leak into the flanks); the kernel alone skins the space
    between the spread legs rigidly with the nearer leg, which gives the posed feet a second root.

    Args:
        vertices_canonical: (V, 3) canonical template vertices.
        weights: (V, J) per-vertex skinning weights (non-negative, rows summing to 1).
        box_min, box_max: (3,) grid box, e.g. from `canonical_grid_box`.
        resolution: (D, H, W) voxel counts along z, y, x.
        k: nearest vertices blended per voxel (clamped to V).
        smoothing_iterations: 3x3x3 box-blur passes.
        spread: growth of the kernel width with distance (unitless); None for inverse distance.
    Returns:
        (J, D, H, W) float32 weights on the device of `weights` (CPU for numpy input).
    """
    vertices = _as_tensor(vertices_canonical, "vertices_canonical")
    vertex_weights = _as_tensor(weights, "weights")
    box_min = _as_tensor(box_min, "box_min")
    box_max = _as_tensor(box_max, "box_max")
    _check_points(vertices, "vertices_canonical")
    if vertex_weights.ndim != 2 or vertex_weights.shape[0] != vertices.shape[0]:
        raise InputError(
            f"weights: shape {tuple(vertex_weights.shape)}, expected (V, J) with "
            f"V = {vertices.shape[0]} (the number of vertices)"
        )
    if vertices.shape[0] == 0:
        raise InputError("vertices_canonical: shape (0, 3), expected at least one vertex")
    check_box(box_min, box_max, "box_min/box_max")
    if k < 1:
        raise InputError(f"k: {k}, expected >= 1")
    if spread is not None and not spread >= 0:
        raise InputError(f"spread: {spread}, expected >= 0 (or None for inverse-distance weights)")
    if bool((vertex_weights < 0).any()):
        raise InputError("weights: negative skinning weights; expected non-negative (V, J)")
    if bool((vertex_weights.sum(dim=1) <= 0).any()):
        raise InputError("weights: some vertices have all-zero skinning weights")
    device = vertex_weights.device

    positions = grid_point_positions(
        box_min.detach().cpu().double(), box_max.detach().cpu().double(), resolution
    )
    depth, height, width = positions.shape[:3]
    vertices_np = vertices.detach().cpu().double().numpy()
    weights_np = vertex_weights.detach().cpu().double().numpy()
    weights_np = weights_np / weights_np.sum(axis=1, keepdims=True)
    k = min(int(k), vertices_np.shape[0])

    points = positions.reshape(-1, 3).numpy()
    distance, index = cKDTree(vertices_np).query(points, k=k)
    distance = distance.reshape(-1, k)
    index = index.reshape(-1, k)
    # The floor keeps a voxel sitting on a vertex finite; it then takes (almost) that vertex's weights.
    inverse_distance = 1.0 / np.maximum(distance, 1e-4)
    inverse_distance /= inverse_distance.sum(axis=1, keepdims=True)
    voxel_weights = np.einsum("nk,nkj->nj", inverse_distance, weights_np[index])

    grid = torch.from_numpy(voxel_weights.T.reshape(-1, depth, height, width)).to(torch.float32)
    grid = grid / grid.sum(dim=0, keepdim=True)
    grid = smooth_weights_grid(grid, smoothing_iterations)
    if spread is not None:
        # Near voxels take the kernel's weights; the hand-over is linear in the distance, so continuous.
        near = (SPREAD_FAR_M - distance[:, 0]) / (SPREAD_FAR_M - SPREAD_NEAR_M)
        near = np.clip(near, 0.0, 1.0)
        needed = near > 0
        kernel = np.zeros((len(points), weights_np.shape[1]))
        kernel[needed] = distance_adaptive_weights(vertices_np, weights_np, points[needed], spread)
        alpha = torch.from_numpy(near.reshape(1, depth, height, width)).to(torch.float32)
        kernel_grid = torch.from_numpy(kernel.T.reshape(-1, depth, height, width)).to(torch.float32)
        grid = alpha * kernel_grid + (1.0 - alpha) * grid
        grid = grid / grid.sum(dim=0, keepdim=True)
    return grid.contiguous().to(device)


def distance_adaptive_weights(
    vertices: np.ndarray, vertex_weights: np.ndarray, points: np.ndarray, spread: float, chunk: int = 2048
) -> np.ndarray:
    """Blend vertex weights at points with a Gaussian that widens away from the body.

    Each point takes its SPREAD_NEIGHBORS nearest vertices, weighted by
    exp(-(|p - v|^2 - d^2) / (2 sigma^2)), with d the distance to the nearest vertex and
    sigma = SPREAD_SIGMA0_M + spread * d. Subtracting d^2 only rescales a point's kernel (it keeps
    the exponentials from underflowing far from the body); the blend is continuous in the point.

    Args:
        vertices: (V, 3) float64. vertex_weights: (V, J) rows summing to 1. points: (N, 3).
        spread: kernel growth with distance (0: a fixed 1 cm kernel everywhere).
        chunk: points per k-NN query (bounds memory at chunk x SPREAD_NEIGHBORS x J floats).
    Returns:
        (N, J) float64 weights, rows summing to 1.
    """
    tree = cKDTree(vertices)
    k = min(SPREAD_NEIGHBORS, len(vertices))
    out = np.empty((len(points), vertex_weights.shape[1]))
    for start in range(0, len(points), chunk):
        distance, index = tree.query(points[start:start + chunk], k=k)
        distance, index = distance.reshape(len(distance), k), index.reshape(len(index), k)
        sigma = SPREAD_SIGMA0_M + spread * distance[:, :1]
        kernel = np.exp(-0.5 * (distance**2 - distance[:, :1] ** 2) / sigma**2)
        kernel /= kernel.sum(axis=1, keepdims=True)
        out[start:start + chunk] = np.einsum("nk,nkj->nj", kernel, vertex_weights[index])
    return out


def _normalized_coordinates(
    x: torch.Tensor, box_min: torch.Tensor, box_max: torch.Tensor
) -> torch.Tensor:
    """Map canonical points (..., 3) to grid_sample's [-1, 1]^3 (x, y, z order = W, H, D)."""
    box_min = box_min.to(dtype=x.dtype, device=x.device)
    box_max = box_max.to(dtype=x.dtype, device=x.device)
    return (x - box_min) * (2.0 / (box_max - box_min)) - 1.0


def sample_grid(
    values: torch.Tensor, box_min: torch.Tensor, box_max: torch.Tensor, x: torch.Tensor
) -> torch.Tensor:
    """Trilinear lookup of a (C, D, H, W) grid at canonical points.

    Points outside the box take the value at the nearest border (padding "border"), so weights
    stay a convex combination there; use `inside_grid` to know which lookups were inside.

    Args:
        values: (C, D, H, W) grid over [box_min, box_max].
        x: (P, 3) canonical points.
    Returns:
        (P, C) in the dtype of `values`.
    """
    coords = _normalized_coordinates(x.to(values.dtype), box_min, box_max)
    sampled = F.grid_sample(
        values.unsqueeze(0),
        coords.reshape(1, -1, 1, 1, 3),
        mode="bilinear",
        padding_mode="border",
        align_corners=True,
    )
    return sampled.reshape(values.shape[0], -1).transpose(0, 1)


def sample_skinning_weights(
    weights_grid: torch.Tensor, box_min: torch.Tensor, box_max: torch.Tensor, x: torch.Tensor
) -> torch.Tensor:
    """Skinning weights at canonical points by trilinear interpolation.

    Args:
        weights_grid: (J, D, H, W).
        box_min, box_max: (3,) grid box.
        x: (P, 3) canonical points.
    Returns:
        (P, J) weights (non-negative, summing to 1 wherever the grid's voxels do).
    """
    if weights_grid.ndim != 4:
        raise InputError(f"weights_grid: shape {tuple(weights_grid.shape)}, expected (J, D, H, W)")
    _check_points(x, "x")
    return sample_grid(weights_grid, box_min, box_max, x)


def inside_grid(box_min: torch.Tensor, box_max: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """(..., 3) canonical points -> (...,) bool, True where the point lies in the closed box."""
    box_min = box_min.to(dtype=x.dtype, device=x.device)
    box_max = box_max.to(dtype=x.dtype, device=x.device)
    return ((x >= box_min) & (x <= box_max)).all(dim=-1)


def blended_transform_grid(weights_grid: torch.Tensor, bone_transforms: torch.Tensor) -> torch.Tensor:
    """Per-voxel blended transform `sum_j w_j B_j`, top 3x4 block (the last row is (0, 0, 0, 1)).

    Args:
        weights_grid: (J, D, H, W) voxel weights.
        bone_transforms: (J, 4, 4) canonical -> posed world bone transforms of one frame.
    Returns:
        (12, D, H, W), channel 4 * r + c holding entry (r, c) of the 3x4 block; differentiable in
        both inputs.
    """
    if weights_grid.ndim != 4:
        raise InputError(f"weights_grid: shape {tuple(weights_grid.shape)}, expected (J, D, H, W)")
    num_joints = weights_grid.shape[0]
    if bone_transforms.shape != (num_joints, 4, 4):
        raise InputError(
            f"bone_transforms: shape {tuple(bone_transforms.shape)}, expected ({num_joints}, 4, 4) "
            "to match the weight grid's joint count"
        )
    affine = bone_transforms[:, :3, :].reshape(num_joints, 12).to(weights_grid.dtype)
    depth, height, width = weights_grid.shape[1:]
    blended = affine.transpose(0, 1) @ weights_grid.reshape(num_joints, -1)
    return blended.reshape(12, depth, height, width)


def sample_blended_transforms(
    blended_grid: torch.Tensor, box_min: torch.Tensor, box_max: torch.Tensor, x: torch.Tensor
) -> torch.Tensor:
    """Blended 3x4 transforms at canonical points with one trilinear lookup.

    Args:
        blended_grid: (12, D, H, W) from `blended_transform_grid`.
        x: (P, 3) canonical points.
    Returns:
        (P, 3, 4) = sum_j w_j(x) B_j[:3, :] with trilinear weights w(x).
    """
    return sample_grid(blended_grid, box_min, box_max, x).reshape(-1, 3, 4)


def apply_affine(transforms: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """(P, 3, 4) affine transforms applied to (P, 3) points -> (P, 3)."""
    return (transforms[:, :, :3] @ x.unsqueeze(-1)).squeeze(-1) + transforms[:, :, 3]
