"""Whole-frame pose alignment while training: each training frame's pose fitted to its own image
with the avatar frozen, a few times in a run.

    report = align_training_poses(avatar, canonical_grid, refiner, data, config, seed)
    report   # {"frames": T, "kept": k, "loss_before": ..., "loss_after": ..., "pose_rot_deg": ..., "pose_root_mm": ..., "seconds": ...}

Training's own pose step (igavatar.training.pose_refine, stepped in Trainer.train_step) sees a
frame on about steps / frames of the steps, through a few patches: every visit moves each
correction by about the rate whatever its gradient says, and on ZJU-MoCap 377 and a synthetic
clip with 5 degrees of pose noise the corrections stayed noise
(tests/benchmarks/results/zju377-registration.md, pose-noise.md). This does what
`eval --refine-test-poses` does for a held-out frame (igavatar.training.held_out_poses): many
steps of one frame's corrections against that frame alone, kept only if a fixed set of its pixels
is explained better. Run at a few points of training, the avatar made from noisy poses is already
their average, and each frame's pose moves towards it.

The pass is all or nothing: if it is interrupted (Ctrl-C), every correction is put back as it was,
so a checkpoint written then and `--resume` see the state before the pass, which runs again.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from igavatar.model.avatar import Avatar
from igavatar.render.occupancy import OccupancyGrid
from igavatar.training.config import TrainConfig
from igavatar.training.data import TrainingData
from igavatar.training.held_out_poses import HeldOutFrame, HeldOutPoseConfig, optimise_frame_pose
from igavatar.training.pose_refine import PoseRefiner


def pass_steps(config: TrainConfig, total_steps: int) -> list[int]:
    """The steps before which a run of `total_steps` makes its passes (config.pose_align_fractions;
    none when config.pose_align_steps is 0)."""
    if config.pose_align_steps == 0:
        return []
    return [int(fraction * total_steps) for fraction in config.pose_align_fractions]


def frame_of(data: TrainingData, index: int) -> HeldOutFrame:
    """Dataset frame `index` as held_out_poses reads one (numpy; its stored bone transforms)."""
    return HeldOutFrame(image=data.images[index].numpy(), mask=data.masks[index].numpy(), K=data.K[index].numpy(),
                        w2c=data.w2c[index].numpy(), bone_transforms=data.bone_transforms[index].numpy(),
                        pose_condition=data.pose_condition[index].numpy(), posed_box=data.posed_boxes[index].numpy())


def align_training_poses(avatar: Avatar, canonical_grid: OccupancyGrid, refiner: PoseRefiner, data: TrainingData,
                         config: TrainConfig, seed: int) -> dict:
    """One pass over the refiner's frames (see the module docstring); returns its summary for the
    model's manifest: frames fitted and kept, the fixed pixel sets' mean loss before and after (the
    better of the two per frame), the mean corrections after the pass, and its seconds.

    Args:
        avatar, canonical_grid: the avatar as trained so far (its weights are not stepped).
        refiner: the training run's pose corrections, changed in place (only kept frames move).
        data: the training frames; config: the run's TrainConfig (its pose_align_* fields and the
            rays, patches and loss weights a step uses).
        seed: the pass's seed (the same pass of a resumed run draws the same pixels).
    """
    started = time.perf_counter()
    fit_config = HeldOutPoseConfig(steps=config.pose_align_steps, learning_rate=config.pose_align_lr,
                                   prior_weight=config.pose_prior_weight,
                                   translation_scale_m=config.pose_translation_scale_m)
    saved = refiner.rotation.detach().clone(), refiner.translation.detach().clone()
    fits = []
    try:
        for slot, index in enumerate(refiner.frames.tolist()):
            fits.append(optimise_frame_pose(avatar, canonical_grid, refiner, index, frame_of(data, index), fit_config,
                                            config, seed=seed * 1_000_003 + slot))
    except BaseException:
        with torch.no_grad():
            refiner.rotation.copy_(saved[0])
            refiner.translation.copy_(saved[1])
        raise
    kept = [fit for fit in fits if fit.kept]
    before = [fit.loss_before for fit in fits if np.isfinite(fit.loss_before)]
    after = [min(fit.loss_before, fit.loss_after) for fit in fits if np.isfinite(fit.loss_before)]
    magnitudes = refiner.correction_magnitudes()
    return {"frames": len(fits), "kept": len(kept),
            "loss_before": float(np.mean(before)) if before else None,  # None: no frame had a mask pixel
            "loss_after": float(np.mean(after)) if after else None,
            "pose_rot_deg": magnitudes["pose_rot_deg"], "pose_root_mm": magnitudes["pose_root_mm"],
            "seconds": time.perf_counter() - started}
