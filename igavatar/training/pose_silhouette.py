"""Training poses fitted to the masks before training: the shape prior, posed into each training
frame by its corrected pose, must lie inside the frame's mask and reach its outline.

    fit = fit_poses_to_masks(refiner, data, deformer, prior_vertices, config)
    fit.report   # {"frames": T, "kept": k, "outside_px_before": ..., "outside_px_after": ..., "pose_rot_deg": ..., ...}
    voting = corrected_data(data, refiner)   # the frames as the fit posed them, for the priors' vote

Whole-frame passes against the avatar's renders (igavatar.training.pose_align) need an avatar to
compare with, and one trained on wrong poses is their blurred average: after two passes, 5 degrees
of noise a joint still cost CD-L1 42 mm against 3.7 with the exact poses
(tests/benchmarks/results/pose-noise.md). The masks need no avatar. Before the first step, every
training frame's corrections are fitted at once to the silhouette term of the video fit
(igavatar.body.silhouette_fit): points of the dataset's
shape prior (the naked template for tight clothes, the masks' visual hull for loose ones), skinned
by the deformer's weights, must fall inside the mask, and the mask's outline must lie near the posed
points (up to a margin for clothes). A prior keeps the corrections near the estimate; a silhouette
says almost nothing of a twist about a limb, and the prior holds those corrections near zero. It
says little of depth either: a temporal term (pose_silhouette_smoothness) asks the refined joints
to move smoothly between frames that are neighbours in one clip (igavatar.training.pose_time).

A frame keeps its fit only if its silhouette term went down. The fit is all or nothing: an
interrupt puts every correction back. The corrections it found are kept apart from training's later
ones (SilhouetteFit), so that a resumed run votes its body-inside prior on the same poses.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np
import torch

from igavatar.body.image_maps import huber_px
from igavatar.body.rotations import invert_rigid
from igavatar.body.silhouette_fit import HUBER_PX, SilhouetteTarget, spread_subset
from igavatar.model.deformer import FastSnarfDeformer
from igavatar.skinning.grid import sample_skinning_weights
from igavatar.training.config import TrainConfig
from igavatar.training.data import TrainingData
from igavatar.training.pose_refine import PoseRefiner
from igavatar.training.pose_time import TimeTriplets, time_triplets

#: Points of the prior the silhouette checks in every frame (as the video fit).
PRIOR_POINTS = 600
#: A posed joint accelerating by this many meters per source frame squared costs as much, times
#: pose_silhouette_smoothness, as the silhouette term's mean px (5 degrees of noise a joint puts the
#: major joints' second differences at a few cm).
ACCELERATION_SCALE_M = 0.02
#: Accelerations well above this (m per source frame squared) pull less and less (Geman-McClure):
#: they are the person's fast motion, or a cut, not an estimate's noise. It is not enough alone: a
#: 360-degree turn in 4 frames (0.2-0.7 m a joint) was still pulled 0.35 m off, which the guard on
#: the root's turn (pose_time.MAX_ROOT_TURN_DEG) prevents.
ACCELERATION_CAP_M = 0.1


@dataclass(frozen=True)
class SilhouetteFit:
    """The fit's summary (for the model's manifest) and the corrections it left.

    Attributes:
        report: frames, kept, outside_px_before / _after, pose_rot_deg, pose_root_mm, seconds.
        rotation: (T, K, 3) and translation: (T, 3) the refiner's corrections right after the fit.
    """

    report: dict
    rotation: torch.Tensor
    translation: torch.Tensor

    def state(self) -> dict:
        """For a checkpoint (igavatar.training.checkpoint)."""
        return {"report": self.report, "rotation": self.rotation, "translation": self.translation}

    @classmethod
    def from_state(cls, state: dict) -> "SilhouetteFit":
        return cls(dict(state["report"]), torch.as_tensor(state["rotation"]), torch.as_tensor(state["translation"]))

    def apply(self, refiner: PoseRefiner) -> None:
        """Set the refiner's corrections to the fit's (a resumed run, before its checkpoint is loaded)."""
        with torch.no_grad():
            refiner.rotation.copy_(self.rotation)
            refiner.translation.copy_(self.translation)


def corrected_data(data: TrainingData, refiner: PoseRefiner) -> TrainingData:
    """`data` with the refined frames' bone transforms as the refiner's corrections pose them."""
    transforms = data.bone_transforms.clone()
    transforms[refiner.frames.cpu()] = refiner.corrected_transforms().detach().cpu().to(transforms.dtype)
    return dataclasses.replace(data, bone_transforms=transforms)


def silhouette_target(refiner: PoseRefiner, data: TrainingData, deformer: FastSnarfDeformer,
                      prior_vertices: np.ndarray) -> SilhouetteTarget:
    """The refiner's frames' masks and PRIOR_POINTS points of the canonical prior (V, 3), with the
    deformer's skinning weights there. Its `rest` space is canonical space (rest_joints 0), so its
    `posed_points` takes canonical -> posed bone transforms (T, J, 4, 4)."""
    frames = refiner.frames.cpu()
    chosen = spread_subset(np.asarray(prior_vertices, dtype=np.float64), PRIOR_POINTS)
    points = torch.as_tensor(np.asarray(prior_vertices, dtype=np.float64)[chosen])
    grid = deformer.weights_grid.detach().cpu()
    weights = sample_skinning_weights(grid, deformer.box_min.cpu(), deformer.box_max.cpu(), points.to(grid.dtype))
    return SilhouetteTarget.of(data.masks[frames].numpy(), points.numpy(), weights.double().numpy(),
                               np.zeros((deformer.num_joints, 3)))


def frame_losses(target: SilhouetteTarget, transforms: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor,
                 coverage_weight: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Per frame (T,): the robust silhouette term, and the mean px of the points outside the mask.

    Args:
        transforms: (T, J, 4, 4) canonical -> posed world; K: (T, 3, 3); w2c: (T, 4, 4) float64.
    """
    x_world = target.posed_points(transforms)  # (T, S, 3)
    x_camera = torch.einsum("tij,tsj->tsi", w2c[:, :3, :3], x_world) + w2c[:, None, :3, 3]
    projected = torch.einsum("tij,tsj->tsi", K, x_camera)
    uv = projected[..., :2] / x_camera[..., 2:].clamp_min(1e-3)
    outside, uncovered = target.distances_at(uv, coverage_weight > 0)
    loss = huber_px(outside, HUBER_PX).mean(1)
    if uncovered is not None:
        loss = loss + coverage_weight * huber_px(uncovered, HUBER_PX).mean(1)
    return loss, outside.mean(1)


