"""The model's rigged (and optionally animated) GLB, shared by `export` and `animate`.

    write_model_glb(tmp / "avatar.glb", model, vertices, faces, colors, skin_weights,
                    influences=4, motion=(local_rotations, root_translation, fps))

Joint names, parents and the canonical joints (the bind pose) come from the model's subject;
the file is in glTF's +Y-up frame (`gltf_axes` of the model's body model, baked in); a motion
given relative to the skeleton's rest pose (as forward kinematics and `ModelArtifact.pose` take
it) is re-expressed relative to the canonical bind pose first.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from igavatar.mesh.gltf import gltf_axes, pose_relative_to_canonical, write_rigged_glb
from igavatar.avatar.model import ModelArtifact


def write_model_glb(
    path: Path,
    model: ModelArtifact,
    vertices: np.ndarray,
    faces: np.ndarray,
    colors: np.ndarray,
    skin_weights: np.ndarray,
    influences: int,
    motion: tuple[torch.Tensor, torch.Tensor, float] | None = None,
    texture: tuple[np.ndarray, bytes] | None = None,
) -> dict:
    """Write the GLB; returns the facts every manifest records about it.

    Args:
        vertices: (V, 3) canonical; faces: (F, 3); colors: (V, 3) uint8 sRGB.
        skin_weights: (V, J) full weights (the writer keeps the top `influences`).
        motion: optional (local_rotations (N, J, 3, 3) relative to the rest pose, root_translation
            (N, 3) in world meters, fps).
        texture: optional (uv (V, 2), PNG bytes) for a textured primitive.
    Returns:
        {"joints", "influences", "animation_frames", "fps", "up_axis", "world_to_gltf", "world_to_gltf_offset",
        "origin"}; x_gltf = world_to_gltf @ x_world + world_to_gltf_offset.
    """
    subject = model.subject
    parents = np.asarray(subject.parents, dtype=np.int64)
    axes = gltf_axes(model.axes_kind)
    animation = None
    if motion is not None:
        rotations, translation, fps = motion
        # GLB node rotations are relative to the bind (canonical) pose.
        relative, offset = pose_relative_to_canonical(
            rotations.double().cpu().numpy(), translation.double().cpu().numpy(),
            subject.canonical_rotations, np.zeros(3), parents,
        )
        animation = (relative, offset, float(fps))
    offset = write_rigged_glb(
        path, vertices, faces, colors, model.joint_names, parents,
        np.asarray(subject.canonical_joints, dtype=np.float64), skin_weights,
        world_to_gltf=axes, animation=animation, influences=influences, texture=texture,
    )
    return {
        "joints": len(model.joint_names), "influences": influences,
        "animation_frames": 0 if motion is None else int(motion[0].shape[0]),
        "fps": None if motion is None else float(motion[2]),
        "up_axis": "+Y", "world_to_gltf": axes.tolist(), "world_to_gltf_offset": [round(float(x), 6) for x in offset],
        "origin": "on the floor under the root joint",
    }
