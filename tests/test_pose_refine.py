"""Pose refinement: corrections reproduce the stored poses at zero, pose the skeleton as FK does,
and pull a known pose error back when optimised against the images."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from igavatar.avatar.dataset import PRIOR_FILE, read_dataset, training_data
from igavatar.avatar.model import build_avatar
from igavatar.body.rotations import axis_angle_to_matrix
from igavatar.body.skeleton import bone_transforms, forward_kinematics
from igavatar.training.config import preset
from igavatar.training.pose_refine import PoseRefiner
from igavatar.training.trainer import Trainer


def _skeleton_frames(n_frames: int = 3, seed: int = 0):
    """A small chain-and-branch skeleton, its canonical pose and random posed frames."""
    parents = np.array([-1, 0, 1, 2, 1, 4])
    rest = np.array([[0, 0, 1.0], [0, 0, 1.2], [0.2, 0, 1.4], [0.5, 0, 1.4], [-0.2, 0, 1.4], [-0.5, 0, 1.4]])
    generator = torch.Generator().manual_seed(seed)
    canonical = axis_angle_to_matrix(0.3 * torch.randn(6, 3, generator=generator, dtype=torch.float64))
    rotations = axis_angle_to_matrix(0.5 * torch.randn(n_frames, 6, 3, generator=generator, dtype=torch.float64))
    translation = torch.randn(n_frames, 3, generator=generator, dtype=torch.float64)
    g_canonical = forward_kinematics(canonical, rest, parents)
    g_posed = forward_kinematics(rotations, rest, parents, translation)
    return parents, rest, canonical, rotations, translation, bone_transforms(g_posed, g_canonical[None])


def test_zero_corrections_reproduce_the_stored_transforms():
    parents, rest, canonical, _, _, transforms = _skeleton_frames()
    refiner = PoseRefiner(transforms.float(), parents, rest, canonical.numpy(), torch.tensor([0, 2]))
    assert refiner.refines(0) and not refiner.refines(1) and refiner.refines(2)
    for index in (0, 2):
        assert torch.allclose(refiner.bone_transforms(index), transforms[index].float(), atol=1e-5)


def test_a_correction_rotates_the_joint_as_forward_kinematics_does():
    parents, rest, canonical, rotations, translation, transforms = _skeleton_frames(n_frames=1, seed=3)
    refiner = PoseRefiner(transforms.float(), parents, rest, canonical.numpy(), torch.tensor([0]))
    delta = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    shift = torch.tensor([0.05, 0.0, -0.02], dtype=torch.float64)
    with torch.no_grad():
        refiner.rotation[0, 2] = delta.float()
        refiner.translation[0] = shift.float()
    expected_rotations = rotations.clone()
    expected_rotations[0, 2] = rotations[0, 2] @ axis_angle_to_matrix(delta)
    expected = bone_transforms(forward_kinematics(expected_rotations, rest, parents, translation + shift),
                               forward_kinematics(canonical, rest, parents)[None])[0]
    assert torch.allclose(refiner.bone_transforms(0).double(), expected, atol=1e-5)
    # Joints above the corrected one do not move.
    assert torch.allclose(refiner.bone_transforms(0)[:2].double(),
                          bone_transforms(forward_kinematics(rotations, rest, parents, translation + shift),
                                          forward_kinematics(canonical, rest, parents)[None])[0, :2], atol=1e-5)


def test_all_frames_at_once_match_frame_by_frame_with_their_gradients():
    parents, rest, canonical, _, _, transforms = _skeleton_frames(n_frames=4, seed=9)
    refiner = PoseRefiner(transforms.float(), parents, rest, canonical.numpy(), torch.tensor([0, 1, 3]),
                          joints=np.array([0, 2, 4]))
    generator = torch.Generator().manual_seed(1)
    with torch.no_grad():
        refiner.rotation.copy_(0.2 * torch.randn(refiner.rotation.shape, generator=generator))
        refiner.translation.copy_(0.05 * torch.randn(refiner.translation.shape, generator=generator))
    weights = torch.randn(3, 6, 4, 4, generator=generator, dtype=torch.float64)
    batched = refiner.corrected_transforms()
    (batched * weights).sum().backward()
    grads = refiner.rotation.grad.clone(), refiner.translation.grad.clone()
    refiner.zero_grad()
    single = torch.stack([refiner.bone_transforms(index).double() for index in (0, 1, 3)])
    (single * weights).sum().backward()
    assert torch.allclose(batched.float().double(), single, atol=1e-6)
    assert torch.allclose(grads[0], refiner.rotation.grad, atol=1e-4)
    assert torch.allclose(grads[1], refiner.translation.grad, atol=1e-4)


def test_only_the_chosen_joints_are_corrected():
    parents, rest, canonical, _, _, transforms = _skeleton_frames(n_frames=1, seed=5)
    refiner = PoseRefiner(transforms.float(), parents, rest, canonical.numpy(), torch.tensor([0]), joints=np.array([0, 2]))
    assert refiner.rotation.shape == (1, 2, 3)
    with torch.no_grad():
        refiner.rotation[0, 1] = torch.tensor([0.0, 0.4, 0.0])  # joint 2
    corrected = refiner.bone_transforms(0)
    # Joints 0, 1 and the other branch (4, 5) keep their transforms; 2 and its child 3 turn.
    assert torch.allclose(corrected[[0, 1, 4, 5]], transforms[0, [0, 1, 4, 5]].float(), atol=1e-5)
    assert not torch.allclose(corrected[[2, 3]], transforms[0, [2, 3]].float(), atol=1e-3)


def test_refinement_reduces_a_known_pose_error(small_run, tmp_path):
    """An avatar whose SDF is the subject's template, one frame shifted sideways by 4 cm: optimising
    only the corrections against that frame's mask moves its root back to where the image shows it."""
    from stages.progress import NULL_PROGRESS
    from stages.train import _shape_initialize

    dataset = read_dataset(small_run / "dataset")
    data = training_data(dataset)
    config = dataclasses.replace(
        preset("tiny"), shape_init_steps=300, shape_init_points=4096, rays_per_step=256, patch_size=8,
        samples_per_ray=32, occupancy_resolution=32, refine_poses=True, pose_refine_start_fraction=0.0,
        pose_lr=0.006, pose_prior_weight=0.0, lr=0.0, steps=80, validate_every=0,
        loss_weights=dataclasses.replace(preset("tiny").loss_weights, rgb=0.0, alpha=1.0))
    avatar = build_avatar(config, dataset.subject, dataset.pose_dim)
    _shape_initialize(avatar, config, dataset.path / PRIOR_FILE, dataset.subject.canonical_box,
                      [tmp_path / "shape_init.npz"], NULL_PROGRESS)
    for parameter in avatar.parameters():
        parameter.requires_grad_(False)
    index = int(data.train_indices[0])
    # Sideways in the image (the camera's x axis in world coordinates): what one view can see.
    sideways = torch.as_tensor(np.linalg.inv(data.w2c[index].double().numpy())[:3, 0], dtype=torch.float32)
    shifted = data.bone_transforms.clone()
    shifted[index, :, :3, 3] += 0.04 * sideways
    data = dataclasses.replace(data, bone_transforms=shifted, train_indices=torch.tensor([index]))
    subject = dataset.subject
    refiner = PoseRefiner(data.bone_transforms, subject.parents, subject.rest_joints, subject.canonical_rotations,
                          data.train_indices)
    trainer = Trainer(config, data, avatar, "cpu", pose_refiner=refiner)
    for _ in range(80):
        trainer.train_step()
    moved_back = -float(refiner.translation[0].detach() @ sideways)
    # The correction points back along the shift and undoes a good part of it.
    assert moved_back > 0.02, refiner.translation[0]


