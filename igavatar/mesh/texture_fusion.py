"""A texture fused from the training images: every texel's surface point, posed in each training
frame, looked up in the frames whose camera sees it.

    views = [ProjectedView(posed_vertices, K, w2c, image, mask), ...]       # one per training frame
    image, covered, stats = fuse_texture(atlas_vertices, faces, uv, 1024, views, fallback_fn=field_colors)

This is the route of texture-stitching pipelines: the geometry and the poses are good enough to
project the images onto the surface, so the texture is as sharp as the photographs instead of as
the color network. Per texel and view:
    visible   the camera's ray towards the texel's posed point first hits the mesh within
              `occlusion_m` of that point (Embree), the point projects inside the image, on the
              subject's mask (eroded by `mask_erode_px`, so the background at the silhouette does
              not bleed in) and the surface faces the camera (cos > `min_cos`);
    weight    cos^`angle_power` / depth^2: frontal, close views dominate, so a texel takes its
              color from the few views that see it best rather than a blur over all of them.
The fused color is the weighted mean of the visible views' bilinear samples. Texels no view sees
(under the arms, the soles) take `fallback_fn` (the color field) when given; then the seams are
dilated as in `bake_texture`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from igavatar.geometry.raycast import MeshRayCaster
from igavatar.mesh.texture import DEFAULT_PADDING, dilate, rasterize_uv, sample_texture


@dataclass(frozen=True, eq=False)
class ProjectedView:
    """One training frame: the mesh posed in it and what its camera saw.

    Attributes:
        posed_vertices: (V, 3) world positions of the atlas mesh's vertices in this frame.
        K: (3, 3) intrinsics; w2c: (4, 4) world -> camera (OpenCV axes) of the image.
        image: (H, W, 3) uint8 sRGB; mask: (H, W) bool subject mask.
    """

    posed_vertices: np.ndarray
    K: np.ndarray
    w2c: np.ndarray
    image: np.ndarray
    mask: np.ndarray


@dataclass(frozen=True)
class FusionSettings:
    """How views are chosen and weighted (see the module docstring)."""

    min_cos: float = 0.2
    angle_power: float = 4.0
    occlusion_m: float = 0.01
    mask_erode_px: int = 2


def _face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    corners = vertices[faces]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)


def view_samples(view: ProjectedView, faces: np.ndarray, texel_face: np.ndarray, texel_bary: np.ndarray,
                 settings: FusionSettings) -> tuple[np.ndarray, np.ndarray]:
    """Colors (P, 3) in [0, 1] and weights (P,) (0 where unseen) of P texels in one view.

    Args:
        faces: (F, 3) of the atlas mesh; texel_face: (P,) the face holding each texel;
        texel_bary: (P, 3) its barycentric coordinates in that face.
    """
    vertices = np.asarray(view.posed_vertices, np.float64)
    points = np.einsum("pk,pkd->pd", texel_bary, vertices[faces[texel_face]])
    rotation, translation = view.w2c[:3, :3], view.w2c[:3, 3]
    center = -rotation.T @ translation
    to_point = points - center
    depth_along_ray = np.linalg.norm(to_point, axis=1)
    direction = to_point / np.maximum(depth_along_ray[:, None], 1e-12)
    cos = -(np.einsum("pd,pd->p", _face_normals(vertices, faces)[texel_face], direction))
    camera = points @ rotation.T + translation
    z = camera[:, 2]
    candidate = (cos > settings.min_cos) & (z > 1e-6)
    pixel = camera @ np.asarray(view.K, np.float64).T
    x = pixel[:, 0] / np.where(z > 1e-6, z, 1.0)
    y = pixel[:, 1] / np.where(z > 1e-6, z, 1.0)
    h, w = view.mask.shape
    candidate &= (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    mask = np.asarray(view.mask, np.uint8)
    if settings.mask_erode_px > 0:
        mask = cv2.erode(mask, np.ones((2 * settings.mask_erode_px + 1,) * 2, np.uint8))
    candidate &= mask[np.clip(np.round(y), 0, h - 1).astype(np.int64), np.clip(np.round(x), 0, w - 1).astype(np.int64)] > 0
    weights = np.zeros(points.shape[0])
    colors = np.zeros((points.shape[0], 3))
    index = np.flatnonzero(candidate)
    if index.size == 0:
        return colors, weights
    hits = MeshRayCaster(vertices, faces).first_hits(np.broadcast_to(center, (index.size, 3)), direction[index])
    seen = index[hits.distance >= depth_along_ray[index] - settings.occlusion_m]
    weights[seen] = cos[seen] ** settings.angle_power / depth_along_ray[seen] ** 2
    # Pixel centers at integers are texel centers at (x + 0.5) / w in texture coordinates.
    uv = np.stack([(x[seen] + 0.5) / w, (y[seen] + 0.5) / h], axis=1)
    colors[seen] = sample_texture(np.asarray(view.image)[..., :3], uv) / 255.0
    return colors, weights


def fuse_texture(
    vertices: np.ndarray,
    faces: np.ndarray,
    uv: np.ndarray,
    size: int,
    views: Iterable[ProjectedView],
    fallback_fn: Callable[[np.ndarray], np.ndarray] | None = None,
    settings: FusionSettings = FusionSettings(),
    rings: int = 2 * DEFAULT_PADDING,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Fuse the views' images into a texture over the atlas.

    Args:
        vertices: (V, 3) canonical positions of the atlas mesh (seam vertices duplicated), used by
            fallback_fn; faces: (F, 3); uv: (V, 2) in [0, 1], v down; size: texture side in texels.
        views: ProjectedView per frame, their posed_vertices in the same vertex order.
        fallback_fn: (P, 3) canonical points -> (P, 3) sRGB in [0, 1] for texels no view sees.
    Returns:
        image (size, size, 3) uint8 sRGB, covered (size, size) bool (texels inside a chart), and
        {"views", "texels", "seen_fraction", "mean_views_per_texel"}.
    """
    faces = np.asarray(faces, np.int64)
    face_of, bary = rasterize_uv(uv, faces, size)
    covered = face_of >= 0
    rows, cols = np.nonzero(covered)
    texel_face, texel_bary = face_of[rows, cols], bary[rows, cols]
    color_sum = np.zeros((rows.size, 3))
    weight_sum = np.zeros(rows.size)
    views_seen = np.zeros(rows.size, np.int64)
    n_views = 0
    for view in views:
        colors, weights = view_samples(view, faces, texel_face, texel_bary, settings)
        color_sum += colors * weights[:, None]
        weight_sum += weights
        views_seen += weights > 0
        n_views += 1
    seen = weight_sum > 0
    fused = color_sum / np.maximum(weight_sum, 1e-300)[:, None]
    if fallback_fn is not None and (~seen).any():
        points = np.einsum("pk,pkd->pd", texel_bary[~seen], np.asarray(vertices, np.float64)[faces[texel_face[~seen]]])
        fused[~seen] = np.asarray(fallback_fn(points), np.float64)
    filled = covered.copy()
    if fallback_fn is None:
        filled[rows[~seen], cols[~seen]] = False
    image = np.zeros((size, size, 3))
    image[rows, cols] = np.clip(fused, 0.0, 1.0)
    image = dilate(image, filled, rings)
    stats = {"views": n_views, "texels": int(rows.size), "seen_fraction": round(float(seen.mean()) if rows.size else 0.0, 4),
             "mean_views_per_texel": round(float(views_seen[seen].mean()) if seen.any() else 0.0, 2)}
    return (image * 255).round().astype(np.uint8), covered, stats
