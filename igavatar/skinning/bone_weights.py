"""Skinning weights from a skeleton's bones alone, for subjects without a template mesh.

    weights = bone_skinning_weights(points, joints_canonical, skeleton)         # (P, J)
    grid = build_bone_skinning_grid(joints_canonical, skeleton, box_min, box_max, (64, 16, 64))

A point's weights are a softmax over the joints of minus its (penalised) distance to each joint's
bone segments (igavatar.body.bones), divided by a temperature of a few centimeters: a point on a
bone takes (almost) all of its weight from it, and weights blend smoothly over a few centimeters
where bones meet. Distance alone goes wrong where a bone passes near a body part it does not
move, so two penalties add to the distance:
  - behind the joint: a bone's weight fades for points behind the plane through its joint that
    is normal to the bone (the side of its parent). The upper arm does not take the torso under
    the armpit, the thigh does not take the belly, the shin does not take the thigh.
  - across the midplane: a bone of the subject's left side does not take points right of the
    body's symmetry plane (and vice versa): the two thighs never share weight at the crotch.
The result is the same `(J, D, H, W)` grid layout `igavatar.skinning.grid.build_skinning_grid`
makes from a template, optionally blurred by `smooth_weights_grid`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from igavatar.body.bones import (
    BoneSegments,
    bone_segments,
    children_of,
    joint_sides,
    leaf_lengths,
    midplane,
    segment_distances,
    skeleton_kind,
)
from igavatar.body.skeleton import Skeleton
from igavatar.errors import InputError
from igavatar.skinning.grid import grid_point_positions, smooth_weights_grid

__all__ = ["BoneWeightConfig", "bone_skinning_weights", "build_bone_skinning_grid"]

# Points per chunk: the (P, B, 3) distance intermediates stay around 30 MB for 150 segments.
_CHUNK_POINTS = 8192


def _float64(values: torch.Tensor | np.ndarray) -> np.ndarray:
    """A float64 numpy copy of a tensor or array (read-only arrays welcome)."""
    if isinstance(values, torch.Tensor):
        return values.detach().cpu().double().numpy()
    return np.array(values, dtype=np.float64)


@dataclass(frozen=True)
class BoneWeightConfig:
    """How bone distances become weights (lengths in meters)."""

    temperature_m: float = 0.02
    """Softmax temperature: weights of two bones at distances d1 < d2 have the ratio
    exp((d2 - d1) / T), so blends span a few T around where bones meet."""
    behind_penalty: float = 1.0
    """Extra distance per meter a point lies behind a joint's plane (on its parent's side)."""
    midplane_penalty: float = 10.0
    """Extra distance per meter a point lies across the midplane from a sided bone."""
    smoothing_iterations: int = 2
    """3x3x3 box-blur passes over the grid (smooth_weights_grid), as the template grid gets."""


def _bone_directions(joints: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """(J, 3) unit direction of each joint's bone: the mean direction to its children, or its
    parent's bone continued for a leaf; zero for the root and where undefined."""
    children = children_of(parents)
    directions = np.zeros_like(joints)
    for j, kids in enumerate(children):
        if parents[j] < 0:
            continue  # the root moves everything: no side of it is "behind"
        if kids:
            vectors = joints[kids] - joints[j]
            vectors /= np.maximum(np.linalg.norm(vectors, axis=1, keepdims=True), 1e-12)
            direction = vectors.mean(axis=0)
        else:
            direction = joints[j] - joints[parents[j]]
        norm = float(np.linalg.norm(direction))
        if norm > 1e-6:
            directions[j] = direction / norm
    return directions


@dataclass(frozen=True)
class _Bones:
    """What the distances need, computed once per skeleton and pose."""

    joints: np.ndarray  # (J, 3)
    segments: BoneSegments
    directions: np.ndarray  # (J, 3) unit bone directions (zero: no "behind")
    sides: np.ndarray  # (J,) +1 left, -1 right, 0 midline
    plane: tuple[np.ndarray, np.ndarray] | None  # midplane point and left-pointing normal


def _bones(joints: np.ndarray, skeleton: Skeleton) -> _Bones:
    parents = skeleton.parents
    sides = joint_sides(skeleton)
    return _Bones(
        joints=joints,
        segments=bone_segments(joints, parents, leaf_lengths(skeleton, skeleton_kind(skeleton))),
        directions=_bone_directions(joints, parents),
        sides=sides,
        plane=midplane(joints, sides),
    )


