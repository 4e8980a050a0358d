"""The avatar's surface as a mesh: canonical and posed extraction, colors, skin weights.

    vertices, faces = canonical_surface(avatar, resolution=256)      # closed by the canonical box
    vertices, faces = posed_surface(posed, box_min, box_max, 128)    # marching in posed space
    colors = vertex_colors(avatar, vertices)                         # (V, 3) uint8
    world = posed.pose_vertices(vertices)                             # see igavatar.model.posed

Extraction is igavatar.geometry.extract (coarse grid, then a fine narrow band); `progress`, when
given, is called as progress(points_done, points_total). Every mesh is the level set
`avatar.surface_level(surface_level)` of the SDF: "silhouette" (the default) where the renderer's
silhouette lies (igavatar.model.fields.silhouette_offset), "zero" its zero level.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from igavatar.geometry.extract import extract_mesh
from igavatar.model.avatar import SURFACE_LEVELS, Avatar
from igavatar.model.posed import PosedAvatar
from igavatar.skinning.grid import sample_skinning_weights

#: Coarse marching-cubes grid of the canonical surface (the posed one uses half of it).
COARSE_RESOLUTION = 64
#: The closed canonical surface is marched over the canonical box grown by this fraction of its
#: longest side, so the box's cap lies inside the grid.
_BOX_PAD = 0.02

Progress = Callable[[int, int], None] | None


def _closed_sdf(avatar: Avatar, level_m: float) -> Callable[[torch.Tensor], torch.Tensor]:
    """SDF of the canonical surface intersected with the canonical box: x (M, 3) -> (M,).

    max(sdf, box distance) is the SDF of the intersection (up to the usual max-bound), so a
    surface that reaches the box is capped there instead of left open.
    """
    box = avatar.canonical_box
    center, half = (box[0] + box[1]) / 2, (box[1] - box[0]) / 2

    def sdf_fn(x_canonical: torch.Tensor) -> torch.Tensor:
        sdf = avatar.surface_sdf(x_canonical, level_m)
        q = (x_canonical - center).abs() - half
        box_sdf = q.clamp_min(0).norm(dim=-1) + q.amax(dim=-1).clamp_max(0)
        return torch.maximum(sdf, box_sdf)

    return sdf_fn


@torch.no_grad()
def canonical_surface(
    avatar: Avatar, resolution: int, coarse_resolution: int = COARSE_RESOLUTION, progress: Progress = None,
    surface_level: str = SURFACE_LEVELS[0],
) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes of the canonical SDF capped by the canonical box (closed), before cleanup.

    Returns vertices (V, 3) float32 in canonical space and faces (F, 3) int64, outward wound.
    """
    box = avatar.canonical_box.detach().cpu().numpy().astype(np.float64)
    pad = _BOX_PAD * float((box[1] - box[0]).max())
    return extract_mesh(_closed_sdf(avatar, avatar.surface_level(surface_level)), box[0] - pad, box[1] + pad, resolution=resolution,
                        coarse_resolution=coarse_resolution, progress=progress, device=avatar.canonical_box.device)


def vertices_on_box(avatar: Avatar, vertices: np.ndarray, resolution: int) -> np.ndarray:
    """(V,) bool: vertices of a `canonical_surface` at `resolution` that lie on the canonical box's
    cap (within half a marching-cubes voxel of a box face), i.e. where the surface was cut open."""
    box = avatar.canonical_box.detach().cpu().numpy().astype(np.float64)
    half_voxel = 0.5 * float((box[1] - box[0]).max()) * (1 + 2 * _BOX_PAD) / (resolution - 1)
    return np.any((np.abs(vertices - box[0]) < half_voxel) | (np.abs(vertices - box[1]) < half_voxel), axis=1)


@torch.no_grad()
def posed_surface(
    posed: PosedAvatar, box_min: np.ndarray, box_max: np.ndarray, resolution: int,
    coarse_resolution: int = COARSE_RESOLUTION // 2, progress: Progress = None, surface_level: str = SURFACE_LEVELS[0],
) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes in posed space (the paper's alternative), before cleanup.

    The SDF of a posed point is the canonical SDF at its correspondence (PosedAvatar.sdf).
    Returns world vertices (V, 3) and faces (F, 3).
    """
    # Skinning stretches distances a little, so the narrow band is widened (see extract_mesh).
    level_m = posed.avatar.surface_level(surface_level)
    return extract_mesh(lambda x_posed: posed.sdf(x_posed, level_m), box_min, box_max, resolution=resolution, coarse_resolution=coarse_resolution,
                        progress=progress, device=posed.device, band=2.0, chunk_points=2**15)


@torch.no_grad()
def surface_colors(avatar: Avatar, points: np.ndarray, chunk: int = 65536) -> np.ndarray:
    """sRGB (M, 3) float32 in [0, 1] of the color field at canonical points (normals from the SDF)."""
    device = avatar.canonical_box.device
    colors = []
    for part in torch.from_numpy(np.asarray(points, np.float32)).split(chunk):
        x_canonical = part.to(device)
        _, feature, gradient = avatar.sdf_field.forward_with_gradient(x_canonical)
        normal = torch.nn.functional.normalize(gradient, dim=-1)
        colors.append(avatar.color_field(feature, normal, x_canonical).cpu())
    if not colors:
        return np.zeros((0, 3), np.float32)
    return torch.cat(colors).clamp(0, 1).numpy()


def vertex_colors(avatar: Avatar, vertices: np.ndarray, chunk: int = 65536) -> np.ndarray:
    """RGB (V, 3) uint8 of the color field at canonical vertices (normals from the SDF)."""
    return (surface_colors(avatar, vertices, chunk) * 255).round().astype(np.uint8)


@torch.no_grad()
def posed_vertex_colors(posed: PosedAvatar, x_posed: np.ndarray) -> np.ndarray:
    """RGB (V, 3) uint8 of the color field at the canonical correspondences of world points."""
    x = torch.from_numpy(np.asarray(x_posed, np.float32)).to(posed.device)
    return vertex_colors(posed.avatar, posed.canonical_points(x).cpu().numpy())


@torch.no_grad()
def vertex_skin_weights(avatar: Avatar, vertices: np.ndarray) -> np.ndarray:
    """Skinning weights (V, J) float32 sampled from the canonical skinning grid."""
    deformer = avatar.deformer
    x = torch.from_numpy(np.asarray(vertices, np.float32)).to(deformer.weights_grid.device)
    return sample_skinning_weights(deformer.weights_grid, deformer.box_min, deformer.box_max, x).cpu().numpy()
