"""Kinematic skeletons, forward kinematics and linear blend skinning (pure torch functions).

    G = forward_kinematics(local_rotations, skeleton.rest_joints, skeleton.parents, root_translation)
    x_posed = linear_blend_skinning(x_canonical, weights, bone_transforms(G, G_canonical))

Convention (SMPL's): every joint's rest frame is world-aligned, and `local_rotations[..., j, :, :]`
rotates joint j's subtree about joint j's rest position, relative to the rest pose and expressed in
the parent's (world-aligned at rest) frame. The global transform of joint j is
`G_j = G_parent(j) @ [R_j | rest_j - rest_parent(j)]`, with `G_root = [R_root | rest_root + t]`, so a
point x rigidly attached to joint j in the rest pose moves to `G_j @ [x - rest_j; 1]`. Shapes: J joints,
V vertices, leading `...` batch dimensions (usually N frames).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from igavatar.body.rotations import invert_rigid, rigid_matrix
from igavatar.errors import InputError


def _validate_parents(parents: np.ndarray, what: str) -> None:
    """Raise InputError unless `parents` is one tree rooted at index 0 with parents before children."""
    if parents.ndim != 1 or parents.shape[0] == 0:
        raise InputError(f"{what}: parents has shape {parents.shape}, expected (J,) with J >= 1")
    num_joints = parents.shape[0]
    bad = np.flatnonzero((parents < -1) | (parents >= num_joints))
    if bad.size:
        j = int(bad[0])
        raise InputError(
            f"{what}: parents[{j}] = {int(parents[j])} is not a joint index in [-1, {num_joints - 1}]"
        )
    if parents[0] != -1:
        raise InputError(f"{what}: parents[0] = {int(parents[0])}, expected -1 (joint 0 is the root)")
    roots = np.flatnonzero(parents == -1)
    if roots.size > 1:
        raise InputError(
            f"{what}: joints {roots.tolist()} all have parent -1; expected a single root at index 0"
        )
    self_parent = np.flatnonzero(parents == np.arange(num_joints))
    if self_parent.size:
        j = int(self_parent[0])
        raise InputError(f"{what}: joint {j} is its own parent (parents[{j}] = {j}): cycle")
    late = np.flatnonzero(parents[1:] >= np.arange(1, num_joints))
    if late.size == 0:
        return
    # Parents out of order: report a cycle if there is one (a chain that never reaches the root
    # within J steps), since reordering cannot fix that.
    for j in range(num_joints):
        node, steps = j, 0
        while node != -1 and steps <= num_joints:
            node, steps = int(parents[node]), steps + 1
        if node != -1:
            raise InputError(
                f"{what}: the parent chain of joint {j} never reaches the root (a cycle in parents)"
            )
    j = int(late[0]) + 1
    raise InputError(
        f"{what}: joint {j} has parent {int(parents[j])}, which comes after it; "
        "reorder the joints so that every parent precedes its children"
    )


@dataclass(frozen=True, eq=False)
class Skeleton:
    """A kinematic tree with its rest (identity-rotation) joint positions.

    Attributes:
        parents: (J,) int64, parents[0] = -1 (the root), parents[j] < j otherwise.
        rest_joints: (J, 3) float64 joint positions in meters in the rest pose (world axes).
        joint_names: J distinct names.
    Arrays are copied and made read-only, so a Skeleton is an immutable value.
    """

    parents: np.ndarray
    rest_joints: np.ndarray
    joint_names: tuple[str, ...]

    def __post_init__(self) -> None:
        parents_in = np.asarray(self.parents)
        if parents_in.size and not np.issubdtype(parents_in.dtype, np.integer):
            if not np.all(np.equal(np.mod(parents_in, 1), 0)):
                raise InputError(f"skeleton: parents must be integers, got dtype {parents_in.dtype}")
        parents = parents_in.astype(np.int64).copy()
        _validate_parents(parents, "skeleton")
        num_joints = parents.shape[0]
        rest_joints = np.array(self.rest_joints, dtype=np.float64)
        if rest_joints.shape != (num_joints, 3):
            raise InputError(
                f"skeleton: rest_joints has shape {rest_joints.shape}, expected ({num_joints}, 3) "
                "to match parents"
            )
        if not np.all(np.isfinite(rest_joints)):
            raise InputError("skeleton: rest_joints contains NaN or infinite values")
        names = tuple(str(name) for name in self.joint_names)
        if len(names) != num_joints:
            raise InputError(
                f"skeleton: {len(names)} joint_names for {num_joints} joints; expected one name per joint"
            )
        if len(set(names)) != num_joints:
            duplicates = sorted({n for n in names if names.count(n) > 1})
            raise InputError(f"skeleton: duplicate joint names {duplicates}")
        parents.setflags(write=False)
        rest_joints.setflags(write=False)
        object.__setattr__(self, "parents", parents)
        object.__setattr__(self, "rest_joints", rest_joints)
        object.__setattr__(self, "joint_names", names)

    @property
    def num_joints(self) -> int:
        """J, the number of joints."""
        return int(self.parents.shape[0])

    def index(self, name: str) -> int:
        """Index of the joint called `name`; InputError listing a few names if there is none."""
        try:
            return self.joint_names.index(name)
        except ValueError:
            shown = ", ".join(self.joint_names[:8])
            raise InputError(
                f"skeleton has no joint named {name!r} (joints: {shown}"
                f"{', ...' if self.num_joints > 8 else ''})"
            ) from None

    def descendants(self, joint: int) -> np.ndarray:
        """Sorted indices of `joint` and every joint below it in the tree, (K,) int64."""
        inside = np.zeros(self.num_joints, dtype=bool)
        inside[joint] = True
        # Parents precede children, so one forward pass marks whole subtrees.
        for j in range(joint + 1, self.num_joints):
            inside[j] = inside[self.parents[j]]
        return np.flatnonzero(inside)

    def rest_joints_tensor(
        self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
    ) -> torch.Tensor:
        """rest_joints as a (J, 3) tensor (a copy)."""
        return torch.tensor(self.rest_joints, dtype=dtype, device=device)


@functools.lru_cache(maxsize=64)
def _depth_levels(parents: tuple[int, ...]) -> tuple[list[tuple[np.ndarray, np.ndarray]], np.ndarray]:
    """The FK schedule of a tree: per depth level (its joints, each one's parent's slot in the
    previous level), root level first; and the permutation from level order back to joint order.
    Validates the tree first (lru_cache does not cache the exception)."""
    _validate_parents(np.asarray(parents, dtype=np.int64), "forward_kinematics")
    depth = np.zeros(len(parents), dtype=np.int64)
    for j in range(1, len(parents)):
        depth[j] = depth[parents[j]] + 1
    levels = []
    previous_slot: dict[int, int] = {}
    for d in range(int(depth.max()) + 1):
        joints = np.flatnonzero(depth == d)
        parent_slots = np.array([previous_slot[parents[j]] for j in joints] if d else [0], dtype=np.int64)
        levels.append((joints, parent_slots))
        previous_slot = {int(j): i for i, j in enumerate(joints)}
    order = np.concatenate([joints for joints, _ in levels])
    return levels, np.argsort(order)


def _parents_tuple(parents: Sequence[int] | np.ndarray | torch.Tensor) -> tuple[int, ...]:
    if isinstance(parents, torch.Tensor):
        parents = parents.detach().cpu().numpy()
    return tuple(int(p) for p in np.asarray(parents, dtype=np.int64).reshape(-1))


def forward_kinematics(
    local_rotations: torch.Tensor,
    rest_joints: torch.Tensor | np.ndarray,
    parents: Sequence[int] | np.ndarray | torch.Tensor,
    root_translation: torch.Tensor | None = None,
) -> torch.Tensor:
    """Global joint transforms of a posed skeleton.

    Args:
        local_rotations: (..., J, 3, 3) rotation of each joint relative to the rest pose, in the
            parent's world-aligned rest frame (SMPL convention); identity everywhere = rest pose.
        rest_joints: (J, 3) rest joint positions in meters (tensor or array).
        parents: (J,) parent indices, -1 for the root at index 0, parents before children.
        root_translation: (..., 3) world translation added to the root, or None for zero.
    Returns:
        (..., J, 4, 4) global transforms G_j: G_j @ [x - rest_j; 1] poses a point x attached to
        joint j; at the rest pose G_j = [I | rest_j + t].
    """
    parents_key = _parents_tuple(parents)
    num_joints = len(parents_key)
    if local_rotations.shape[-3:] != (num_joints, 3, 3):
        raise InputError(
            f"forward_kinematics: local_rotations has shape {tuple(local_rotations.shape)}, "
            f"expected (..., {num_joints}, 3, 3)"
        )
    if isinstance(rest_joints, np.ndarray):
        rest_joints = np.array(rest_joints)  # a writable copy: torch warns about read-only arrays
    rest = torch.as_tensor(rest_joints, dtype=local_rotations.dtype, device=local_rotations.device)
    if rest.shape != (num_joints, 3):
        raise InputError(
            f"forward_kinematics: rest_joints has shape {tuple(rest.shape)}, expected ({num_joints}, 3)"
        )
    batch = local_rotations.shape[:-3]
    if root_translation is not None:
        if root_translation.shape[-1:] != (3,):
            raise InputError(
                f"forward_kinematics: root_translation has shape {tuple(root_translation.shape)}, "
                "expected (..., 3)"
            )
        batch = torch.broadcast_shapes(batch, root_translation.shape[:-1])
    # Offsets of each joint from its parent at rest; the root's "offset" is its absolute position.
    parent_index = torch.tensor(parents_key[1:], dtype=torch.long, device=rest.device)
    offsets = torch.cat((rest[:1], rest[1:] - rest[parent_index]), dim=0).expand(batch + (num_joints, 3))
    if root_translation is not None:
        root_offset = offsets[..., 0, :] + root_translation
        offsets = torch.cat((root_offset[..., None, :], offsets[..., 1:, :]), dim=-2)
    local = rigid_matrix(local_rotations.expand(batch + (num_joints, 3, 3)), offsets)

    # One batched product per depth level instead of one per joint.
    levels, inverse = _depth_levels(parents_key)
    device = rest.device
    by_level = [local[..., torch.as_tensor(levels[0][0], device=device), :, :]]
    for joints, parent_slots in levels[1:]:
        parent_global = by_level[-1][..., torch.as_tensor(parent_slots, device=device), :, :]
        by_level.append(parent_global @ local[..., torch.as_tensor(joints, device=device), :, :])
    return torch.cat(by_level, dim=-3)[..., torch.as_tensor(inverse, device=device), :, :]


def bone_transforms(global_posed: torch.Tensor, global_canonical: torch.Tensor) -> torch.Tensor:
    """Transforms taking canonical-space points attached to each bone to posed world space.

    Args:
        global_posed: (..., J, 4, 4) forward_kinematics of the target pose.
        global_canonical: (..., J, 4, 4) forward_kinematics of the canonical pose (broadcasts).
    Returns:
        (..., J, 4, 4) B_j = G_j(pose) @ inverse(G_j(canonical)); includes the root motion.
    """
    return global_posed @ invert_rigid(global_canonical)


def linear_blend_skinning(
    x: torch.Tensor, weights: torch.Tensor, bone_transforms: torch.Tensor
) -> torch.Tensor:
    """Linear blend skinning: x_posed = sum_j w_j B_j x.

    Args:
        x: (..., V, 3) points (usually canonical space).
        weights: (V, J) or (..., V, J) skinning weights (rows normally sum to 1).
        bone_transforms: (..., J, 4, 4) per-bone rigid transforms (see bone_transforms()).
    Returns:
        (..., V, 3) transformed points; leading dimensions of the three inputs broadcast.
    """
    num_joints = bone_transforms.shape[-3]
    if weights.shape[-1] != num_joints:
        raise InputError(
            f"linear_blend_skinning: weights has shape {tuple(weights.shape)} but bone_transforms "
            f"has {num_joints} joints; expected (..., V, {num_joints})"
        )
    if x.shape[-1] != 3 or weights.shape[-2] != x.shape[-2]:
        raise InputError(
            f"linear_blend_skinning: x has shape {tuple(x.shape)} and weights {tuple(weights.shape)}; "
            "expected (..., V, 3) and (..., V, J) with the same V"
        )
    # Blend the 3x4 matrices first (V x 12 numbers) rather than transforming every point by every bone.
    rows = bone_transforms[..., :3, :].flatten(-2)  # (..., J, 12)
    blended = (weights @ rows).unflatten(-1, (3, 4))  # (..., V, 3, 4)
    return (blended[..., :3] @ x[..., None])[..., 0] + blended[..., 3]


SMPL_JOINT_NAMES: tuple[str, ...] = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "left_hand", "right_hand",
)
"""The 24 SMPL joints in SMPL's order (rest pose: T-pose, +Y up, the face looks towards +Z)."""

