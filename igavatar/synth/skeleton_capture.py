"""The synthetic subject's poses written without its body model: as a bare skeleton, or as one root.

    arrays = bare_skeleton_poses(skeleton, local_rotations, root_translation)   # Anny's joints, no mesh
    arrays = root_only_poses(x_posed)                    # a static subject: one rigid root per frame

Both return the capture v1 'skeleton' poses.npz arrays (parents, rest_joints, rotvecs, transl,
joint_names). They let the benchmark measure the skeleton-only path (no template: the shape prior
comes from the masks) on subjects whose true surface is known.
"""

from __future__ import annotations

import numpy as np
import torch

from igavatar.body.rotations import matrix_to_axis_angle
from igavatar.body.skeleton import Skeleton

#: A static subject's frames must be rigid copies of the first to this many meters (RMS).
RIGID_TOLERANCE_M = 1e-4


def bare_skeleton_poses(skeleton: Skeleton, local_rotations: torch.Tensor, root_translation: torch.Tensor) -> dict[str, np.ndarray]:
    """The same skeleton and motion, as capture v1 'skeleton' arrays.

    Args:
        skeleton: the body's tree and rest joints (J joints).
        local_rotations: (N, J, 3, 3) per-frame local rotations.
        root_translation: (N, 3) per-frame root translation.
    """
    return {
        "parents": np.asarray(skeleton.parents, np.int64),
        "rest_joints": np.asarray(skeleton.rest_joints, np.float64),
        "rotvecs": matrix_to_axis_angle(local_rotations.double()).numpy(),
        "transl": root_translation.double().numpy(),
        "joint_names": np.array(skeleton.joint_names, dtype=np.str_),
    }


def rigid_fit(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares rotation R (3, 3) and translation t (3,) with target ~ source @ R.T + t (Kabsch),
    and the RMS residual in the points' units. source, target: (V, 3)."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    u, _, vt = np.linalg.svd((source - mu_s).T @ (target - mu_t))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rotation = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    translation = mu_t - mu_s @ rotation.T
    residual = float(np.sqrt(np.mean(np.sum((source @ rotation.T + translation - target) ** 2, axis=1))))
    return rotation, translation, residual


def root_only_poses(x_posed: np.ndarray) -> dict[str, np.ndarray]:
    """A skeleton of one joint that moves the first frame's surface rigidly onto every frame's.

    The joint sits at the first frame's centroid; canonical space is the first frame's world
    space (rest pose = identity rotation, no translation).

    Args:
        x_posed: (N, V, 3) the subject's surface in every frame; frames must be rigid copies.
    Raises:
        ValueError: a frame is not a rigid copy of the first (the subject moved its limbs).
    """
    first = np.asarray(x_posed[0], np.float64)
    joint = first.mean(0)
    rotvecs, transl = [], []
    for index, frame in enumerate(np.asarray(x_posed, np.float64)):
        rotation, translation, residual = rigid_fit(first, frame)
        if residual > RIGID_TOLERANCE_M:
            raise ValueError(f"frame {index} is not a rigid copy of frame 0 (RMS {residual * 1000:.2f} mm): not a static subject")
        rotvecs.append(matrix_to_axis_angle(torch.from_numpy(rotation))[None].numpy())
        # forward_kinematics places the root at rest_joint + transl and rotates about it:
        # x -> R (x - j) + j + transl, which equals R x + t when transl = t - j + R j.
        transl.append(translation - joint + rotation @ joint)
    return {
        "parents": np.array([-1], np.int64),
        "rest_joints": joint[None],
        "rotvecs": np.stack(rotvecs),
        "transl": np.stack(transl),
        "joint_names": np.array(["root"], dtype=np.str_),
    }
