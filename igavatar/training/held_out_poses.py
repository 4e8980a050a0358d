"""Test-time pose refinement: one held-out frame's pose corrected against its own image, the avatar fixed.

    frame = HeldOutFrame(image, mask, K, w2c, bone_transforms, pose_condition, posed_box)
    refined = refine_frame_pose(avatar, canonical_grid, subject, frame, HeldOutPoseConfig(), model_config)
    refined.bone_transforms     # (J, 4, 4) canonical -> world: refined, or the given ones if that fit worse
    refined.record()            # what was done, for the eval report

Estimated poses (a video's fit, a dataset's SMPL fits) are a few degrees off; a held-out frame
rendered in its estimated pose then scores the pose error as much as the avatar. Peers (Anim-NeRF,
InstantAvatar) optimise each test frame's pose against its image before scoring the image. This
does the same with the training path's own machinery (igavatar.training.pose_refine): corrections
of the root and the major bones and a root shift, through the implicit-function gradient of root
finding, with the photometric and mask losses of training and a prior toward the estimate. Only
the pose changes; the avatar's weights are frozen. `eval --refine-test-poses` uses it for the
image metrics only (`../shared/design/EVAL.md`: off by default, recorded when on).

The refined pose is kept only when it explains a fixed set of the frame's pixels better than the
estimate did (a loss measured before and after on the same rays), so a refinement that wanders
cannot lower the score. The fit itself, optimise_frame_pose, also serves training's whole-frame
pose passes (igavatar.training.pose_align), on the training run's own corrections.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from igavatar.model.avatar import Avatar
from igavatar.model.losses import alpha_loss, rgb_loss
from igavatar.model.posed import PosedAvatar
from igavatar.render.occupancy import OccupancyGrid
from igavatar.render.rays import pixel_rays, rays_in_box
from igavatar.render.sampler import sample_along_rays
from igavatar.render.volume import render_rays
from igavatar.training.config import TrainConfig
from igavatar.training.data import sample_patch_pixels
from igavatar.training.pose_refine import PoseRefiner, with_pose_gradient


class SkeletonArrays(Protocol):
    """What the refinement reads of a subject (igavatar.avatar.subject.SubjectArrays has it):
    parents (J,), rest_joints (J, 3), canonical_rotations (J, 3, 3), init_bones (the major bones)."""

    parents: np.ndarray
    rest_joints: np.ndarray
    canonical_rotations: np.ndarray
    init_bones: np.ndarray


@dataclass(frozen=True)
class HeldOutPoseConfig:
    """How hard one held-out frame's pose is refined."""

    steps: int = 80
    learning_rate: float = 0.0005
    """Adam's step (radians, meters). Measured on a video-fitted subject's held-out frames: 0.003
    wandered (box PSNR -0.8 to -1.0 dB where kept), 0.001 gained 0.4 dB and 0.0005 0.5 dB on the
    frame where it helped most (tests/benchmarks/results/video-fit-offsets.md)."""
    prior_weight: float = 0.001
    """Weight of the squared corrections (as PoseRefiner.regularization): weak, the image decides."""
    translation_scale_m: float = 0.02
    check_patches: int = 16
    """Patches of the fixed set on which the loss before and after is compared."""


@dataclass(frozen=True)
class HeldOutFrame:
    """One frame to refine: its image (H, W, 3) uint8 RGB and mask (H, W) bool at the dataset's
    size, K (3, 3), w2c (4, 4), bone_transforms (J, 4, 4) canonical -> world, pose_condition
    (pose_dim,) and posed_box (2, 3) world, as the dataset stores them (numpy)."""

    image: np.ndarray
    mask: np.ndarray
    K: np.ndarray
    w2c: np.ndarray
    bone_transforms: np.ndarray
    pose_condition: np.ndarray
    posed_box: np.ndarray


