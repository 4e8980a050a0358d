"""Held-out frames take their refined neighbours' pose corrections, interpolated in time."""

from __future__ import annotations

import numpy as np
import torch

from igavatar.avatar.pose_carry import apply_corrections, carry_corrections
from igavatar.body.rotations import axis_angle_to_matrix
from igavatar.training.pose_refine import PoseRefiner


def _roots(n: int, step_deg: float = 6.0) -> torch.Tensor:
    """(n, 3, 3) root rotations of a turn about z by step_deg a frame."""
    angles = torch.deg2rad(torch.arange(n, dtype=torch.float64) * step_deg)
    return axis_angle_to_matrix(torch.stack((torch.zeros(n, dtype=torch.float64),) * 2 + (angles,), -1)).float()


def _corrections(n: int, k: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    rotation = torch.arange(n * k * 3, dtype=torch.float32).reshape(n, k, 3) * 1e-3
    translation = torch.arange(n * 3, dtype=torch.float32).reshape(n, 3) * 1e-3
    return rotation, translation


def test_a_frame_between_two_refined_frames_takes_their_corrections_by_time():
    refined = ["frame_000000", "frame_000002", "frame_000005"]
    rotation, translation = _corrections(3)
    roots = _roots(6)
    carried = carry_corrections(refined, roots[[0, 2, 5]], rotation, translation,
                                ["frame_000001", "frame_000003", "frame_000002"], roots[[1, 3, 2]])
    # frame_000002 is refined itself: it keeps its own correction and is not carried.
    assert carried.positions == [0, 1]
    assert carried.neighbours == [("frame_000000", "frame_000002"), ("frame_000002", "frame_000005")]
    torch.testing.assert_close(carried.rotation[0], 0.5 * (rotation[0] + rotation[1]))
    torch.testing.assert_close(carried.translation[1], (2 * translation[1] + translation[2]) / 3)


def test_an_end_of_the_clip_takes_the_nearest_within_one_spacing():
    refined = ["frame_000000", "frame_000001", "frame_000002"]
    rotation, translation = _corrections(3)
    roots = _roots(6)
    carried = carry_corrections(refined, roots[:3], rotation, translation, ["frame_000003", "frame_000005"],
                                roots[[3, 5]])
    assert carried.positions == [0] and carried.neighbours == [("frame_000002",)]
    torch.testing.assert_close(carried.rotation[0], rotation[2])


def test_gaps_other_clips_unnumbered_names_and_turns_keep_their_pose():
    refined = ["frame_000000", "frame_000001", "frame_000010", "frame_000011"]
    rotation, translation = _corrections(4)
    roots = _roots(12)
    names = ["frame_000005", "test_walk_0003", "portrait", "frame_000012"]
    carried = carry_corrections(refined, roots[[0, 1, 10, 11]], rotation, translation, names,
                                roots[[5, 3, 0, 11]])
    # frame_000005 lies in a gap of 9 frames (the clip steps 1); frame_000012's root has not turned
    # from frame_000011's, so it is carried; the other clip and the unnumbered name are not.
    assert carried.positions == [3]
    turned = roots[[5, 3, 0, 11]].clone()
    turned[3] = _roots(12, step_deg=30.0)[11]  # 30 degrees a frame: far from its neighbour's root
    assert len(carry_corrections(refined, roots[[0, 1, 10, 11]], rotation, translation, names, turned)) == 0


def test_applied_corrections_pose_a_frame_as_training_poses_a_refined_one():
    parents = np.array([-1, 0, 1, 0])
    rest = np.array([[0, 0, 1.0], [0, 0, 1.3], [0, 0, 1.6], [0.2, 0, 1.0]])
    canonical_rotations = np.tile(np.eye(3), (4, 1, 1))
    generator = torch.Generator().manual_seed(0)
    refiner = PoseRefiner(torch.eye(4).repeat(2, 4, 1, 1), parents, rest, canonical_rotations, torch.arange(2))
    with torch.no_grad():  # some pose, as the dataset stores it
        refiner.rotation.copy_(0.3 * torch.randn(2, 4, 3, generator=generator))
        refiner.translation.copy_(0.1 * torch.randn(2, 3, generator=generator))
    given = refiner.all_bone_transforms()
    joints = np.array([0, 2])
    rotation = 0.05 * torch.randn(2, 2, 3, generator=generator)
    translation = 0.01 * torch.randn(2, 3, generator=generator)
    corrected = apply_corrections(given, parents, rest, canonical_rotations, joints, rotation, translation)
    training = PoseRefiner(given.float(), parents, rest, canonical_rotations, torch.arange(2), joints)
    with torch.no_grad():
        training.rotation.copy_(rotation)
        training.translation.copy_(translation)
    torch.testing.assert_close(corrected, torch.stack([training.bone_transforms(i) for i in range(2)]),
                               atol=1e-5, rtol=0)
    unchanged = apply_corrections(given, parents, rest, canonical_rotations, joints, torch.zeros(2, 2, 3),
                                  torch.zeros(2, 3))
    torch.testing.assert_close(unchanged, given.float(), atol=1e-5, rtol=0)
    # A correction of joint 2 alone turns joint 2 and leaves the root and the other branch (joint 3) as they were.
    only_two = torch.zeros(2, 2, 3)
    only_two[:, 1] = rotation[:, 1]
    turned = apply_corrections(given, parents, rest, canonical_rotations, joints, only_two, torch.zeros(2, 3))
    torch.testing.assert_close(turned[:, [0, 1, 3]], given[:, [0, 1, 3]].float(), atol=1e-5, rtol=0)
    assert (turned[:, 2] - given[:, 2].float()).abs().max() > 1e-3
