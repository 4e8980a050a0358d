"""The 'skeleton' body model: a bare kinematic tree with per-frame rotations, no mesh.

    subject = skeleton_subject(capture)        # PosedSubject with template_* = None

poses.npz (DATA.md 1d): parents (J,), rest_joints (J, 3), rotvecs (N, J, 3), transl (N, 3),
joint_names (J,) optional. The canonical pose is a star pose with the legs spread when the
skeleton's kind is known (SMPL's tree, Anny's labels; igavatar.body.bones.skeleton_kind), else the
rest pose. Skinning weights and the shape prior then come from the bones (preprocess).
"""

from __future__ import annotations

import numpy as np
import torch

from igavatar.body.bones import skeleton_kind
from igavatar.body.motions import body_to_world, semantic_joint_map
from igavatar.body.rotations import axis_angle_to_matrix
from igavatar.body.skeleton import SMPL_JOINT_NAMES, SMPL_PARENTS, Skeleton
from igavatar.capture.capture_v1 import CaptureV1
from igavatar.capture.posed_subject import PosedSubject, major_bones
from igavatar.errors import InputError

#: Hip abduction (rad) of the canonical star pose, per skeleton kind: Fast-SNARF's 0.5 for SMPL's
#: T-pose; Anny's 0.4 as AnnyBody.canonical_star_pose, so both share one canonical space.
STAR_LEG_SPREAD = {"smpl": 0.5, "anny": 0.4}
#: How many bones root finding starts from in a skeleton of unknown kind (SMPL's 13 plus one,
#: as ROOT_FINDING_PARTS).
GENERIC_INIT_BONES = 14


def star_pose(skeleton: Skeleton, kind: str | None) -> torch.Tensor:
    """(J, 3, 3) float32 canonical rotations: both hips abducted by STAR_LEG_SPREAD[kind] about the
    body's forward axis so that the legs do not touch in canonical space; the rest pose (identity)
    for a skeleton of unknown kind, whose legs igavatar cannot name."""
    rotvecs = torch.zeros(skeleton.num_joints, 3, dtype=torch.float64)
    if kind is not None:
        names = semantic_joint_map(kind)
        forward = torch.as_tensor(body_to_world(kind)[:, 2])
        spread = STAR_LEG_SPREAD[kind]
        # A positive rotation about the forward axis swings a downward limb towards the subject's left.
        rotvecs[skeleton.index(names["left_thigh"])] = spread * forward
        rotvecs[skeleton.index(names["right_thigh"])] = -spread * forward
    return axis_angle_to_matrix(rotvecs).to(torch.float32)


def longest_bones(skeleton: Skeleton, count: int = GENERIC_INIT_BONES) -> tuple[int, ...]:
    """Root-finding start bones of a skeleton of unknown kind: the root plus the `count - 1`
    joints with the longest bones to a child (these move the most of the body; ties go to the
    joint with more descendants). Every joint when J <= count."""
    if skeleton.num_joints <= count:
        return tuple(range(skeleton.num_joints))
    rest, parents = skeleton.rest_joints, skeleton.parents
    longest = np.zeros(skeleton.num_joints)
    for j in range(1, skeleton.num_joints):
        longest[parents[j]] = max(longest[parents[j]], float(np.linalg.norm(rest[j] - rest[parents[j]])))
    descendants = np.array([len(skeleton.descendants(j)) for j in range(skeleton.num_joints)])
    order = sorted(range(1, skeleton.num_joints), key=lambda j: (-longest[j], -descendants[j], j))
    return tuple(sorted({0, *order[: count - 1]}))


def _source(capture: CaptureV1) -> str:
    if capture.input_format == "capture-v1":
        return str(capture.root / "poses.npz")
    return f"{capture.root} ({capture.input_format})"


def _joint_names(capture: CaptureV1, parents: np.ndarray) -> tuple[str, ...]:
    """joint_names from poses.npz; SMPL's names for SMPL's tree; else joint_00, joint_01, ..."""
    if "joint_names" in capture.poses:
        names = np.asarray(capture.poses["joint_names"])
        if names.shape != parents.shape or names.dtype.kind not in "US":
            raise InputError(
                f"{_source(capture)}: key 'joint_names' has shape {names.shape} and dtype {names.dtype}, "
                f"expected ({parents.shape[0]},) strings, one per joint"
            )
        return tuple(str(n) for n in names)
    if tuple(parents.tolist()) == SMPL_PARENTS:
        return SMPL_JOINT_NAMES
    return tuple(f"joint_{j:02d}" for j in range(parents.shape[0]))


def skeleton_subject(capture: CaptureV1) -> PosedSubject:
    """PosedSubject of a capture whose body model is 'skeleton' (shapes checked by the reader).

    Raises:
        InputError: parents that are not one tree with parents before children, non-integer
            parents, bad joint names (naming poses.npz and the key).
    """
    poses = capture.poses
    parents = np.asarray(poses["parents"])
    if parents.dtype.kind not in "iu":
        raise InputError(f"{_source(capture)}: key 'parents' has dtype {parents.dtype}, expected integers (root -1)")
    parents = parents.astype(np.int64)
    for key in ("rest_joints", "rotvecs", "transl"):
        if np.asarray(poses[key]).dtype.kind not in "iuf":
            raise InputError(f"{_source(capture)}: key '{key}' has dtype {np.asarray(poses[key]).dtype}, expected numbers")
    names = _joint_names(capture, parents)
    try:
        skeleton = Skeleton(parents, np.asarray(poses["rest_joints"], dtype=np.float64), names)
    except InputError as error:
        raise InputError(f"{_source(capture)}: {error}") from None
    rotvecs = torch.as_tensor(np.asarray(poses["rotvecs"], dtype=np.float64))
    transl = torch.as_tensor(np.asarray(poses["transl"], dtype=np.float64))
    kind = skeleton_kind(skeleton)
    return PosedSubject(
        body_model="skeleton",
        skeleton=skeleton,
        local_rotations=axis_angle_to_matrix(rotvecs).to(torch.float32),
        root_translation=transl.to(torch.float32),
        canonical_rotations=star_pose(skeleton, kind),
        template_vertices_rest=None,
        template_faces=None,
        template_weights=None,
        description={"skeleton_kind": kind or "unknown"},
        init_bones=major_bones(skeleton, kind) if kind is not None else longest_bones(skeleton),
    )
