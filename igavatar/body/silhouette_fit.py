"""A silhouette term for the landmark fit: the posed body must lie inside the person's mask.

    target = SilhouetteTarget.of(masks, rest_vertices, skinning_weights, rest_joints, points=600)
    loss = target.loss_px(global_posed, K, w2c, coverage_weight=0.0)  # robust mean px outside the masks
    loss = target.loss_at(uv, coverage_weight=0.0)   # the same, at pixels already projected

Landmarks place a body's joints but say little about where its flesh is: in a side view the
hips' and shoulders' landmarks sit somewhere inside the torso, and the fit then puts the torso a
few centimetres in front of or behind the person (the view's lateral direction), which the avatar
sees as a different body in each frame. The mask says where the person is. The body model is
naked and the person is clothed, so only one side of the comparison holds for every outfit: every
point of the body lies inside the mask (clothes, hair and a dress only make the mask larger). The
term is each surface point's distance outside the mask, read from the mask's distance transform
at its projection (bilinear, so it is differentiable in the pose), robust (Huber) beyond a few px.

The other side, optional (coverage_weight > 0, off in the video fit): each point of the mask's
outline should lie within a margin for clothes of the body, up to a cap. It is what says how far
away the body is (its size in the image), and it did fix some of the frames' depth, but where
clothes stand far off the body (a dress) it pulled the legs apart
(tests/benchmarks/results/video-fit-silhouette.md).

The surface is a fixed subset of the body's vertices (60 frames x 600 points stay cheap to pose
every step of the fit), skinned with their 4 strongest weights by the shared
igavatar.body.skeleton.linear_blend_skinning.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from igavatar.body.image_maps import frame_px_grid, huber_px, shrunk_size
from igavatar.body.rotations import rigid_matrix
from igavatar.body.skeleton import linear_blend_skinning

#: Points of the body surface the term checks (a fixed, evenly spread subset of the mesh).
SURFACE_POINTS = 600
#: The distance maps are kept at most this many pixels on a side (float32): 300 frames of 1024 px
#: would otherwise hold 2.5 GB; a distance map is smooth, so sampling a smaller one loses little.
DISTANCE_MAP_SIDE = 512
#: Skinning weights kept per point (Anny's vertices carry at most a few).
WEIGHTS_PER_POINT = 4
#: Points along each mask's outline for the coverage term.
CONTOUR_POINTS = 100
#: Clothes may stand this far (a share of the person's height in the image) off the body.
CLOTHES_MARGIN = 0.02
#: Outline points farther than the margin plus this (a share of the height) from the body pull no more.
COVERAGE_CAP = 0.03
#: Below this many pixels outside, the penalty is quadratic (segmentation edges are soft).
HUBER_PX = 2.0


@dataclass(frozen=True)
class SilhouetteTarget:
    """What the silhouette term needs, as float64 tensors.

    Attributes:
        outside_distance: (N, 1, h, w) float32 per frame, each pixel's distance to the mask (0 inside)
            in the frame's px, at 1 / map_scale of the frame's size.
        rest_points: (S, 3) rest-pose surface points (world, meters).
        weights: (S, J) their skinning weights, only the WEIGHTS_PER_POINT strongest, renormalised
            to sum to 1.
        rest_to_joint: (J, 4, 4) [I | -rest_j]: rest pose -> each joint's rest frame, so that a
            global joint transform G_j makes the bone transform G_j @ rest_to_joint_j.
        frame_weight: (N,) 0 for frames without a usable mask.
    """

    outside_distance: torch.Tensor
    rest_points: torch.Tensor
    weights: torch.Tensor
    rest_to_joint: torch.Tensor
    frame_weight: torch.Tensor
    map_scale: float = 1.0
    contour_px: torch.Tensor | None = None
    contour_margin_px: torch.Tensor | None = None
    contour_cap_px: torch.Tensor | None = None

    @classmethod
    def of(cls, masks: np.ndarray, rest_vertices: np.ndarray, skinning_weights: np.ndarray,
           rest_joints: np.ndarray, points: int = SURFACE_POINTS) -> "SilhouetteTarget":
        """From (N, H, W) mask probabilities, the body's (V, 3) rest vertices, (V, J) skinning
        weights and (J, 3) rest joints."""
        inside = np.asarray(masks) >= 0.5
        distance, scale = _distance_maps(inside)
        chosen = spread_subset(np.asarray(rest_vertices, dtype=np.float64), points)
        weights = np.asarray(skinning_weights, dtype=np.float64)[chosen]
        bones = np.argsort(-weights, axis=1)[:, :WEIGHTS_PER_POINT]
        kept = np.take_along_axis(weights, bones, axis=1)
        kept = kept / np.maximum(kept.sum(1, keepdims=True), 1e-12)
        strongest = np.zeros_like(weights)
        np.put_along_axis(strongest, bones, kept, axis=1)
        rest_joints = torch.as_tensor(np.array(rest_joints, dtype=np.float64))
        contours = np.stack([contour_points(m, CONTOUR_POINTS) for m in inside])
        heights = np.array([np.ptp(np.nonzero(m)[0]) if m.any() else 0 for m in inside], dtype=np.float64)
        return cls(torch.as_tensor(distance)[:, None],
                   torch.as_tensor(np.asarray(rest_vertices, dtype=np.float64)[chosen]),
                   torch.as_tensor(strongest),
                   rigid_matrix(torch.eye(3, dtype=torch.float64).expand(len(rest_joints), 3, 3), -rest_joints),
                   torch.as_tensor(inside.any(axis=(1, 2)), dtype=torch.float64), scale,
                   torch.as_tensor(contours), torch.as_tensor(CLOTHES_MARGIN * heights),
                   torch.as_tensor(COVERAGE_CAP * heights))

    def posed_points(self, global_posed: torch.Tensor) -> torch.Tensor:
        """(N, S, 3) world surface points for (N, J, 4, 4) global joint transforms (rest -> posed)."""
        return linear_blend_skinning(self.rest_points, self.weights, global_posed @ self.rest_to_joint)

    def projected(self, global_posed: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, S, 2) pixels and (N, S) camera-frame depths (meters) of the posed surface points."""
        x_camera = self.posed_points(global_posed) @ w2c[:3, :3].T + w2c[:3, 3]
        return (x_camera @ K.T)[..., :2] / x_camera[..., 2:].clamp_min(1e-3), x_camera[..., 2]

    def distances_px(self, global_posed: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor,
                     coverage: bool = True) -> tuple[torch.Tensor, torch.Tensor | None]:
        """distances_at the posed surface points' pixels (projected)."""
        return self.distances_at(self.projected(global_posed, K, w2c)[0], coverage)

    def distances_at(self, uv: torch.Tensor, coverage: bool = True) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(outside (N, S), uncovered (N, C) or None), in px, of the surface points at pixels uv (N, S, 2):
        - outside: each posed surface point's distance beyond its frame's mask;
        - uncovered: each point of the mask's outline's distance to the nearest body point, less a
          margin for clothes (it keeps the body from shrinking away from the outline, e.g. by
          moving off in depth)."""
        height, width = self.outside_distance.shape[-2:]
        # A point beyond the image reads the border's distance (the person is checked to be in frame).
        grid = frame_px_grid(uv, self.map_scale, height, width)
        outside = torch.nn.functional.grid_sample(self.outside_distance, grid[:, None].to(self.outside_distance.dtype),
                                                  mode="bilinear", padding_mode="border",
                                                  align_corners=True)[:, 0, 0].to(uv.dtype)
        if not coverage:
            return outside, None
        with torch.no_grad():  # which body point is nearest: the gradient flows through its distance only
            nearest = torch.cdist(self.contour_px, uv).argmin(-1)  # (N, C)
        closest = torch.gather(uv, 1, nearest[..., None].expand(-1, -1, 2))
        gap = ((closest - self.contour_px).norm(dim=-1) - self.contour_margin_px[:, None]).clamp_min(0)
        # Beyond the cap an outline point is clothes standing off the body (a skirt's hem): no pull.
        return outside, torch.minimum(gap, self.contour_cap_px[:, None])

    def loss_px(self, global_posed: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor,
                coverage_weight: float) -> torch.Tensor:
        """loss_at the posed surface points' pixels (projected)."""
        return self.loss_at(self.projected(global_posed, K, w2c)[0], coverage_weight)

    def loss_at(self, uv: torch.Tensor, coverage_weight: float) -> torch.Tensor:
        """Mean robust outside + coverage_weight x mean robust uncovered distance (distances_at) of
        the surface points at pixels uv (N, S, 2)."""
        outside, uncovered = self.distances_at(uv, coverage_weight > 0)
        loss = self._mean(huber_px(outside, HUBER_PX))
        if uncovered is not None:
            loss = loss + coverage_weight * self._mean(huber_px(uncovered, HUBER_PX))
        return loss

    def mean_distances_px(self, uv: torch.Tensor) -> dict[str, float]:
        """For the record: the mean outside and uncovered distances (px) over frames with a mask, of
        the surface points at pixels uv (N, S, 2)."""
        with torch.no_grad():
            outside, uncovered = self.distances_at(uv)
            return {"outside_px": float(self._mean(outside)), "uncovered_px": float(self._mean(uncovered))}

    def _mean(self, per_point: torch.Tensor) -> torch.Tensor:
        """Mean of (N, P) values over the frames that have a mask."""
        total = (self.frame_weight.sum() * per_point.shape[1]).clamp_min(1.0)
        return (self.frame_weight[:, None] * per_point).sum() / total


