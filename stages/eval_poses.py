"""How eval poses a test frame other than by the dataset's pose, and the report's lines on it:
`--carry-poses` (its refined neighbours' corrections) and `--refine-test-poses` (fitted to its own image).

    poses = carried_poses(model, dataset, test_frames, carry=True)   # poses[i]: (J, 4, 4); poses.record(i)
    posed = refined_posed(record, model, dataset, test_frames, i, poses[i], steps=60, seed=0)
    notes += carried_notes(records) + refinement_notes(records)
"""

from __future__ import annotations

import time

import numpy as np
import torch

from igavatar.avatar.dataset import DatasetArtifact, DatasetFrames
from igavatar.avatar.model import ModelArtifact
from igavatar.avatar.poses import model_frame_poses
from igavatar.model.posed import PosedAvatar
from igavatar.training.held_out_poses import HeldOutFrame, HeldOutPoseConfig, refine_frame_pose


def carried_poses(model: ModelArtifact, dataset: DatasetArtifact, test: DatasetFrames, carry: bool) -> CarriedTestPoses:
    """The test frames that take their refined neighbours' corrections (eval --carry-poses)."""
    given = torch.from_numpy(test.bone_transforms).float()
    own = model_frame_poses(model, dataset.path, list(test.names), given, carry=carry)
    return CarriedTestPoses({i: transforms.numpy() for i, transforms in own.carried.items()}, own.carried_sizes,
                            test.bone_transforms)


class CarriedTestPoses:
    """Test frame index -> (J, 4, 4) transforms: carried where the model gave one, else the dataset's."""

    def __init__(self, carried: dict[int, np.ndarray], sizes: dict[int, dict[str, float]], given: np.ndarray) -> None:
        self.carried, self.sizes, self.given = carried, sizes, given

    def __getitem__(self, i: int) -> np.ndarray:
        return self.carried.get(i, self.given[i])

    def record(self, i: int) -> dict | None:
        """The report's carried_pose of test frame i: the correction's size (None: the dataset's pose)."""
        return dict(self.sizes[i]) if i in self.carried else None


def refined_posed(record: dict, model: ModelArtifact, dataset: DatasetArtifact, test: DatasetFrames, i: int,
                  start_transforms: np.ndarray, steps: int, seed: int) -> PosedAvatar:
    """Test frame i of `test` posed as refined against its own image (for the image metrics only),
    from start_transforms (J, 4, 4); the refinement and its time go into the frame's report `record`."""
    image, mask = dataset.image_and_mask(test.names[i])
    frame = HeldOutFrame(image, mask, test.K[i], test.w2c[i], start_transforms, test.pose_condition[i],
                         test.posed_boxes[i])
    tick = time.perf_counter()
    refined = refine_frame_pose(model.avatar, model.canonical_grid, model.subject, frame, HeldOutPoseConfig(steps=steps),
                                model.config, seed=seed)
    record["seconds"]["pose_refinement"] = time.perf_counter() - tick
    record["pose_refinement"] = refined.record()
    return model.posed(torch.from_numpy(refined.bone_transforms), torch.from_numpy(test.pose_condition[i]))


def carried_notes(records: list[dict]) -> list[str]:
    """One line on the test frames posed by their refined neighbours' corrections (none when none were)."""
    carried = [r["carried_pose"] for r in records if r.get("carried_pose")]
    if not carried:
        return []
    return [f"test poses: {len(carried)} of {len(records)} test frames posed by the corrections that training found "
            f"for their neighbours in time (--carry-poses; no test image used), mean joint correction "
            f"{np.mean([c['mean_joint_correction_deg'] for c in carried]):.2f} deg, root "
            f"{np.mean([c['root_correction_mm'] for c in carried]):.1f} mm; the others keep the dataset's poses"]


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
