"""Subject masks for captures that have none: GrabCut seeded by the projected, posed body.

    body = PosedBody(vertices=x_posed, faces=faces)          # or PosedBody(joints=j, parents=p)
    mask = estimate_mask(rgb, K, w2c, body)                    # (H, W) bool

The posed body model says roughly where the subject is; the image says exactly. The seeds:
    sure subject       the body's silhouette shrunk by SURE_INSIDE_M (clearly inside it)
    probable subject   the silhouette of the posed template mesh (or, without a template,
                       capsules of CAPSULE_RADIUS_M around the bones)
    probable background a band of CLOTHING_BAND_M around it (loose clothes and hair reach out)
    sure background    everything farther away
GrabCut then fits color models to both sides and cuts along image edges (OpenCV's iterated graph
cut, Rother et al. 2004); of its foreground, only the parts connected to the sure subject are
kept. Distances in meters become pixels at the body's depth in that camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from igavatar.errors import InputError

#: Loose clothing and hair may reach this far (m) beyond the template; beyond it is background.
CLOTHING_BAND_M = 0.12
#: Pixels this far (m) inside the body silhouette are taken to be the subject for sure.
SURE_INSIDE_M = 0.03
#: Radius (m) of the probable-subject capsules around bones when there is no template mesh.
CAPSULE_RADIUS_M = 0.08
#: Radius (m) of the sure-subject core along bones when there is no template mesh.
CAPSULE_CORE_M = 0.02
#: GrabCut iterations (color model refits); more change little after about five.
GRABCUT_ITERATIONS = 5
_SUBPIXEL_BITS = 4  # fixed-point bits of the rasteriser's vertex coordinates


@dataclass(frozen=True)
class PosedBody:
    """One frame's posed body in world coordinates (numpy float64).

    Attributes:
        vertices: (V, 3) posed template vertices, or None when the body model has no template.
        faces: (F, 3) int template faces, or None.
        joints: (J, 3) posed joint positions (used when there is no template).
        parents: (J,) parent indices (-1 for the root).
    """

    vertices: np.ndarray | None = None
    faces: np.ndarray | None = None
    joints: np.ndarray | None = None
    parents: np.ndarray | None = None


def _camera_points(K: np.ndarray, w2c: np.ndarray, x_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (P, 2) and depths (P,) of world points."""
    x_cam = x_world @ w2c[:3, :3].T + w2c[:3, 3]
    depth = x_cam[:, 2]
    uv = (x_cam @ K.T)[:, :2] / np.maximum(depth, 1e-6)[:, None]
    return uv, depth


def meters_to_pixels(K: np.ndarray, w2c: np.ndarray, x_world: np.ndarray, meters: float) -> float:
    """How many pixels `meters` spans at the median depth of the points `x_world` (P, 3)."""
    _, depth = _camera_points(K, w2c, x_world)
    in_front = depth[depth > 1e-6]
    if in_front.size == 0:
        return 0.0
    return float(meters * 0.5 * (K[0, 0] + K[1, 1]) / np.median(in_front))


def mesh_silhouette(
    vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, w2c: np.ndarray, size_hw: tuple[int, int]
) -> np.ndarray:
    """(H, W) bool: pixels covered by the mesh (V, 3) / (F, 3) seen by camera (K, w2c).

    Triangles are filled one by one (cv2.fillPoly would cancel overlapping ones out); those with
    a vertex behind the camera are skipped.
    """
    uv, depth = _camera_points(K, w2c, np.asarray(vertices, np.float64))
    faces = np.asarray(faces, np.int64)
    visible = np.all(depth[faces] > 1e-6, axis=1)
    triangles = np.round(uv[faces[visible]] * (1 << _SUBPIXEL_BITS)).astype(np.int64)
    # Keep coordinates inside int32 for OpenCV; triangles that far out cannot touch the image.
    limit = (1 << 30) >> _SUBPIXEL_BITS
    inside = np.all(np.abs(triangles) < limit << _SUBPIXEL_BITS, axis=(1, 2))
    canvas = np.zeros(size_hw, np.uint8)
    for triangle in triangles[inside].astype(np.int32):
        cv2.fillConvexPoly(canvas, triangle, 1, cv2.LINE_8, _SUBPIXEL_BITS)
    return canvas > 0


def skeleton_silhouette(
    joints: np.ndarray, parents: np.ndarray, K: np.ndarray, w2c: np.ndarray, size_hw: tuple[int, int],
    radius_m: float,
) -> np.ndarray:
    """(H, W) bool: capsules of `radius_m` around the bones (child joint to parent) of a posed
    skeleton (J, 3), each drawn with its radius in pixels at its own depth."""
    uv, depth = _camera_points(K, w2c, np.asarray(joints, np.float64))
    focal = 0.5 * (K[0, 0] + K[1, 1])
    canvas = np.zeros(size_hw, np.uint8)
    for child, parent in enumerate(np.asarray(parents)):
        ends = [child] if parent < 0 else [int(parent), child]
        if np.any(depth[ends] <= 1e-6):
            continue
        radius = max(1, int(round(radius_m * focal / float(np.mean(depth[ends])))))
        points = [tuple(int(round(v)) for v in uv[e]) for e in ends]
        cv2.line(canvas, points[0], points[-1], 1, 2 * radius + 1, cv2.LINE_8)
        for point in points:
            cv2.circle(canvas, point, radius, 1, -1, cv2.LINE_8)
    return canvas > 0