def test_pose_rate_falls_to_zero_by_the_end(small_run):
    """The corrections' rate is pose_lr when refinement starts and falls linearly to 0 at the last
    step, so the final poses are the ones the final avatar was fitted with (a constant rate kept
    them walking after the avatar's own rate had decayed); a training step applies it."""
    dataset = read_dataset(small_run / "dataset")
    data = training_data(dataset)
    config = dataclasses.replace(preset("tiny"), steps=100, refine_poses=True, pose_refine_start_fraction=0.5,
                                 pose_lr=0.004, rays_per_step=64, patch_size=8, samples_per_ray=16,
                                 occupancy_resolution=32, validate_every=0)
    subject = dataset.subject
    refiner = PoseRefiner(data.bone_transforms, subject.parents, subject.rest_joints, subject.canonical_rotations,
                          data.train_indices)
    trainer = Trainer(config, data, build_avatar(config, subject, dataset.pose_dim), "cpu", pose_refiner=refiner)
    rates = [trainer.pose_learning_rate(step) for step in (0, 50, 75, 99, 100)]
    assert rates == pytest.approx([0.004, 0.004, 0.002, 0.00008, 0.0])
    trainer.step = 75
    trainer.train_step()
    assert trainer.pose_optimizer.param_groups[0]["lr"] == pytest.approx(0.002)
