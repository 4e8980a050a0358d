"""Ray casting of triangle meshes with Embree (embreex): first hits, pinhole pixel rays, images.

    rays = CameraRays(K, w2c, height, width, supersample=2)          # once per camera
    frame = render_mesh(MeshRayCaster(x_world, faces), rays, shade)  # frame.rgb, frame.mask, frame.depth

Embree intersects in float32; barycentric weights follow Embree's convention, hit point =
b0 * v0 + b1 * v1 + b2 * v2 with (b0, b1, b2) = (1 - u - v, u, v). Shapes: R rays, V vertices,
F faces, H x W pixels, s x s samples per pixel.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from igavatar.errors import InputError
from igavatar.geometry.projection import camera_center, project_points


@dataclass(frozen=True)
class RayHits:
    """First intersections of R rays with a mesh.

    Attributes:
        face_index: (R,) int64 index of the first face hit, -1 where the ray misses.
        barycentric: (R, 3) float64 weights of the hit face's three vertices (zeros on a miss).
        distance: (R,) float64 ray parameter of the hit (a distance for unit directions), inf on a miss.
    """

    face_index: np.ndarray
    barycentric: np.ndarray
    distance: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        """(R,) bool: whether each ray hit the mesh."""
        return self.face_index >= 0


class MeshRayCaster:
    """An Embree BVH over one triangle mesh (built once; query with many ray batches).

    Args:
        vertices: (V, 3) positions (any frame; rays must be given in the same frame).
        faces: (F, 3) vertex indices.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        vertices = np.asarray(vertices, dtype=np.float64)
        faces = np.asarray(faces, dtype=np.int64)
        if vertices.ndim != 2 or vertices.shape[1] != 3:
            raise InputError(f"ray caster: vertices have shape {vertices.shape}, expected (V, 3)")
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
            raise InputError(f"ray caster: faces have shape {faces.shape}, expected (F, 3) with F >= 1")
        if faces.min() < 0 or faces.max() >= vertices.shape[0]:
            raise InputError(f"ray caster: faces index vertices outside [0, {vertices.shape[0] - 1}]")
        self.vertices = vertices
        self.faces = faces
        self._scene = rtcore_scene.EmbreeScene()
        # Embree keeps its own float32 copy of the triangles.
        TriangleMesh(self._scene, vertices[faces].astype(np.float32))

    def first_hits(self, origins: np.ndarray, directions: np.ndarray) -> RayHits:
        """First hit of each ray `origins + t * directions`, t > 0.

        Args:
            origins: (R, 3) ray origins.
            directions: (R, 3) ray directions (unit length for `distance` to be metric).
        Returns:
            RayHits for the R rays.
        """
        origins = np.ascontiguousarray(origins, dtype=np.float32).reshape(-1, 3)
        directions = np.ascontiguousarray(directions, dtype=np.float32).reshape(-1, 3)
        if origins.shape != directions.shape:
            raise InputError(f"ray caster: origins {origins.shape} and directions {directions.shape} differ")
        if origins.shape[0] == 0:
            return RayHits(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0))
        result = self._scene.run(origins, directions, output=1)
        face_index = result["primID"].astype(np.int64)
        hit = face_index >= 0
        u = np.where(hit, result["u"], 0.0).astype(np.float64)
        v = np.where(hit, result["v"], 0.0).astype(np.float64)
        barycentric = np.stack([1.0 - u - v, u, v], axis=-1) * hit[:, None]
        distance = np.where(hit, result["tfar"].astype(np.float64), np.inf)
        return RayHits(face_index, barycentric, distance)


def interpolate_vertex_values(values: np.ndarray, faces: np.ndarray, hits: RayHits) -> np.ndarray:
    """Barycentric interpolation of per-vertex values at the hit points.

    Args:
        values: (V, C) per-vertex values (e.g. canonical positions, region coverages).
        faces: (F, 3) the faces the hits refer to.
        hits: R hits; rays that missed get zeros.
    Returns:
        (R, C) float64 values at the hit points.
    """
    values = np.asarray(values, dtype=np.float64)
    face = np.maximum(hits.face_index, 0)
    corners = values[faces[face]]  # (R, 3, C)
    return np.einsum("rk,rkc->rc", hits.barycentric, corners)


class CameraRays:
    """The world-space rays of every sample of an OpenCV pinhole camera, computed once per camera.

    Sample (i, j) of the (H * s, W * s) grid sits at pixel coordinates
    (x, y) = (j // s + ((j % s) + 0.5) / s - 0.5, i // s + ((i % s) + 0.5) / s - 0.5), so with s = 1 the
    rays pass through the pixel centers at integer coordinates.

    Args:
        K: (3, 3) intrinsics in pixels; w2c: (4, 4) world-to-camera; height, width: image size.
        supersample: samples per pixel along each axis (s).
    Attributes:
        origin: (3,) camera center in world coordinates.
        directions: (H * s, W * s, 3) float32 unit ray directions in world coordinates.
    """

    def __init__(self, K: np.ndarray, w2c: np.ndarray, height: int, width: int, supersample: int = 2) -> None:
        if supersample < 1:
            raise InputError(f"camera rays: supersample must be >= 1, got {supersample}")
        if height < 1 or width < 1:
            raise InputError(f"camera rays: image size {width}x{height} must be positive")
        self.K = np.asarray(K, dtype=np.float64)
        self.w2c = np.asarray(w2c, dtype=np.float64)
        self.height, self.width, self.supersample = int(height), int(width), int(supersample)
        s = self.supersample
        offsets = (np.arange(s) + 0.5) / s - 0.5
        sample_x = (np.arange(width)[:, None] + offsets[None, :]).reshape(-1)
        sample_y = (np.arange(height)[:, None] + offsets[None, :]).reshape(-1)
        # K^-1 [x, y, 1] for an upper-triangular K without skew, then rotated to world:
        # d = a(x) * right + b(y) * down + forward, with the camera axes as rows of R.
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        skew = self.K[0, 1]
        b = (sample_y - cy) / fy
        a = (sample_x[None, :] - cx - skew * b[:, None]) / fx
        right, down, forward = self.w2c[:3, :3]
        directions = a[..., None] * right + b[:, None, None] * down + forward
        directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
        self.directions = directions.astype(np.float32)
        self.origin = camera_center(self.w2c)