def _distance_maps(inside: np.ndarray) -> tuple[np.ndarray, float]:
    """(N, h, w) float32 distances in frame px to each mask (N, H, W) bool, and the frame px per
    map px (the maps shrunk to at most DISTANCE_MAP_SIDE on a side)."""
    scale, size = shrunk_size(*inside.shape[1:], DISTANCE_MAP_SIDE)
    maps = []
    for mask in inside:
        small = mask if scale == 1.0 else cv2.resize(mask.astype(np.float32), size, interpolation=cv2.INTER_AREA) >= 0.5
        maps.append(cv2.distanceTransform((~small).astype(np.uint8), cv2.DIST_L2, 5) * np.float32(scale))
    return np.stack(maps).astype(np.float32), float(scale)


def contour_points(mask: np.ndarray, count: int) -> np.ndarray:
    """(count, 2) float (x, y) evenly spaced along the outer outline of the mask's largest region."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return np.zeros((count, 2))
    outline = max(contours, key=cv2.contourArea)[:, 0].astype(np.float64)
    return outline[np.linspace(0, len(outline) - 1, count).round().astype(int)]


def spread_subset(points: np.ndarray, count: int) -> np.ndarray:
    """Indices of up to `count` of `points` (P, 3) spread evenly over them (farthest-point
    sampling from the first point; deterministic)."""
    count = min(count, len(points))
    chosen = np.zeros(count, dtype=np.int64)
    nearest = np.full(len(points), np.inf)
    for i in range(1, count):
        nearest = np.minimum(nearest, np.linalg.norm(points - points[chosen[i - 1]], axis=1))
        chosen[i] = int(nearest.argmax())
    return chosen
