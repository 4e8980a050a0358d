"""A capture's body, posed: each body model of capture v1 becomes the same `PosedSubject`.

    subject = subject_from_capture(capture, anny_cache=None, on_status=None)
    canonical = canonicalize(subject)      # bone transforms, canonical template, boxes

The types and posing functions live in igavatar.capture.posed_subject (re-exported here); this
module picks the body model's adapter (Anny here, SMPL and bare skeletons in their own modules).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import torch

from igavatar.capture.capture_v1 import CaptureV1
from igavatar.capture.posed_subject import (  # noqa: F401 (re-exported)
    CanonicalSubject,
    PosedFrames,
    PosedSubject,
    canonicalize,
    major_bones,
    pose_frames,
)
from igavatar.capture.subject_skeleton import skeleton_subject
from igavatar.capture.subject_smpl import smpl_subject


def _anny_subject(capture: CaptureV1, anny_cache: Path | None, on_status: Callable[[str], None] | None) -> PosedSubject:
    from igavatar.body.anny_body import AnnyBody

    labels = [str(label) for label in capture.poses["phenotype_labels"]]
    values = [float(v) for v in capture.poses["phenotype_values"]]
    body = AnnyBody.load(dict(zip(labels, values)), cache_dir=anny_cache, on_status=on_status)
    pose_parameters = torch.as_tensor(capture.poses["pose_parameters"], dtype=torch.float64)
    local_rotations, root_translation = body.local_rotations_from_pose_parameters(pose_parameters)
    return PosedSubject(
        body_model="anny",
        skeleton=body.skeleton,
        local_rotations=local_rotations.to(torch.float32),
        root_translation=root_translation.to(torch.float32),
        canonical_rotations=body.canonical_star_pose(),
        template_vertices_rest=body.rest_vertices,
        template_faces=body.faces,
        template_weights=body.skinning_weights,
        description={"phenotype": body.phenotype},
        init_bones=major_bones(body.skeleton, "anny"),
    )


def subject_from_capture(
    capture: CaptureV1,
    anny_cache: Path | None = None,
    on_status: Callable[[str], None] | None = None,
    smpl_model: Path | None = None,
) -> PosedSubject:
    """Evaluate the capture's body model for every frame.

    Args:
        anny_cache: Anny's cache directory (None: its default).
        smpl_model: the user's SMPL model file (.pkl/.npz), needed by captures with SMPL betas.

    Raises:
        BodyModelError / InputError: from the body model's adapter.
    """
    if capture.body_model == "anny":
        return _anny_subject(capture, anny_cache, on_status)
    if capture.body_model == "smpl":
        return smpl_subject(capture, smpl_model)
    return skeleton_subject(capture)