@dataclass(frozen=True)
class Rendering:
    """One rendered view.

    Attributes:
        rgb: (H, W, 3) uint8 color (background where nothing was hit).
        mask: (H, W) bool, coverage > 0.5 of the same samples that made `rgb`.
        coverage: (H, W) float32 fraction of the s x s samples that hit the mesh.
        depth: (H, W) float32 mean camera-space z of the hit samples, 0 where the mask is False.
    """

    rgb: np.ndarray
    mask: np.ndarray
    coverage: np.ndarray
    depth: np.ndarray


ShadeFunction = Callable[[RayHits, np.ndarray, np.ndarray], np.ndarray]
"""shade(hits, x_world (P, 3), view_dirs (P, 3)) -> (P, 3) RGB in [0, 1] for P rays that hit."""


def render_mesh(
    caster: MeshRayCaster,
    rays: CameraRays,
    shade: ShadeFunction,
    *,
    background: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> Rendering:
    """Ray cast an image of the mesh with s x s rays per pixel, averaged (box filter).

    Only the pixels inside the projected bounding box of the mesh are traced; the rest is background.

    Args:
        caster: the mesh, in world coordinates.
        rays: the camera's sample rays (its K, w2c, size and s).
        shade: colors the hits (see ShadeFunction); called once with every hit sample.
        background: RGB in [0, 1] where rays miss.
    Returns:
        a Rendering.
    """
    K, w2c, height, width, s = rays.K, rays.w2c, rays.height, rays.width, rays.supersample
    x_pixels, z = project_points(K, w2c, caster.vertices)
    background_rgb = np.asarray(background, dtype=np.float64)
    if np.all(z > 1e-6):
        # Whole mesh in front of the camera: its projection bounds every pixel it can cover.
        x0, y0 = np.floor(x_pixels.min(axis=0) - 1.0).astype(int)
        x1, y1 = np.ceil(x_pixels.max(axis=0) + 1.0).astype(int)
        x0, y0 = max(x0, 0), max(y0, 0)
        x1, y1 = min(x1, width - 1), min(y1, height - 1)
    else:
        x0, y0, x1, y1 = 0, 0, width - 1, height - 1
    rgb = np.broadcast_to(background_rgb, (height, width, 3)).copy()
    coverage = np.zeros((height, width), dtype=np.float64)
    depth = np.zeros((height, width), dtype=np.float64)
    if x1 >= x0 and y1 >= y0:
        box_w, box_h = x1 - x0 + 1, y1 - y0 + 1
        directions = rays.directions[y0 * s : (y1 + 1) * s, x0 * s : (x1 + 1) * s].reshape(-1, 3)
        origins = np.broadcast_to(rays.origin.astype(np.float32), directions.shape)
        hits = caster.first_hits(origins, directions)
        hit = hits.hit
        sample_rgb = np.broadcast_to(background_rgb, (hit.shape[0], 3)).copy()
        sample_depth = np.zeros(hit.shape[0])
        if hit.any():
            sub_hits = RayHits(hits.face_index[hit], hits.barycentric[hit], hits.distance[hit])
            hit_dirs = directions[hit].astype(np.float64)
            x_world = rays.origin + hit_dirs * sub_hits.distance[:, None]
            sample_rgb[hit] = np.clip(shade(sub_hits, x_world, hit_dirs), 0.0, 1.0)
            sample_depth[hit] = (x_world @ w2c[2, :3]) + w2c[2, 3]

        def pool(values: np.ndarray) -> np.ndarray:
            # (box_h*s * box_w*s, C) -> (box_h, box_w, C) mean over each pixel's s x s samples
            return values.reshape(box_h, s, box_w, s, -1).mean(axis=(1, 3))

        box_coverage = pool(hit.astype(np.float64)[:, None])[..., 0]
        rgb[y0 : y1 + 1, x0 : x1 + 1] = pool(sample_rgb)
        depth_sum = pool(sample_depth[:, None])[..., 0]
        coverage[y0 : y1 + 1, x0 : x1 + 1] = box_coverage
        depth[y0 : y1 + 1, x0 : x1 + 1] = np.where(
            box_coverage > 0, depth_sum / np.maximum(box_coverage, 1e-12), 0.0
        )
    mask = coverage > 0.5
    depth = np.where(mask, depth, 0.0)
    rgb_u8 = np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)
    return Rendering(rgb=rgb_u8, mask=mask, coverage=coverage.astype(np.float32), depth=depth.astype(np.float32))