@dataclass(frozen=True)
class RefinedPose:
    """bone_transforms (J, 4, 4) float32, the corrections found and whether they were kept."""

    bone_transforms: np.ndarray
    kept: bool
    rotation_deg: float
    root_mm: float
    loss_before: float
    loss_after: float

    def record(self) -> dict:
        """The frame's refinement, for the eval report."""
        def number(value: float) -> float | None:
            return round(value, 6) if math.isfinite(value) else None

        return {"kept": self.kept, "mean_joint_correction_deg": round(self.rotation_deg, 3),
                "root_correction_mm": round(self.root_mm, 2), "check_loss_before": number(self.loss_before),
                "check_loss_after": number(self.loss_after)}


class _Frame:
    """The frame's tensors on the avatar's device and the rendering of a set of its pixels."""

    def __init__(self, frame: HeldOutFrame, device: torch.device, model_config: TrainConfig) -> None:
        self.image = torch.from_numpy(frame.image).to(device, torch.float32) / 255.0
        self.mask = torch.from_numpy(frame.mask).to(device)
        ys, xs = torch.nonzero(torch.from_numpy(frame.mask), as_tuple=True)
        self.mask_pixels = torch.stack((xs, ys), dim=-1)
        self.K = torch.from_numpy(frame.K).to(device, torch.float32)
        self.w2c = torch.from_numpy(frame.w2c).to(device, torch.float32)
        self.pose_condition = torch.from_numpy(frame.pose_condition).to(device, torch.float32)
        self.posed_box = torch.from_numpy(frame.posed_box).to(device, torch.float32)
        self.size_hw = (int(frame.mask.shape[0]), int(frame.mask.shape[1]))
        self.config = model_config

    def pixels(self, n_patches: int, generator: torch.Generator) -> torch.Tensor:
        c = self.config
        return sample_patch_pixels(self.mask_pixels, self.size_hw, n_patches, c.patch_size, c.patch_centres_in_mask,
                                   generator)

    def loss(self, avatar: Avatar, canonical_grid: OccupancyGrid, refiner: PoseRefiner, index: int, pixels: torch.Tensor,
             generator: torch.Generator, with_gradient: bool) -> torch.Tensor:
        """Training's photometric + mask loss on `pixels` (random background) in the pose refiner
        gives dataset frame `index`."""
        c, device = self.config, self.K.device
        prepared = avatar.deformer.prepare(refiner.bone_transforms(index).to(device))
        posed = PosedAvatar(avatar, prepared, self.pose_condition)
        grid = posed.occupancy(canonical_grid, self.posed_box, c.occupancy_resolution)
        target_rgb = self.image[pixels[:, 1], pixels[:, 0]]
        target_mask = self.mask[pixels[:, 1], pixels[:, 0]].float()
        background = torch.rand(target_rgb.shape, generator=generator).to(device)
        target = torch.where(target_mask[:, None] > 0.5, target_rgb, background)
        origins, directions = pixel_rays(self.K, self.w2c, pixels.to(device, torch.float32))
        rays = rays_in_box(origins, directions, self.posed_box[0], self.posed_box[1])
        sample_generator = torch.Generator(device=device).manual_seed(int(torch.randint(0, 2**62, (1,), generator=generator)))
        samples = sample_along_rays(rays, c.samples_per_ray, grid.is_occupied, generator=sample_generator)
        canonical, x_rigid = posed.canonical_samples(samples)
        if with_gradient:
            canonical, x_rigid = with_pose_gradient(avatar.deformer, prepared, samples, canonical, x_rigid,
                                                    c.pose_gradient_samples, generator)
        out = render_rays(canonical, posed.fields_at, background)
        weights = c.loss_weights
        return weights.rgb * rgb_loss(out.rgb, target) + weights.alpha * alpha_loss(out.opacity, target_mask)


def _check_loss(frame: _Frame, avatar: Avatar, grid: OccupancyGrid, refiner: PoseRefiner, index: int,
                pixels: torch.Tensor, seed: int) -> float:
    """The loss on a fixed pixel set with a fixed background and samples (comparable before/after)."""
    with torch.no_grad():
        return float(frame.loss(avatar, grid, refiner, index, pixels, torch.Generator().manual_seed(seed), False))


