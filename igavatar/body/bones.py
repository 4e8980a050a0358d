"""A skeleton's bones as geometry: its kind, left/right sides, and the segments each joint moves.

    kind = skeleton_kind(skeleton)                                 # 'smpl', 'anny' or None
    segments = bone_segments(joints_canonical, skeleton.parents, leaf_lengths(skeleton, kind))

Used where a skeleton comes without a template mesh: skinning weights from the distance to the
bones (igavatar.skinning.bone_weights) and a shape prior of capsules around them
(igavatar.body.capsules). The segments of joint j are the lines from j to each of its children
(the part of the body j's transform moves, as in SMPL); a leaf joint (head, hand, foot tip) gets
one segment continuing its parent's bone, so that it moves something too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from igavatar.body.motions import semantic_joint_map
from igavatar.body.skeleton import SMPL_JOINT_NAMES, SMPL_PARENTS, Skeleton

#: Length (meters, adult scale) of the segment beyond each leaf joint of the SMPL tree: the
#: head joint sits at the skull base (the crown is ~0.2 m higher), the hand joint at the knuckles,
#: the foot joint at the ball of the foot.
SMPL_LEAF_LENGTHS_M: dict[str, float] = {
    "head": 0.12, "left_hand": 0.08, "right_hand": 0.08, "left_foot": 0.06, "right_foot": 0.06,
}
#: Leaf segments of skeletons of unknown kind are this fraction of the parent bone.
LEAF_LENGTH_FRACTION = 0.5
#: Nominal thigh + shin length (m) of the adult the meter tables above are written for.
NOMINAL_LEG_LENGTH_M = 0.82


@dataclass(frozen=True)
class BoneSegments:
    """Line segments rigidly attached to joints (float64 numpy).

    Attributes:
        joint: (B,) int64, the joint whose transform moves segment b.
        start: (B, 3) segment starts (the joint's position).
        end: (B, 3) segment ends (a child joint, or the tip of a leaf's extension).
    """

    joint: np.ndarray
    start: np.ndarray
    end: np.ndarray


def skeleton_kind(skeleton: Skeleton) -> str | None:
    """'smpl' for SMPL's 24-joint tree with SMPL's names, 'anny' when every joint the Anny motions
    name is present (Anny's bone labels), else None (a skeleton of unknown kind)."""
    names = set(skeleton.joint_names)
    if tuple(skeleton.parents.tolist()) == SMPL_PARENTS and skeleton.joint_names == SMPL_JOINT_NAMES:
        return "smpl"
    if set(semantic_joint_map("anny").values()) <= names:
        return "anny"
    return None


def _side_of(name: str) -> int:
    """+1 for a left-side joint name, -1 for right, 0 otherwise (SMPL 'left_hip', Anny
    'upperleg01.L', and the common 'l_hip' / 'hip_l' / 'LeftUpLeg' spellings)."""
    lower = name.lower()
    for side, sign in (("left", 1), ("right", -1)):
        letter = side[0]
        if (
            lower.startswith((side, f"{letter}_", f"{letter}.")) or lower.endswith((f"_{letter}", f".{letter}"))
            or f"_{side}" in lower or f".{side}" in lower
        ):
            return sign
    return 0


def joint_sides(skeleton: Skeleton) -> np.ndarray:
    """(J,) int64: +1 for joints on the subject's left, -1 right, 0 on the midline (from names)."""
    return np.array([_side_of(name) for name in skeleton.joint_names], dtype=np.int64)


def midplane(joints: np.ndarray, sides: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The body's left/right symmetry plane, from the sided joints in one pose.

    Args:
        joints: (J, 3) joint positions.
        sides: (J,) from joint_sides.
    Returns:
        (point (3,), unit normal (3,) pointing to the subject's left), or None when the skeleton
        has no joints on both sides (or they coincide).
    """
    left, right = joints[sides > 0], joints[sides < 0]
    if len(left) == 0 or len(right) == 0:
        return None
    left_mean, right_mean = left.mean(axis=0), right.mean(axis=0)
    normal = left_mean - right_mean
    length = float(np.linalg.norm(normal))
    if length < 1e-6:
        return None
    return 0.5 * (left_mean + right_mean), normal / length


def children_of(parents: np.ndarray) -> list[list[int]]:
    """Children of each joint, in index order."""
    children: list[list[int]] = [[] for _ in range(len(parents))]
    for j, parent in enumerate(parents):
        if parent >= 0:
            children[int(parent)].append(j)
    return children


def leg_scale(skeleton: Skeleton, kind: str | None) -> float:
    """Size of the subject relative to the adult the meter tables are written for, from the
    rest thigh + shin lengths (1 for an unknown kind), clamped to [0.5, 1.5]."""
    if kind is None:
        return 1.0
    names = semantic_joint_map(kind)
    lengths = []
    for side in ("left", "right"):
        hip, knee, ankle = (skeleton.rest_joints[skeleton.index(names[f"{side}_{part}"])] for part in ("thigh", "shin", "foot"))
        lengths.append(np.linalg.norm(knee - hip) + np.linalg.norm(ankle - knee))
    return float(np.clip(np.mean(lengths) / NOMINAL_LEG_LENGTH_M, 0.5, 1.5))


def leaf_lengths(skeleton: Skeleton, kind: str | None) -> np.ndarray:
    """(J,) length in meters of each leaf joint's extension segment (0 for inner joints).

    SMPL's leaves use SMPL_LEAF_LENGTHS_M scaled by leg_scale; other skeletons
    LEAF_LENGTH_FRACTION of the parent bone in the rest pose.
    """
    parents = skeleton.parents
    children = children_of(parents)
    lengths = np.zeros(skeleton.num_joints)
    scale = leg_scale(skeleton, kind)
    for j, name in enumerate(skeleton.joint_names):
        if children[j] or parents[j] < 0:
            continue
        if kind == "smpl" and name in SMPL_LEAF_LENGTHS_M:
            lengths[j] = SMPL_LEAF_LENGTHS_M[name] * scale
        else:
            bone = skeleton.rest_joints[j] - skeleton.rest_joints[parents[j]]
            lengths[j] = LEAF_LENGTH_FRACTION * float(np.linalg.norm(bone))
    return lengths


def bone_segments(joints: np.ndarray, parents: np.ndarray, leaf_length: np.ndarray) -> BoneSegments:
    """The segments each joint moves, in the pose given by `joints`.

    Args:
        joints: (J, 3) joint positions (e.g. canonical).
        parents: (J,) parent indices (root -1 at index 0).
        leaf_length: (J,) length of each leaf's extension along its parent's bone (from leaf_lengths).
    Returns:
        BoneSegments: one per (joint, child) pair and one per leaf; a lone root (J = 1) has none.
    """
    joints = np.asarray(joints, dtype=np.float64)
    children = children_of(np.asarray(parents))
    owner, start, end = [], [], []
    for j, kids in enumerate(children):
        for child in kids:
            owner.append(j)
            start.append(joints[j])
            end.append(joints[child])
        if not kids and parents[j] >= 0:
            direction = joints[j] - joints[parents[j]]
            norm = float(np.linalg.norm(direction))
            tip = joints[j] + (direction / norm * leaf_length[j] if norm > 1e-9 else 0.0)
            owner.append(j)
            start.append(joints[j])
            end.append(tip)
    return BoneSegments(
        joint=np.array(owner, dtype=np.int64),
        start=np.array(start, dtype=np.float64).reshape(-1, 3),
        end=np.array(end, dtype=np.float64).reshape(-1, 3),
    )


def segment_distances(points: np.ndarray, segments: BoneSegments) -> tuple[np.ndarray, np.ndarray]:
    """Distance from every point to every segment, and where along the segment it is closest.

    Args:
        points: (P, 3).
        segments: B segments.
    Returns:
        distance (P, B) and t (P, B): the unclamped position of the point's projection on each
        segment's line (0 at the start joint, 1 at the end); degenerate segments give t = 0.
    """
    points = np.asarray(points, dtype=np.float64)
    axis = segments.end - segments.start  # (B, 3)
    length2 = np.einsum("bi,bi->b", axis, axis)
    offset = points[:, None, :] - segments.start[None]  # (P, B, 3)
    t = np.einsum("pbi,bi->pb", offset, axis) / np.maximum(length2, 1e-18)
    closest = segments.start[None] + np.clip(t, 0.0, 1.0)[..., None] * axis[None]
    distance = np.linalg.norm(points[:, None, :] - closest, axis=-1)
    return distance, t