def temporal_loss(triplets: TimeTriplets, transforms: torch.Tensor, joints_canonical: torch.Tensor) -> torch.Tensor:
    """Mean over the triplets and the refined joints of (acceleration / ACCELERATION_SCALE_M)^2,
    capped smoothly near ACCELERATION_CAP_M (igavatar.training.pose_time); a scalar, 0 without
    triplets.

    Args:
        transforms: (T, K, 4, 4) canonical -> posed world of the refined joints;
            joints_canonical: (K, 3) float64 their canonical positions.
    """
    if len(triplets) == 0:
        return transforms.new_zeros(())
    posed = (transforms[..., :3, :3] @ joints_canonical[None, :, :, None])[..., 0] + transforms[..., :3, 3]
    squared = triplets.acceleration(posed).square().sum(-1)  # (M, K) m^2 per source frame^4
    capped = squared * ACCELERATION_CAP_M**2 / (squared + ACCELERATION_CAP_M**2)
    return (capped / ACCELERATION_SCALE_M**2).mean()


def fit_poses_to_masks(refiner: PoseRefiner, data: TrainingData, deformer: FastSnarfDeformer,
                       prior_vertices: np.ndarray, config: TrainConfig) -> SilhouetteFit:
    """Fit every refined frame's corrections to its mask (module docstring), in place; returns the
    summary for the model's manifest and the corrections.

    Args:
        refiner: the run's pose corrections (changed in place: only frames whose term fell move).
        data: the training frames (masks, cameras); deformer: its skinning weights pose the prior.
        prior_vertices: (V, 3) canonical vertices of the dataset's shape prior.
        config: pose_silhouette_steps, pose_silhouette_lr, pose_silhouette_coverage,
            pose_silhouette_prior_weight, pose_silhouette_translation_scale_m,
            pose_silhouette_smoothness (the temporal term over frames named as neighbours).
    """
    started = time.perf_counter()
    target = silhouette_target(refiner, data, deformer, prior_vertices)
    frames = refiner.frames.cpu()
    triplets = time_triplets([data.frame_names[int(i)] for i in frames], data.bone_transforms[frames, 0, :3, :3])
    # The refined joints' canonical positions: the canonical pose's joint frames' origins.
    joint_index = refiner.joints.cpu()
    joints = invert_rigid(refiner.canonical_inverse.cpu().double())[joint_index, :3, 3]
    K, w2c = data.K[frames].double(), data.w2c[frames].double()
    device = refiner.rotation.device
    saved = refiner.rotation.detach().clone(), refiner.translation.detach().clone()
    optimizer = torch.optim.Adam([refiner.rotation, refiner.translation], lr=config.pose_silhouette_lr)
    try:
        with torch.no_grad():
            before, outside_before = frame_losses(target, refiner.corrected_transforms().cpu(), K, w2c,
                                                  config.pose_silhouette_coverage)
        for _ in range(config.pose_silhouette_steps):
            optimizer.zero_grad(set_to_none=True)
            transforms = refiner.corrected_transforms().cpu()
            loss, _ = frame_losses(target, transforms, K, w2c, config.pose_silhouette_coverage)
            prior = (refiner.rotation.square().sum((1, 2))
                     + (refiner.translation / config.pose_silhouette_translation_scale_m).square().sum(1)).cpu()
            total = (target.frame_weight * (loss + config.pose_silhouette_prior_weight * prior)).sum()
            total = total / target.frame_weight.sum().clamp_min(1.0)
            if config.pose_silhouette_smoothness > 0:
                total = total + config.pose_silhouette_smoothness * temporal_loss(triplets, transforms[:, joint_index], joints)
            total.backward()
            optimizer.step()
        with torch.no_grad():
            after, outside_after = frame_losses(target, refiner.corrected_transforms().cpu(), K, w2c,
                                                config.pose_silhouette_coverage)
            worse = (after >= before).to(device)
            refiner.rotation[worse] = saved[0][worse]
            refiner.translation[worse] = saved[1][worse]
    except BaseException:
        with torch.no_grad():
            refiner.rotation.copy_(saved[0])
            refiner.translation.copy_(saved[1])
        raise
    worse = worse.cpu()
    masked = target.frame_weight > 0
    outside_final = torch.where(worse, outside_before, outside_after)
    magnitudes = refiner.correction_magnitudes()
    report = {"frames": len(frames), "kept": int((~worse & masked).sum()), "time_triplets": len(triplets),
              "outside_px_before": float(outside_before[masked].mean()) if masked.any() else None,
              "outside_px_after": float(outside_final[masked].mean()) if masked.any() else None,
              "pose_rot_deg": magnitudes["pose_rot_deg"], "pose_root_mm": magnitudes["pose_root_mm"],
              "seconds": time.perf_counter() - started}
    return SilhouetteFit(report, refiner.rotation.detach().cpu().clone(), refiner.translation.detach().cpu().clone())
