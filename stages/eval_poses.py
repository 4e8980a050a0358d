"""`eval --refine-test-poses`: a test frame posed as refined against its own image, and the report's line.

    posed = refined_posed(record, model, dataset, test_frames, i, steps=60, seed=0)
    notes += refinement_notes(records)
"""

from __future__ import annotations

import time

import numpy as np
import torch

from igavatar.avatar.dataset import DatasetArtifact, DatasetFrames
from igavatar.avatar.model import ModelArtifact
from igavatar.model.posed import PosedAvatar
from igavatar.training.held_out_poses import HeldOutFrame, HeldOutPoseConfig, refine_frame_pose


def refined_posed(record: dict, model: ModelArtifact, dataset: DatasetArtifact, test: DatasetFrames, i: int,
                  steps: int, seed: int) -> PosedAvatar:
    """Test frame i of `test` posed as refined against its own image (for the image metrics only);
    the refinement and its time go into the frame's report `record`."""
    image, mask = dataset.image_and_mask(test.names[i])
    frame = HeldOutFrame(image, mask, test.K[i], test.w2c[i], test.bone_transforms[i], test.pose_condition[i],
                         test.posed_boxes[i])
    tick = time.perf_counter()
    refined = refine_frame_pose(model.avatar, model.canonical_grid, model.subject, frame, HeldOutPoseConfig(steps=steps),
                                model.config, seed=seed)
    record["seconds"]["pose_refinement"] = time.perf_counter() - tick
    record["pose_refinement"] = refined.record()
    return model.posed(torch.from_numpy(refined.bone_transforms), torch.from_numpy(test.pose_condition[i]))


def refinement_notes(records: list[dict]) -> list[str]:
    """One line on the test-time pose refinement when it ran (none otherwise)."""
    refined = [r["pose_refinement"] for r in records if r.get("pose_refinement")]
    if not refined:
        return []
    kept = [r for r in refined if r["kept"]]
    line = (f"test-time pose refinement (image metrics only; geometry uses the given poses): kept on {len(kept)} of "
            f"{len(refined)} rendered frames")
    if kept:
        line += (f", mean joint correction {np.mean([r['mean_joint_correction_deg'] for r in kept]):.2f} deg, "
                 f"root {np.mean([r['root_correction_mm'] for r in kept]):.1f} mm")
    return [line]
