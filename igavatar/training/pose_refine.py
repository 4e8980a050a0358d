"""Per-frame pose corrections optimised with the avatar (as InstantAvatar and Vid2Avatar do).

    refiner = PoseRefiner(data.bone_transforms, parents, rest_joints, canonical_rotations, data.train_indices)
    frame_transforms = refiner.bone_transforms(index)       # (J, 4, 4), differentiable
    loss = loss + refiner.regularization(index, weight)     # pulls the corrections towards 0

A dataset stores each frame's bone transforms B_j = G_j(pose) G_j(canonical)^-1 (canonical ->
posed world). From them and the skeleton the frame's local transforms L_j = G_parent^-1 G_j are
recovered once; a correction rotates each joint's local frame by R(dr_j) (about the joint, so its
subtree turns with it) and moves the root by dt:

    G'_root = T(dt) L_root R(dr_root),   G'_j = G'_parent L_j R(dr_j),   B'_j = G'_j G_j(canonical)^-1.

Only training frames get corrections; every other frame keeps its stored transforms exactly.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from igavatar.body.rotations import axis_angle_to_matrix, invert_rigid
from igavatar.body.skeleton import forward_kinematics
from igavatar.model.deformer import FastSnarfDeformer, PreparedFrame
from igavatar.render.sampler import RaySamples

#: The model artifact's file of refined training poses (written by `train` when it refines).
REFINED_POSES_FILE = "refined_poses.npz"


class PoseRefiner(torch.nn.Module):
    """Rotation corrections (T, K, 3) of K joints and root translation corrections (T, 3) for T
    training frames.

    Args:
        bone_transforms: (N, J, 4, 4) the dataset's canonical -> posed world transforms.
        parents: (J,) int, -1 at the root (index 0), parents before children.
        rest_joints: (J, 3) rest joints; canonical_rotations: (J, 3, 3) local rotations of the
            canonical pose (the dataset's subject arrays).
        frames: (T,) dataset indices of the frames that get corrections.
        joints: (K,) the joints whose rotations are corrected (None: all). The major bones that
            move much skin: the images say little about a finger or a twist bone, whose
            corrections then only wander.
    """

    def __init__(self, bone_transforms: torch.Tensor, parents: np.ndarray, rest_joints: np.ndarray,
                 canonical_rotations: np.ndarray, frames: torch.Tensor, joints: np.ndarray | None = None) -> None:
        super().__init__()
        parents = np.asarray(parents, dtype=np.int64)
        canonical = forward_kinematics(torch.as_tensor(canonical_rotations, dtype=torch.float64),
                                       torch.as_tensor(rest_joints, dtype=torch.float64), parents)
        base = bone_transforms[frames].to(torch.float64)
        global_posed = base @ canonical  # (T, J, 4, 4)
        parent_global = global_posed[:, np.maximum(parents, 0)]
        local = invert_rigid(parent_global) @ global_posed
        local[:, 0] = global_posed[:, 0]
        self.parents = tuple(int(p) for p in parents)
        self.register_buffer("local", local)
        self.register_buffer("canonical_inverse", invert_rigid(canonical))
        self.register_buffer("frames", frames.clone().long())
        slots = torch.full((int(bone_transforms.shape[0]),), -1, dtype=torch.long)
        slots[frames] = torch.arange(len(frames))
        self.register_buffer("slots", slots)
        joints = np.arange(len(parents)) if joints is None else np.unique(np.asarray(joints, dtype=np.int64))
        self.register_buffer("joints", torch.as_tensor(joints))
        self.rotation = torch.nn.Parameter(torch.zeros(len(frames), len(joints), 3, dtype=torch.float32))
        self.translation = torch.nn.Parameter(torch.zeros(len(frames), 3, dtype=torch.float32))
        self._levels = _levels(self.parents)

    def refines(self, index: int) -> bool:
        return 0 <= index < len(self.slots) and int(self.slots[index]) >= 0

    def bone_transforms(self, index: int) -> torch.Tensor:
        """(J, 4, 4) float32 corrected canonical -> posed transforms of dataset frame `index`."""
        slot = int(self.slots[index])
        return self._corrected(self.local[slot], self.rotation[slot], self.translation[slot]).float()

    def all_bone_transforms(self) -> torch.Tensor:
        """(T, J, 4, 4) float64 corrected transforms of every refined frame, in `frames` order (no grad)."""
        with torch.no_grad():
            return self.corrected_transforms()

    def corrected_transforms(self) -> torch.Tensor:
        """(T, J, 4, 4) float64 corrected canonical -> posed transforms of every refined frame, in
        `frames` order, differentiable in the corrections (every frame at once: one product per
        level of the skeleton instead of one per joint and frame, as `bone_transforms` does)."""
        frames, joints = self.local.shape[:2]
        correction = torch.eye(4, dtype=self.local.dtype, device=self.local.device).repeat(frames, joints, 1, 1)
        correction[:, self.joints, :3, :3] = axis_angle_to_matrix(self.rotation.to(self.local.dtype))
        local = self.local @ correction
        shift = torch.zeros_like(local[:, 0])
        shift[:, :3, 3] = self.translation.to(local.dtype)
        global_transforms = local.clone()
        global_transforms[:, 0] = local[:, 0] + shift
        parents = torch.as_tensor(self.parents, device=local.device)
        for level in self._levels:
            level = torch.as_tensor(level, device=local.device)
            global_transforms[:, level] = global_transforms[:, parents[level]] @ local[:, level]
        return global_transforms @ self.canonical_inverse

    def _corrected(self, local: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
        correction = torch.eye(4, dtype=local.dtype, device=local.device).repeat(len(local), 1, 1)
        correction[self.joints, :3, :3] = axis_angle_to_matrix(rotation.to(local.dtype))
        local = local @ correction
        shift = torch.zeros_like(local[0])
        shift[:3, 3] = translation.to(local.dtype)
        local = torch.cat((local[:1] + shift[None], local[1:]))
        global_transforms: list[torch.Tensor | None] = [None] * len(self.parents)
        global_transforms[0] = local[0]
        for joints in self._levels:
            for joint in joints:
                global_transforms[joint] = global_transforms[self.parents[joint]] @ local[joint]
        return torch.stack(global_transforms) @ self.canonical_inverse

    def regularization(self, index: int, rotation_weight: float, translation_scale_m: float) -> torch.Tensor:
        """Squared corrections of frame `index`: rotation_weight x (sum |dr_j|^2 + |dt / scale|^2)."""
        slot = int(self.slots[index])
        return rotation_weight * (self.rotation[slot].square().sum()
                                  + (self.translation[slot] / translation_scale_m).square().sum())

    def correction_magnitudes(self) -> dict[str, float]:
        """Mean joint rotation correction (degrees) and root translation correction (mm), for logs."""
        with torch.no_grad():
            angle = self.rotation.norm(dim=-1)
            return {"pose_rot_deg": float(np.degrees(float(angle.mean()))),
                    "pose_root_mm": float(1000 * self.translation.norm(dim=-1).mean())}


def _levels(parents: tuple[int, ...]) -> list[list[int]]:
    """Joints by depth below the root (depth 1 first), so parents are done before children."""
    depth = [0] * len(parents)
    for joint in range(1, len(parents)):
        depth[joint] = depth[parents[joint]] + 1
    return [[j for j in range(1, len(parents)) if depth[j] == d] for d in range(1, max(depth, default=0) + 1)]


def with_pose_gradient(deformer: FastSnarfDeformer, frame: PreparedFrame, samples: RaySamples, canonical: RaySamples,
                       x_rigid: torch.Tensor, max_samples: int, generator: torch.Generator) -> tuple[RaySamples, torch.Tensor]:
    """Canonical samples with implicit-function gradients w.r.t. the frame's bone transforms
    (deformer.attach_implicit_gradient), so the rendering loss reaches the pose corrections: root
    finding itself is not differentiable.

    Only `max_samples` random samples carry them, scaled by (all / chosen) so that their sum
    estimates the full gradient: the Jacobian and grid_sample's backward into the blended grid over
    every sample made a step 3-4x slower than one without refinement.

    Args:
        samples: the posed ray samples; canonical, x_rigid: what PosedAvatar.canonical_samples made
            of them ((M, 3) rigid correspondences of canonical.valid, in that order).
    Returns:
        canonical with its positions and x_rigid, equal in value, differentiable in the transforms.
    """
    x_posed = samples.positions[canonical.valid]
    total = x_rigid.shape[0]
    chosen = min(total, max_samples)
    if chosen == 0:
        return canonical, x_rigid
    pick = torch.randperm(total, generator=generator)[:chosen].to(x_rigid.device)
    attached = deformer.attach_implicit_gradient(x_rigid[pick], x_posed[pick], frame).to(x_rigid.dtype)
    # Value x_rigid, gradient (total / chosen) x the implicit one on the chosen samples.
    x_attached = x_rigid.detach().clone()
    x_attached[pick] = x_rigid[pick].detach() + (total / chosen) * (attached - attached.detach())
    positions = canonical.positions.clone()
    positions[canonical.valid] = x_attached
    return dataclasses.replace(canonical, positions=positions), x_attached
