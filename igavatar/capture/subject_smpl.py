"""A capture whose poses are SMPL parameters, posed with the user's SMPL model file.

    subject = smpl_subject(capture, Path("SMPL_NEUTRAL.pkl"))   # a PosedSubject, 24 joints
    canonical = canonicalize(subject)

poses.npz holds betas (10,), global_orient (N, 3), body_pose (N, 69), transl (N, 3). The skeleton's
rest joints are those of the shaped model, the template is the shaped T-pose mesh (pose blend
shapes are pose-dependent, so they are no part of a canonical template), and `transl` is the FK
root translation unchanged: smplx's world vertex R_root (v - J_root) + J_root + transl is what
igavatar's forward_kinematics gives a root-attached point.
"""

from __future__ import annotations

from pathlib import Path

import torch

from igavatar.body.smpl_model import load_smpl_model, require_smpl_model, smpl_local_rotations, smpl_star_pose
from igavatar.capture.capture_v1 import CaptureV1
from igavatar.capture.posed_subject import PosedSubject, major_bones


def smpl_model_for(capture: CaptureV1, smpl_model: Path | None) -> Path:
    """`smpl_model` if it is a file; else an InputError saying that the capture needs one."""
    where = capture.root / "poses.npz" if capture.input_format == "capture-v1" else capture.root
    return require_smpl_model(smpl_model, str(where))


def smpl_subject(capture: CaptureV1, smpl_model: Path | None) -> PosedSubject:
    """Pose the capture's SMPL body for every frame.

    Args:
        capture: a capture with body model 'smpl' (poses per capture_v1.POSE_LAYOUTS['smpl']).
        smpl_model: the user's SMPL model file (.pkl or .npz), or None.
    Raises:
        InputError: `smpl_model` is None, missing or not an SMPL model file.
    """
    path = smpl_model_for(capture, smpl_model)
    model = load_smpl_model(path)
    betas = torch.as_tensor(capture.poses["betas"], dtype=torch.float64)
    skeleton = model.skeleton(betas)
    rotations = smpl_local_rotations(capture.poses["global_orient"], capture.poses["body_pose"])
    description = {"smpl_model": path.name, "betas": [float(b) for b in betas]}
    if model.gender is not None:
        description["gender"] = model.gender
    return PosedSubject(
        body_model="smpl",
        skeleton=skeleton,
        local_rotations=rotations.to(torch.float32),
        root_translation=torch.as_tensor(capture.poses["transl"], dtype=torch.float32),
        canonical_rotations=smpl_star_pose(),
        template_vertices_rest=model.shaped_vertices(betas).to(torch.float32),
        template_faces=model.faces.clone(),
        template_weights=model.weights.to(torch.float32),
        description=description,
        init_bones=major_bones(skeleton, "smpl"),
    )
