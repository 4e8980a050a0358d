"""A body, posed: the skeleton, per-frame joint rotations and (if any) a template mesh.

    canonical = canonicalize(subject)      # bone transforms, canonical template, boxes
    frames = pose_frames(parents, rest_joints, canonical_rotations, local_rotations, root_translation)

Each body model of capture v1 becomes the same `PosedSubject` (igavatar.capture.subject makes it),
so everything downstream (skinning grid, dataset, training) is body-model agnostic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from igavatar.body.motions import ROOT_FINDING_PARTS, semantic_joint_map
from igavatar.body.rotations import invert_rigid, matrix_to_axis_angle
from igavatar.body.skeleton import Skeleton, bone_transforms, forward_kinematics, linear_blend_skinning


@dataclass(frozen=True)
class PosedSubject:
    """A body model evaluated for every frame of a capture (float32 CPU tensors).

    Attributes:
        body_model: 'anny', 'smpl' or 'skeleton'.
        skeleton: joints (J) with rest positions.
        local_rotations: (N, J, 3, 3) per-frame rotations relative to the rest pose.
        root_translation: (N, 3) per-frame root translation in world coordinates.
        canonical_rotations: (J, 3, 3) the canonical (star) pose relative to the rest pose.
        template_vertices_rest: (V, 3) template in the rest pose, or None (no shape prior).
        template_faces: (F, 3) int64, or None.
        template_weights: (V, J) skinning weights of the template, or None.
        description: JSON-able facts recorded in the dataset (e.g. the phenotype).
        init_bones: joint indices root finding starts from (the body's major bones).
    """

    body_model: str
    skeleton: Skeleton
    local_rotations: torch.Tensor
    root_translation: torch.Tensor
    canonical_rotations: torch.Tensor
    template_vertices_rest: torch.Tensor | None
    template_faces: torch.Tensor | None
    template_weights: torch.Tensor | None
    description: dict
    init_bones: tuple[int, ...]


@dataclass(frozen=True)
class CanonicalSubject:
    """What training needs from the body, in canonical space (float32 CPU tensors).

    Attributes:
        canonical_joints: (J, 3) joint positions in the canonical pose.
        bone_transforms: (N, J, 4, 4) canonical -> posed world, per frame (root motion included).
        posed_joints: (N, J, 3) world joint positions per frame.
        pose_condition: (N, 3 * (J - 1)) axis-angle of the non-root joints (non-rigid input).
        template_vertices: (V, 3) canonical template, or None.
        posed_template_boxes: (N, 2, 3) world-space bounding boxes of the posed template (or of
            the posed joints when there is no template), unpadded.
    """

    canonical_joints: torch.Tensor
    bone_transforms: torch.Tensor
    posed_joints: torch.Tensor
    pose_condition: torch.Tensor
    template_vertices: torch.Tensor | None
    posed_template_boxes: torch.Tensor


def major_bones(skeleton: Skeleton, skeleton_kind: str) -> tuple[int, ...]:
    """Indices of the major bones (ROOT_FINDING_PARTS) in a skeleton of a known kind."""
    names = semantic_joint_map(skeleton_kind)
    return tuple(sorted({skeleton.index(names[part]) for part in ROOT_FINDING_PARTS}))


@dataclass(frozen=True)
class PosedFrames:
    """Bone transforms and conditioning of a pose sequence (float32 tensors).

    Attributes:
        bone_transforms: (N, J, 4, 4) canonical -> posed world.
        pose_condition: (N, 3 * (J - 1)) axis-angle of the non-root joints (non-rigid input).
        posed_joints: (N, J, 3) world joint positions.
    """

    bone_transforms: torch.Tensor
    pose_condition: torch.Tensor
    posed_joints: torch.Tensor


def pose_frames(
    parents: np.ndarray,
    rest_joints: torch.Tensor,
    canonical_rotations: torch.Tensor,
    local_rotations: torch.Tensor,
    root_translation: torch.Tensor,
) -> PosedFrames:
    """Pose a skeleton: local rotations (N, J, 3, 3) + root translation (N, 3) -> PosedFrames.

    `canonical_rotations` (J, 3, 3) is the canonical (star) pose the avatar lives in; every
    rotation is relative to the rest pose (`rest_joints` (J, 3)).
    """
    global_canonical = forward_kinematics(canonical_rotations, rest_joints, parents)
    global_posed = forward_kinematics(local_rotations, rest_joints, parents, root_translation)
    return PosedFrames(
        bone_transforms=bone_transforms(global_posed, global_canonical),
        pose_condition=matrix_to_axis_angle(local_rotations[:, 1:]).flatten(1),
        posed_joints=global_posed[..., :3, 3],
    )


def canonicalize(subject: PosedSubject) -> CanonicalSubject:
    """Bone transforms from the canonical pose to every frame, and the canonical template."""
    skeleton = subject.skeleton
    parents = skeleton.parents
    rest = skeleton.rest_joints_tensor()
    identity = torch.eye(3).expand(skeleton.num_joints, 3, 3)
    global_rest = forward_kinematics(identity, rest, parents)
    global_canonical = forward_kinematics(subject.canonical_rotations, rest, parents)
    frames = pose_frames(parents, rest, subject.canonical_rotations, subject.local_rotations, subject.root_translation)
    transforms = frames.bone_transforms

    template = None
    if subject.template_vertices_rest is not None:
        rest_to_canonical = global_canonical @ invert_rigid(global_rest)
        template = linear_blend_skinning(subject.template_vertices_rest, subject.template_weights, rest_to_canonical)
        posed = linear_blend_skinning(template, subject.template_weights, transforms)
        boxes = torch.stack((posed.amin(dim=1), posed.amax(dim=1)), dim=1)
    else:
        joints = frames.posed_joints
        boxes = torch.stack((joints.amin(dim=1), joints.amax(dim=1)), dim=1)

    return CanonicalSubject(
        canonical_joints=global_canonical[:, :3, 3],
        bone_transforms=transforms,
        posed_joints=frames.posed_joints,
        pose_condition=frames.pose_condition,
        template_vertices=template,
        posed_template_boxes=boxes,
    )
