"""UV atlas and color-texture baking for a decimated, textured avatar mesh.

    atlas = unwrap(vertices, faces, size=1024)                 # xatlas charts packed in a square
    image, covered = bake_texture(atlas.vertices(vertices), atlas.faces, atlas.uv, color_fn, 1024)
    png = png_bytes(image)                                     # igavatar.artifacts.png

UV convention: `UVAtlas.uv` (V', 2) is glTF's TEXCOORD_0, in [0, 1] with u to the right and v
*down* from the image's top row (row = v * size). OBJ's vt has v up: `obj_uv` flips it.

Baking: every texel whose center falls inside a chart triangle is mapped through that
triangle's barycentric coordinates to a point on the 3D surface, and the color field is
queried there (one query per texel, so the texture is as sharp as the field, not as the
decimated mesh's vertices). Texels outside every chart are then filled from their covered
neighbours, ring by ring (`dilate`), so bilinear filtering and mipmaps near a seam never blend in
the empty background.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import xatlas

from igavatar.errors import InputError

DEFAULT_PADDING = 4
"""Texels between charts: room for the seam dilation and for a few mip levels."""


@dataclass(frozen=True)
class UVAtlas:
    """A mesh cut into charts and packed into a square texture.

    Attributes:
        vertex_map: (V',) index of the input vertex each atlas vertex copies (seams duplicate).
        faces: (F, 3) int64 faces over the atlas vertices (same order as the input faces).
        uv: (V', 2) float32 texture coordinates in [0, 1] (v down, glTF's TEXCOORD_0).
        size: texture width = height in pixels.
    """

    vertex_map: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    size: int

    def vertices(self, per_vertex: np.ndarray) -> np.ndarray:
        """Per-vertex data of the input mesh (V, ...) carried to the atlas vertices (V', ...)."""
        return np.asarray(per_vertex)[self.vertex_map]


def unwrap(vertices: np.ndarray, faces: np.ndarray, size: int, padding: int = DEFAULT_PADDING) -> UVAtlas:
    """Charts and UVs of a triangle mesh by xatlas, packed into one `size` x `size` atlas.

    Args:
        vertices: (V, 3) positions; faces: (F, 3) vertex indices.
        size: texture resolution in pixels (>= 16).
        padding: texels left between charts.
    Returns:
        the UVAtlas (faces keep the input order).
    """
    v = np.ascontiguousarray(vertices, dtype=np.float32)
    f = np.ascontiguousarray(faces, dtype=np.uint32)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise InputError(f"unwrap: vertices {v.shape} and faces {f.shape} must be (V, 3) and (F, 3), F >= 1")
    if size < 16:
        raise InputError(f"unwrap: texture size {size}, expected at least 16 pixels")
    # xatlas estimates a texel density for `resolution` but may overshoot it; shrink the density
    # until the packed atlas fits the square (a few rounds at most).
    texels_per_unit = 0.0
    for _ in range(6):
        atlas = xatlas.Atlas()
        atlas.add_mesh(v, f)
        pack = xatlas.PackOptions()
        pack.resolution = int(size)
        pack.padding = int(padding)
        pack.bilinear = True  # leave a texel border around each chart for bilinear filtering
        pack.texels_per_unit = float(texels_per_unit)
        atlas.generate(xatlas.ChartOptions(), pack)
        largest = max(atlas.width, atlas.height)
        if atlas.atlas_count == 1 and largest <= size:
            break
        texels_per_unit = atlas.texels_per_unit * 0.97 * min(1.0, size / largest)
    else:
        raise InputError(f"unwrap: xatlas could not pack the charts into one {size} x {size} atlas")
    vertex_map, atlas_faces, uv = atlas[0]
    # xatlas returns UVs normalized by the atlas' own width and height (at most `size`); rescale
    # to the requested square so that uv * size is a texel position and texels stay square.
    scale = np.array([atlas.width, atlas.height], dtype=np.float64) / float(size)
    uv = np.asarray(uv, dtype=np.float64) * scale
    return UVAtlas(
        vertex_map=np.asarray(vertex_map, dtype=np.int64), faces=np.asarray(atlas_faces, dtype=np.int64),
        uv=uv.astype(np.float32), size=int(size),
    )


def obj_uv(uv: np.ndarray) -> np.ndarray:
    """glTF texture coordinates (v down) as OBJ's vt (v up)."""
    flipped = np.array(uv, dtype=np.float64)
    flipped[:, 1] = 1.0 - flipped[:, 1]
    return flipped


def rasterize_uv(uv: np.ndarray, faces: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Which triangle covers each texel center, and where.

    Args:
        uv: (V, 2) texture coordinates in [0, 1] (v down); faces: (F, 3).
        size: texture width = height.
    Returns:
        face (size, size) int64, -1 where no triangle covers the texel center, and
        barycentric (size, size, 3) float64 coordinates of the center in that triangle.
    """
    texel = np.asarray(uv, dtype=np.float64) * size - 0.5  # texel-center coordinates: center (i, j) at (j, i)
    corners = texel[np.asarray(faces)]  # (F, 3, 2)
    lo = np.clip(np.ceil(corners.min(axis=1)), 0, size - 1).astype(np.int64)  # (F, 2): first x, y inside
    hi = np.clip(np.floor(corners.max(axis=1)), 0, size - 1).astype(np.int64)
    face_of = np.full((size, size), -1, dtype=np.int64)
    bary = np.zeros((size, size, 3), dtype=np.float64)
    extent = np.maximum(hi - lo + 1, 0)
    # Triangles grouped by their bounding box size: one vectorised inside test per group.
    keys = extent[:, 0] * (size + 1) + extent[:, 1]
    for key in np.unique(keys):
        group = np.flatnonzero(keys == key)
        width, height = int(extent[group[0], 0]), int(extent[group[0], 1])
        if width == 0 or height == 0:
            continue
        ys, xs = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
        px = lo[group, 0, None, None] + xs  # (G, h, w)
        py = lo[group, 1, None, None] + ys
        a, b, c = (corners[group, k, None, None, :] for k in range(3))
        denominator = (b[..., 1] - c[..., 1]) * (a[..., 0] - c[..., 0]) + (c[..., 0] - b[..., 0]) * (a[..., 1] - c[..., 1])
        safe = np.where(np.abs(denominator) < 1e-12, 1.0, denominator)
        w0 = ((b[..., 1] - c[..., 1]) * (px - c[..., 0]) + (c[..., 0] - b[..., 0]) * (py - c[..., 1])) / safe
        w1 = ((c[..., 1] - a[..., 1]) * (px - c[..., 0]) + (a[..., 0] - c[..., 0]) * (py - c[..., 1])) / safe
        w2 = 1.0 - w0 - w1
        eps = -1e-9
        inside = (w0 >= eps) & (w1 >= eps) & (w2 >= eps) & (np.abs(denominator) >= 1e-12)
        g, yy, xx = np.nonzero(inside)
        face_of[py[g, yy, xx], px[g, yy, xx]] = group[g]
        bary[py[g, yy, xx], px[g, yy, xx]] = np.stack((w0[g, yy, xx], w1[g, yy, xx], w2[g, yy, xx]), axis=-1)
    return face_of, np.clip(bary, 0.0, 1.0) / np.clip(bary, 0.0, 1.0).sum(axis=-1, keepdims=True).clip(1e-12)


def dilate(image: np.ndarray, covered: np.ndarray, rings: int) -> np.ndarray:
    """Fill uncovered texels from covered neighbours, one ring of texels per iteration.

    Each new texel takes the mean of its already filled 8-neighbours; after `rings` iterations
    the texels still empty get the mean color of the covered ones (they are never sampled).

    Args:
        image: (H, W, C) float colors; covered: (H, W) bool.
    Returns:
        (H, W, C) float64 image.
    """
    result = np.array(image, dtype=np.float64)
    filled = np.array(covered, dtype=bool)
    if not filled.any():
        return result
    kernel = np.ones((3, 3), dtype=np.float64)
    for _ in range(rings):
        if filled.all():
            break
        weight = filled.astype(np.float64)
        total = cv2.filter2D(result * weight[..., None], -1, kernel, borderType=cv2.BORDER_CONSTANT)
        count = cv2.filter2D(weight, -1, kernel, borderType=cv2.BORDER_CONSTANT)
        grow = ~filled & (count > 0)
        if total.ndim == 2:
            total = total[..., None]
        result[grow] = total[grow] / count[grow][:, None]
        filled |= grow
    result[~filled] = result[np.asarray(covered, dtype=bool)].mean(axis=0)
    return result


def bake_texture(
    vertices: np.ndarray,
    faces: np.ndarray,
    uv: np.ndarray,
    color_fn: Callable[[np.ndarray], np.ndarray],
    size: int,
    rings: int = 2 * DEFAULT_PADDING,
    chunk: int = 1 << 18,
) -> tuple[np.ndarray, np.ndarray]:
    """Bake a color field into a texture over a UV layout.

    Args:
        vertices: (V, 3) positions of the UV mesh's vertices (seam vertices duplicated);
        faces: (F, 3); uv: (V, 2) in [0, 1], v down.
        color_fn: (P, 3) surface points -> (P, 3) sRGB colors in [0, 1].
        size: texture width = height; rings: dilation rings over seams.
    Returns:
        image (size, size, 3) uint8 sRGB (row 0 = v 0) and covered (size, size) bool, the texels
        inside a chart (the rest are dilated).
    """
    face_of, bary = rasterize_uv(uv, faces, size)
    covered = face_of >= 0
    rows, cols = np.nonzero(covered)
    corners = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)[face_of[rows, cols]]]  # (P, 3, 3)
    points = np.einsum("pk,pkd->pd", bary[rows, cols], corners)
    colors = np.concatenate([
        np.asarray(color_fn(points[start : start + chunk]), dtype=np.float64)
        for start in range(0, points.shape[0], chunk)
    ]) if points.shape[0] else np.zeros((0, 3))
    image = np.zeros((size, size, 3), dtype=np.float64)
    image[rows, cols] = np.clip(colors, 0.0, 1.0)
    image = dilate(image, covered, rings)
    return (image * 255).round().astype(np.uint8), covered


def sample_texture(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a texture at glTF texture coordinates, as a viewer samples it (clamped).

    Args:
        image: (H, W, C) texture (row 0 = v 0); uv: (P, 2) in [0, 1], v down.
    Returns:
        (P, C) float64 values.
    """
    image = np.asarray(image, dtype=np.float64)
    height, width = image.shape[:2]
    x = np.clip(np.asarray(uv, np.float64)[:, 0] * width - 0.5, 0, width - 1)
    y = np.clip(np.asarray(uv, np.float64)[:, 1] * height - 0.5, 0, height - 1)
    x0, y0 = np.minimum(np.floor(x).astype(np.int64), width - 2), np.minimum(np.floor(y).astype(np.int64), height - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = image[y0, x0] * (1 - fx) + image[y0, x0 + 1] * fx
    bottom = image[y0 + 1, x0] * (1 - fx) + image[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy



