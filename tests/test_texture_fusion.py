"""Texture fusion from images on an analytic case: a colored sphere photographed from known cameras."""

from __future__ import annotations

import numpy as np
import trimesh

from igavatar.geometry.raycast import MeshRayCaster, interpolate_vertex_values
from igavatar.mesh.texture import rasterize_uv, unwrap
from igavatar.mesh.texture_fusion import FusionSettings, ProjectedView, fuse_texture

SIZE = 96  # image side in pixels


def _color(points: np.ndarray) -> np.ndarray:
    """The sphere's paint: a smooth function of the direction, in [0.1, 0.9]."""
    d = points / np.linalg.norm(points, axis=1, keepdims=True)
    return 0.5 + 0.4 * np.stack([d[:, 0], d[:, 1] * d[:, 2], np.sin(3 * d[:, 2])], axis=1)


def _camera(azimuth: float, distance: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """K and w2c (OpenCV axes) of a camera on the equator looking at the origin, +Z up."""
    center = distance * np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
    forward = -center / distance
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])  # rows: camera axes in world
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = rotation, -rotation @ center
    K = np.array([[SIZE * 1.2, 0, (SIZE - 1) / 2], [0, SIZE * 1.2, (SIZE - 1) / 2], [0, 0, 1]])
    return K, w2c


def _photograph(mesh: trimesh.Trimesh, K: np.ndarray, w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The painted sphere as the camera sees it: (SIZE, SIZE, 3) uint8 and its mask."""
    ys, xs = np.mgrid[0:SIZE, 0:SIZE]
    pixels = np.stack([xs.ravel(), ys.ravel(), np.ones(SIZE * SIZE)], axis=1)
    directions_camera = pixels @ np.linalg.inv(K).T
    rotation = w2c[:3, :3]
    directions = directions_camera @ rotation  # camera -> world: R^T d
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    center = -rotation.T @ w2c[:3, 3]
    hits = MeshRayCaster(mesh.vertices, mesh.faces).first_hits(np.broadcast_to(center, directions.shape), directions)
    points = interpolate_vertex_values(mesh.vertices, mesh.faces, hits)
    image = np.full((SIZE * SIZE, 3), 255.0)
    image[hits.hit] = _color(points[hits.hit]) * 255
    return image.reshape(SIZE, SIZE, 3).round().astype(np.uint8), hits.hit.reshape(SIZE, SIZE)


def test_a_painted_sphere_comes_out_in_the_atlas():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    atlas = unwrap(sphere.vertices, sphere.faces, 256)
    vertices = atlas.vertices(sphere.vertices)
    views = []
    for azimuth in np.linspace(0, 2 * np.pi, 8, endpoint=False):
        K, w2c = _camera(azimuth)
        image, mask = _photograph(sphere, K, w2c)
        views.append(ProjectedView(vertices, K, w2c, image, mask))
    green = lambda points: np.tile([0.0, 1.0, 0.0], (len(points), 1))  # noqa: E731
    texture, covered, stats = fuse_texture(vertices, atlas.faces, atlas.uv, 256, views, fallback_fn=green,
                                           settings=FusionSettings(min_cos=0.3))
    assert stats["views"] == 8 and 0.6 < stats["seen_fraction"] < 1.0 and stats["mean_views_per_texel"] > 1.5

    face_of, bary = rasterize_uv(atlas.uv, atlas.faces, 256)
    rows, cols = np.nonzero(covered)
    points = np.einsum("pk,pkd->pd", bary[rows, cols], vertices[atlas.faces[face_of[rows, cols]]])
    got = texture[rows, cols] / 255.0
    latitude = np.abs(points[:, 2]) / 0.5
    equator = latitude < 0.5  # seen frontally by several cameras
    error = np.abs(got[equator] - _color(points[equator])).max(axis=1)
    assert np.median(error) < 0.03 and np.percentile(error, 95) < 0.08
    # The poles face away from every camera (cos < 0.3): they take the fallback.
    pole = latitude > 0.995
    assert pole.any() and np.allclose(got[pole], [0.0, 1.0, 0.0], atol=0.02)


def test_an_occluded_point_takes_no_color_from_the_view_that_cannot_see_it():
    # Two parallel squares; the camera sees only the front one. The back one stays unseen.
    front = trimesh.creation.box(extents=[1.0, 1.0, 0.01])
    back = front.copy()
    back.apply_translation([0, 0, -0.5])
    mesh = trimesh.util.concatenate([front, back])
    atlas = unwrap(mesh.vertices, mesh.faces, 128)
    vertices = atlas.vertices(mesh.vertices)
    K = np.array([[100.0, 0, 47.5], [0, 100.0, 47.5], [0, 0, 1]])
    w2c = np.diag([1.0, -1.0, -1.0, 1.0])
    w2c[2, 3] = 3.0  # the camera at z = +3 looking down -z
    image = np.full((SIZE, SIZE, 3), 200, np.uint8)
    view = ProjectedView(vertices, K, w2c, image, np.ones((SIZE, SIZE), bool))
    texture, covered, stats = fuse_texture(vertices, atlas.faces, atlas.uv, 128, [view],
                                           fallback_fn=lambda p: np.zeros((len(p), 3)), settings=FusionSettings(mask_erode_px=0))
    face_of, bary = rasterize_uv(atlas.uv, atlas.faces, 128)
    rows, cols = np.nonzero(covered)
    z = np.einsum("pk,pk->p", bary[rows, cols], vertices[atlas.faces[face_of[rows, cols]]][:, :, 2])
    back_face_up = np.isclose(z, -0.495, atol=1e-4)  # the back box's top face: turned to the camera, hidden
    front_face_up = np.isclose(z, 0.005, atol=1e-4)
    assert back_face_up.any() and front_face_up.any()
    np.testing.assert_array_equal(texture[rows[back_face_up], cols[back_face_up]], 0)
    # The front one is painted (but for texels on its rim, whose rays can graze the side faces first).
    painted = np.abs(texture[rows[front_face_up], cols[front_face_up]].astype(int) - 200).max(axis=1) <= 1
    assert painted.mean() > 0.9