def _disk(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def seed_labels(probable: np.ndarray, sure: np.ndarray, band_px: int) -> np.ndarray:
    """(H, W) uint8 GrabCut labels from the probable-subject and sure-subject masks (H, W) bool
    and the width in pixels of the probable-background band around the probable subject."""
    labels = np.full(probable.shape, cv2.GC_BGD, np.uint8)
    band = cv2.dilate(probable.astype(np.uint8), _disk(max(1, band_px))) > 0
    labels[band] = cv2.GC_PR_BGD
    labels[probable] = cv2.GC_PR_FGD
    labels[sure & probable] = cv2.GC_FGD
    return labels


def grabcut_mask(rgb: np.ndarray, labels: np.ndarray, iterations: int = GRABCUT_ITERATIONS) -> np.ndarray:
    """(H, W) bool subject mask: GrabCut from seed `labels` (H, W) uint8 on `rgb` (H, W, 3) uint8.

    Only the box around the non-background seeds is cut (with a margin of sure background so that
    the background color model has samples); of the result, the connected parts that hold a sure
    subject pixel are kept (all of it when there is none).
    """
    height, width = labels.shape
    active = np.argwhere(labels != cv2.GC_BGD)
    if active.size == 0 or not np.any((labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)):
        return np.zeros((height, width), bool)
    margin = max(8, (active.max(0) - active.min(0)).max() // 10)
    (y0, x0), (y1, x1) = np.maximum(active.min(0) - margin, 0), np.minimum(active.max(0) + margin + 1, (height, width))
    crop_labels = np.ascontiguousarray(labels[y0:y1, x0:x1])
    has_background = np.any((crop_labels == cv2.GC_BGD) | (crop_labels == cv2.GC_PR_BGD))
    if has_background:
        # GrabCut works in BGR or RGB alike (it only models colors); OpenCV wants 3-channel uint8.
        crop = np.ascontiguousarray(rgb[y0:y1, x0:x1])
        background_model, foreground_model = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
        cv2.grabCut(crop, crop_labels, None, background_model, foreground_model, iterations, cv2.GC_INIT_WITH_MASK)
    subject = np.zeros((height, width), bool)
    subject[y0:y1, x0:x1] = (crop_labels == cv2.GC_FGD) | (crop_labels == cv2.GC_PR_FGD)
    sure = labels == cv2.GC_FGD
    if not sure.any():
        return subject
    _, components = cv2.connectedComponents(subject.astype(np.uint8), connectivity=8)
    keep = np.unique(components[sure & subject])
    return np.isin(components, keep[keep > 0])


def estimate_mask(
    rgb: np.ndarray, K: np.ndarray, w2c: np.ndarray, body: PosedBody,
    band_m: float = CLOTHING_BAND_M, iterations: int = GRABCUT_ITERATIONS,
) -> np.ndarray:
    """(H, W) bool subject mask of one frame.

    Args:
        rgb: (H, W, 3) uint8 image (undistorted: the body is projected with a pinhole camera).
        K: (3, 3) intrinsics for this image size; w2c: (4, 4) world-to-camera.
        body: the posed body (template mesh, or skeleton when there is none).
        band_m: how far (m) beyond the body the subject may reach (clothes, hair).
    Raises:
        InputError: `rgb` is not an (H, W, 3) uint8 image, or the body gives no way to seed.
    """
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise InputError(f"segmentation: image has shape {rgb.shape} and dtype {rgb.dtype}, expected (H, W, 3) uint8")
    size_hw = rgb.shape[:2]
    K, w2c = np.asarray(K, np.float64), np.asarray(w2c, np.float64)
    if body.vertices is not None and body.faces is not None:
        points = np.asarray(body.vertices, np.float64)
        probable = mesh_silhouette(points, body.faces, K, w2c, size_hw)
        sure_px = int(round(meters_to_pixels(K, w2c, points, SURE_INSIDE_M)))
        sure = cv2.erode(probable.astype(np.uint8), _disk(sure_px)) > 0 if sure_px > 0 else probable
    elif body.joints is not None and body.parents is not None:
        points = np.asarray(body.joints, np.float64)
        probable = skeleton_silhouette(points, body.parents, K, w2c, size_hw, CAPSULE_RADIUS_M)
        sure = skeleton_silhouette(points, body.parents, K, w2c, size_hw, CAPSULE_CORE_M)
    else:
        raise InputError("segmentation: the posed body has neither a template mesh nor a skeleton to seed GrabCut")
    band_px = int(round(meters_to_pixels(K, w2c, points, band_m)))
    return grabcut_mask(rgb, seed_labels(probable, sure, band_px), iterations)