def refine_frame_pose(avatar: Avatar, canonical_grid: OccupancyGrid, subject: SkeletonArrays, frame: HeldOutFrame,
                      config: HeldOutPoseConfig, model_config: TrainConfig, seed: int = 0) -> RefinedPose:
    """Refine `frame`'s pose against its image (see the module docstring); the avatar is unchanged.

    Args:
        avatar, canonical_grid: the trained model (any mode; its weights are not stepped).
        subject: the model's subject arrays (parents, rest joints, canonical rotations, init bones).
        model_config: the model's TrainConfig (rays, patches, samples, loss weights as trained).
    """
    device = avatar.canonical_box.device
    joints = np.union1d([0], subject.init_bones)
    refiner = PoseRefiner(torch.from_numpy(np.asarray(frame.bone_transforms, np.float32))[None], subject.parents,
                          subject.rest_joints, subject.canonical_rotations, torch.tensor([0]), joints).to(device)
    fit = optimise_frame_pose(avatar, canonical_grid, refiner, 0, frame, config, model_config, seed)
    transforms = refiner.all_bone_transforms()[0].float().cpu().numpy() if fit.kept else \
        np.asarray(frame.bone_transforms, np.float32)
    return RefinedPose(transforms, fit.kept, fit.rotation_deg, fit.root_mm, fit.loss_before, fit.loss_after)


@dataclass(frozen=True)
class FrameFit:
    """One frame's pose fit: the fixed pixel set's loss before and after, whether the corrections
    were kept, and the corrections found (mean joint rotation in degrees, root shift in mm)."""

    loss_before: float
    loss_after: float
    kept: bool
    rotation_deg: float
    root_mm: float


def optimise_frame_pose(avatar: Avatar, canonical_grid: OccupancyGrid, refiner: PoseRefiner, index: int,
                        frame: HeldOutFrame, config: HeldOutPoseConfig, model_config: TrainConfig,
                        seed: int = 0) -> FrameFit:
    """Step dataset frame `index`'s corrections in `refiner` against `frame`'s image, the avatar frozen;
    put them back as they were unless the loss on a fixed set of the frame's pixels went down.

    `frame.bone_transforms` is not read: the pose is the refiner's. Every other frame's corrections
    are left exactly as they were (a fresh Adam moves no entry whose gradient was always 0).
    An empty mask leaves the corrections alone (losses nan, not kept).
    """
    data = _Frame(frame, avatar.canonical_box.device, model_config)
    if data.mask_pixels.shape[0] == 0:
        return FrameFit(math.nan, math.nan, False, 0.0, 0.0)
    slot = int(refiner.slots[index])
    start = refiner.rotation.detach()[slot].clone(), refiner.translation.detach()[slot].clone()
    generator = torch.Generator().manual_seed(seed)
    n_patches = max(1, model_config.rays_per_step // model_config.patch_size**2)
    check_pixels = data.pixels(config.check_patches, torch.Generator().manual_seed(seed + 1))
    frozen = [p for p in avatar.parameters() if p.requires_grad]
    mode = avatar.training
    avatar.eval()
    try:
        for p in frozen:
            p.requires_grad_(False)
        before = _check_loss(data, avatar, canonical_grid, refiner, index, check_pixels, seed + 2)
        optimizer = torch.optim.Adam(refiner.parameters(), lr=config.learning_rate)
        for _ in range(config.steps):
            loss = data.loss(avatar, canonical_grid, refiner, index, data.pixels(n_patches, generator), generator, True)
            loss = loss + refiner.regularization(index, config.prior_weight, config.translation_scale_m)
            optimizer.zero_grad(set_to_none=True)
            if loss.requires_grad:
                loss.backward()
                optimizer.step()
        after = _check_loss(data, avatar, canonical_grid, refiner, index, check_pixels, seed + 2)
    finally:
        for p in frozen:
            p.requires_grad_(True)
        avatar.train(mode)
    with torch.no_grad():
        rotation_deg = math.degrees(float(refiner.rotation[slot].norm(dim=-1).mean()))
        root_mm = 1000 * float(refiner.translation[slot].norm())
        kept = after < before
        if not kept:
            refiner.rotation[slot] = start[0]
            refiner.translation[slot] = start[1]
    return FrameFit(before, after, kept, rotation_deg, root_mm)
