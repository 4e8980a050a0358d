"""Depth, normal, coverage and color maps of a mesh seen by a frontal camera (export's --exr).

    K, w2c = frontal_camera(vertices, body_axes, 512)
    maps = mesh_maps(vertices, faces, colors, K, w2c, 512)     # {"Z", "N", "A", "RGB"}

Maps are ray-cast from the mesh itself (Embree), so they match the exported file exactly.
"""

from __future__ import annotations

import math

import numpy as np

from igavatar.geometry.mesh_ops import vertex_normals
from igavatar.geometry.raycast import CameraRays, MeshRayCaster, interpolate_vertex_values
from igavatar.mesh.gltf import srgb_to_linear

CAMERA_FOV_DEG = 30.0


def frontal_camera(vertices: np.ndarray, body_axes: np.ndarray, size: int, fov_deg: float = CAMERA_FOV_DEG
                   ) -> tuple[np.ndarray, np.ndarray]:
    """A pinhole camera in front of the body that frames all vertices.

    Args:
        vertices: (V, 3) world points to frame.
        body_axes: (3, 3) columns = the body's left, up, forward directions in world.
        size: image height = width in pixels; fov_deg: field of view.
    Returns:
        K (3, 3) and w2c (4, 4) (OpenCV: x right, y down, z forward), float64.
    """
    _, up, forward = body_axes.T
    z_axis = -forward  # the camera looks at the face
    y_axis = -up
    x_axis = np.cross(y_axis, z_axis)
    rotation = np.stack((x_axis, y_axis, z_axis))
    center = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    local = (vertices - center) @ rotation.T
    tan_half = math.tan(math.radians(fov_deg) / 2)
    # Each vertex needs |offset in the image plane| <= tan_half * (its depth from the camera) / margin.
    margin = 1.1
    distance = float(np.max(-local[:, 2] + np.abs(local[:, :2]).max(axis=1) * margin / tan_half))
    position = center - z_axis * distance
    w2c = np.eye(4)
    w2c[:3, :3] = rotation
    w2c[:3, 3] = -rotation @ position
    focal = size / 2 / tan_half
    K = np.array([[focal, 0.0, (size - 1) / 2], [0.0, focal, (size - 1) / 2], [0.0, 0.0, 1.0]])
    return K, w2c


def mesh_maps(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray, K: np.ndarray, w2c: np.ndarray,
              size: int) -> dict[str, np.ndarray]:
    """Ray-cast depth (Z: camera z), unit world normals (N), coverage (A) and linear color (RGB).

    Args:
        vertices: (V, 3) world; faces: (F, 3); colors: (V, 3) uint8 sRGB; K (3, 3), w2c (4, 4).
    Returns:
        Z (size, size), N (size, size, 3), A (size, size), RGB (size, size, 3), float32.
    """
    rays = CameraRays(K, w2c, size, size, supersample=1)
    caster = MeshRayCaster(vertices, faces)
    directions = rays.directions.reshape(-1, 3)
    hits = caster.first_hits(np.broadcast_to(rays.origin, directions.shape), directions)
    hit = hits.hit
    x_world = rays.origin + directions.astype(np.float64) * np.where(hit, hits.distance, 0.0)[:, None]
    depth = np.where(hit, x_world @ w2c[2, :3] + w2c[2, 3], 0.0)
    normals = interpolate_vertex_values(vertex_normals(vertices, faces), faces, hits)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.where(hit[:, None] & (length > 0), normals / np.maximum(length, 1e-12), 0.0)
    rgb = srgb_to_linear(interpolate_vertex_values(colors / 255.0, faces, hits)) * hit[:, None]
    shape = (size, size)
    return {
        "Z": depth.reshape(shape).astype(np.float32),
        "N": normals.reshape(shape + (3,)).astype(np.float32),
        "A": hit.reshape(shape).astype(np.float32),
        "RGB": rgb.reshape(shape + (3,)).astype(np.float32),
    }
