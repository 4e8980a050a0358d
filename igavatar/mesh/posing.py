"""The avatar's surface as a mesh: canonical extraction, colours, skin weights, posing to world space.

    vertices, faces = canonical_mesh(avatar, resolution=256)
    posed = pose_canonical_vertices(avatar, vertices, frame, pose)      # world coordinates

Posing a canonical surface point v: the non-rigid offset acts on rigid correspondences,
v = x_r + dx(x_r, pose), so x_r is found by the fixed-point iteration x_r <- v - dx(x_r, pose)
(dx is bounded and smooth, a few iterations suffice) and then skinned forward: LBS(x_r).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from igavatar.mesh.extract import extract_mesh
from igavatar.model.avatar import Avatar
from igavatar.model.deformer import PreparedFrame
from igavatar.skinning.grid import sample_skinning_weights


@torch.no_grad()
def canonical_mesh(
    avatar: Avatar,
    resolution: int = 256,
    coarse_resolution: int = 64,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes of the canonical SDF over the canonical box: (V, 3) float32, (F, 3) int64."""
    device = avatar.canonical_box.device

    def sdf_fn(x: torch.Tensor) -> torch.Tensor:
        return avatar.sdf_field(x.to(device))[0]

    box = avatar.canonical_box.cpu().numpy()
    return extract_mesh(sdf_fn, box[0], box[1], resolution=resolution, coarse_resolution=coarse_resolution,
                        progress=progress, device=device)


@torch.no_grad()
def surface_colors(avatar: Avatar, points: np.ndarray, chunk: int = 65536) -> np.ndarray:
    """sRGB (P, 3) float32 in [0, 1] of the colour field at canonical points (normals from the SDF)."""
    device = avatar.canonical_box.device
    colours = []
    for part in torch.from_numpy(np.asarray(points, np.float32)).split(chunk):
        _, feature, gradient = avatar.sdf_field.forward_with_gradient(part.to(device))
        normal = torch.nn.functional.normalize(gradient, dim=-1)
        colours.append(avatar.color_field(feature, normal).cpu())
    if not colours:
        return np.zeros((0, 3), np.float32)
    return torch.cat(colours).clamp(0, 1).numpy()


def vertex_colors(avatar: Avatar, vertices: np.ndarray, chunk: int = 65536) -> np.ndarray:
    """RGB (V, 3) uint8 of the colour field at canonical vertices (normals from the SDF)."""
    return (surface_colors(avatar, vertices, chunk) * 255).round().astype(np.uint8)


@torch.no_grad()
def vertex_skin_weights(avatar: Avatar, vertices: np.ndarray) -> np.ndarray:
    """Skinning weights (V, J) float32 sampled from the canonical skinning grid."""
    deformer = avatar.deformer
    x = torch.from_numpy(np.asarray(vertices, np.float32)).to(deformer.weights_grid.device)
    return sample_skinning_weights(deformer.weights_grid, deformer.box_min, deformer.box_max, x).cpu().numpy()


@torch.no_grad()
def pose_canonical_vertices(
    avatar: Avatar,
    vertices_canonical: np.ndarray,
    frame: PreparedFrame,
    pose: torch.Tensor,
    iterations: int = 3,
    chunk: int = 65536,
) -> np.ndarray:
    """World positions (V, 3) float32 of canonical surface vertices in one pose (non-rigid included)."""
    device = avatar.canonical_box.device
    pose = pose.to(device)
    posed = []
    for part in torch.from_numpy(np.asarray(vertices_canonical, np.float32)).split(chunk):
        v = part.to(device)
        x_rigid = v
        if avatar.nonrigid.enabled:
            for _ in range(iterations):
                x_rigid = v - avatar.nonrigid(x_rigid, pose)
        posed.append(avatar.deformer.forward_skinning(x_rigid, frame).cpu())
    return torch.cat(posed).numpy().astype(np.float32)