SMPL_PARENTS: tuple[int, ...] = (
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21,
)
"""SMPL's standard kinematic tree (parent of each joint in SMPL_JOINT_NAMES order)."""

#: A plausible neutral SMPL T-pose (meters; +Y up, the face towards +Z, the subject's left at +X),
#: typed by hand, not taken from the licensed model (retargeting uses only its bone directions).
NOMINAL_SMPL_REST_JOINTS = np.array([
    [0.000, -0.240, 0.030], [0.060, -0.330, 0.015], [-0.060, -0.330, 0.015], [0.000, -0.115, -0.005],
    [0.105, -0.720, 0.015], [-0.105, -0.720, 0.015], [0.005, 0.020, 0.025], [0.090, -1.150, -0.020],
    [-0.090, -1.150, -0.020], [0.005, 0.075, 0.030], [0.120, -1.210, 0.100], [-0.120, -1.210, 0.100],
    [0.000, 0.290, -0.015], [0.080, 0.190, -0.015], [-0.080, 0.190, -0.015], [0.005, 0.360, 0.040],
    [0.175, 0.230, -0.015], [-0.175, 0.230, -0.015], [0.430, 0.215, -0.035], [-0.430, 0.215, -0.035],
    [0.685, 0.220, -0.040], [-0.685, 0.220, -0.040], [0.765, 0.210, -0.050], [-0.765, 0.210, -0.050],
])

