"""Ghost limbs of the visual-hull prior (igavatar.capture.ghost_limbs).

Analytic: two legs spread in canonical space and brought together in the posed frame. A point
that rides rigidly with the left leg into the right one is voted a ghost; points on and around
either leg, and a point between the legs that both legs share (a skirt), are not; a lone root
votes nothing. The torch distances match igavatar.body.bones' numpy reference.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from igavatar.body.bones import BoneSegments, segment_distances
from igavatar.capture.ghost_limbs import PosedBones, joint_distances, misplaced_votes

# Joints: root, left hip, left foot, right hip, right foot (x = subject's left).
JOINTS = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.4, -0.8, 0.0], [-0.1, 0.0, 0.0], [-0.4, -0.8, 0.0]])
SEGMENTS = [(0, 0, 1), (0, 0, 3), (1, 1, 2), (3, 3, 4)]  # (moving joint, start joint, end joint)


def _rotation_about_z(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _about(pivot: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    transform = torch.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = pivot - rotation @ pivot
    return transform


def _legs_together() -> torch.Tensor:
    """(2, 5, 4, 4): frame 0 the canonical pose, frame 1 each leg turned about its hip to vertical."""
    spread = math.atan2(0.3, 0.8)
    left = _about(JOINTS[1], _rotation_about_z(-spread))  # the left foot swings in to x = 0.1
    right = _about(JOINTS[3], _rotation_about_z(spread))
    posed = torch.stack([torch.eye(4), left, left, right, right])
    return torch.stack([torch.eye(4).expand(5, 4, 4), posed])


def _bones() -> PosedBones:
    moving, start, end = zip(*SEGMENTS)
    return PosedBones(joint=torch.tensor(moving), start=JOINTS[list(start)], end=JOINTS[list(end)],
                      bone_transforms=_legs_together())


def _skin(weights: torch.Tensor, transforms: torch.Tensor):
    """LBS with fixed per-point weights (P, J) as a SkinFn."""
    def skin(frame: int, x: torch.Tensor) -> torch.Tensor:
        blended = torch.einsum("pj,jab->pab", weights, transforms[frame])
        return torch.einsum("pab,pb->pa", blended[:, :3, :3], x) + blended[:, :3, 3]
    return skin


def test_a_point_that_rides_into_the_other_leg_is_a_ghost_and_real_ones_are_not():
    transforms = _legs_together()
    left_only = torch.tensor([0.0, 1.0, 0.0, 0.0, 0.0])
    # The ghost: where the left leg's transform takes a point onto the posed right leg's axis.
    landing = torch.tensor([-0.1, -0.6, 0.0, 1.0])
    ghost = (torch.linalg.inv(transforms[1, 1]) @ landing)[:3]
    on_left_bone = JOINTS[1] + 0.6 * (JOINTS[2] - JOINTS[1])
    beside_left_bone = on_left_bone + torch.tensor([0.06, 0.0, 0.0])  # the leg's outer surface
    inside_of_left_leg = on_left_bone - torch.tensor([0.06, 0.0, 0.0])  # faces the other leg
    skirt = torch.tensor([0.0, -0.3, 0.0])
    points = torch.stack([ghost, on_left_bone, beside_left_bone, inside_of_left_leg, skirt])
    weights = torch.stack([left_only, left_only, left_only, left_only, torch.tensor([0.0, 0.5, 0.0, 0.5, 0.0])])
    assert float(ghost[0]) > 0.0  # the ghost lies on the left, between the spread legs

    votes = misplaced_votes(points, weights, _skin(weights, transforms), [0, 1], _bones())
    assert votes.tolist() == [1, 0, 0, 0, 0]  # frame 0 (canonical) never votes
    # With the margin above the ghost's excess (0.2 m: its own bone stays 0.2 m away), nothing votes.
    assert misplaced_votes(points, weights, _skin(weights, transforms), [0, 1], _bones(), margin_m=0.25).sum() == 0


def test_a_lone_root_votes_nothing():
    bones = PosedBones(joint=torch.zeros(0, dtype=torch.int64), start=torch.zeros(0, 3), end=torch.zeros(0, 3),
                       bone_transforms=torch.eye(4).expand(3, 1, 4, 4))
    points = torch.randn(50, 3)
    votes = misplaced_votes(points, torch.ones(50, 1), lambda frame, x: x + 1.0, [0, 1, 2], bones)
    assert votes.shape == (50,) and votes.sum() == 0


def test_joint_distances_match_the_numpy_reference():
    generator = torch.Generator().manual_seed(0)
    points = torch.randn(300, 3, generator=generator) * 0.5
    bones = _bones()
    # A degenerate (zero-length) segment as a leaf joint may have.
    start = torch.cat([bones.start, JOINTS[2:3]])
    end = torch.cat([bones.end, JOINTS[2:3]])
    joint = torch.cat([bones.joint, torch.tensor([2])])
    got = joint_distances(points, start, end, joint, num_joints=5)

    reference, _ = segment_distances(points.double().numpy(), BoneSegments(joint.numpy(), start.double().numpy(), end.double().numpy()))
    expected = np.full((300, 5), np.inf)
    for b, j in enumerate(joint.tolist()):
        expected[:, j] = np.minimum(expected[:, j], reference[:, b])
    assert np.isinf(got[:, 4].numpy()).all()  # joint 4 moves no segment here
    np.testing.assert_allclose(got[:, :4].numpy(), expected[:, :4], atol=1e-6)


def test_segments_in_frame_move_rigidly_with_their_joint():
    bones = _bones()
    start, end = bones.segments_in_frame(1)
    # The left leg's bone (segment 2) ends straight below the left hip once the leg is turned in.
    torch.testing.assert_close(start[2], JOINTS[1])
    torch.testing.assert_close(end[2], torch.tensor([0.1, -math.hypot(0.3, 0.8), 0.0]), atol=1e-6, rtol=0)
    torch.testing.assert_close((end - start).norm(dim=1), (bones.end - bones.start).norm(dim=1))