def _penalised_distances(points: np.ndarray, bones: _Bones, config: BoneWeightConfig) -> np.ndarray:
    """(P, J) distance from each point to each joint's bone, plus the penalties (meters)."""
    distance, _ = segment_distances(points, bones.segments)
    per_joint = np.full((points.shape[0], bones.joints.shape[0]), np.inf)
    for b, j in enumerate(bones.segments.joint):
        per_joint[:, j] = np.minimum(per_joint[:, j], distance[:, b])

    behind = np.einsum("pji,ji->pj", points[:, None, :] - bones.joints[None], bones.directions)
    per_joint += config.behind_penalty * np.maximum(-behind, 0.0)

    if bones.plane is not None:
        lateral = (points - bones.plane[0]) @ bones.plane[1]  # (P,) > 0 on the subject's left
        per_joint += config.midplane_penalty * np.maximum(-bones.sides[None, :] * lateral[:, None], 0.0)
    return per_joint


def _check(joints: torch.Tensor | np.ndarray, skeleton: Skeleton, config: BoneWeightConfig) -> np.ndarray:
    joints_np = _float64(joints)
    if joints_np.shape != (skeleton.num_joints, 3):
        raise InputError(
            f"bone weights: joints have shape {joints_np.shape}, expected ({skeleton.num_joints}, 3) "
            "for the skeleton's joints"
        )
    if not np.all(np.isfinite(joints_np)):
        raise InputError("bone weights: joint positions contain NaN or infinite values")
    if config.temperature_m <= 0 or config.behind_penalty < 0 or config.midplane_penalty < 0:
        raise InputError(
            f"bone weights: temperature_m={config.temperature_m} must be > 0 and the penalties "
            f"({config.behind_penalty}, {config.midplane_penalty}) >= 0"
        )
    return joints_np


def bone_skinning_weights(
    points: torch.Tensor | np.ndarray,
    joints: torch.Tensor | np.ndarray,
    skeleton: Skeleton,
    config: BoneWeightConfig = BoneWeightConfig(),
) -> torch.Tensor:
    """Skinning weights of points from their distances to the bones (no smoothing).

    Args:
        points: (P, 3) points in the pose of `joints` (usually canonical).
        joints: (J, 3) joint positions in that pose.
        skeleton: the tree (parents, names: sides and kind come from the names).
        config: temperature and penalties.
    Returns:
        (P, J) float32 CPU weights: non-negative, each row summing to 1.
    """
    joints_np = _check(joints, skeleton, config)
    points_np = _float64(points)
    if points_np.ndim != 2 or points_np.shape[1] != 3:
        raise InputError(f"bone weights: points have shape {points_np.shape}, expected (P, 3)")
    if skeleton.num_joints == 1:
        return torch.ones(points_np.shape[0], 1)
    bones = _bones(joints_np, skeleton)
    chunks = []
    for lo in range(0, points_np.shape[0], _CHUNK_POINTS):
        distance = _penalised_distances(points_np[lo : lo + _CHUNK_POINTS], bones, config)
        logits = -distance / config.temperature_m
        logits -= logits.max(axis=1, keepdims=True)  # a stable softmax: far points do not underflow to 0/0
        weights = np.exp(logits)
        chunks.append(weights / weights.sum(axis=1, keepdims=True))
    weights = np.concatenate(chunks) if chunks else np.zeros((0, skeleton.num_joints))
    return torch.from_numpy(weights).to(torch.float32)


def build_bone_skinning_grid(
    joints: torch.Tensor | np.ndarray,
    skeleton: Skeleton,
    box_min: torch.Tensor,
    box_max: torch.Tensor,
    resolution: Sequence[int],
    config: BoneWeightConfig = BoneWeightConfig(),
) -> torch.Tensor:
    """Skinning-weight grid over a canonical box from the bones (cf. build_skinning_grid).

    Args:
        joints: (J, 3) canonical joint positions.
        skeleton: the tree.
        box_min, box_max: (3,) grid box, e.g. from `canonical_grid_box`.
        resolution: (D, H, W) voxel counts along z, y, x.
        config: temperature, penalties and smoothing.
    Returns:
        (J, D, H, W) float32 CPU weights, non-negative, summing to 1 at every voxel.
    """
    box_min = torch.as_tensor(box_min).detach().cpu().double()
    box_max = torch.as_tensor(box_max).detach().cpu().double()
    if box_min.shape != (3,) or box_max.shape != (3,) or not bool((box_max > box_min).all()):
        raise InputError(
            f"bone weights: box_min {box_min.tolist()} / box_max {box_max.tolist()} must be (3,) "
            "with box_max above box_min on every axis"
        )
    positions = grid_point_positions(box_min, box_max, resolution)  # (D, H, W, 3)
    depth, height, width = positions.shape[:3]
    weights = bone_skinning_weights(positions.reshape(-1, 3), joints, skeleton, config)
    grid = weights.T.reshape(-1, depth, height, width).contiguous()
    return smooth_weights_grid(grid, config.smoothing_iterations).contiguous()
