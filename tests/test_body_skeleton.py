"""Rotations, Skeleton validation, forward kinematics and LBS against closed forms and references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from igavatar.body.rotations import (
    axis_angle_to_matrix,
    invert_rigid,
    matrix_to_axis_angle,
    matrix_to_quaternion,
    quaternion_to_axis_angle,
    rigid_matrix,
)
from tests.rotation_oracles import axis_angle_to_quaternion, quaternion_to_matrix, rotation_angle, transform_points
from igavatar.body.skeleton import (
    SMPL_JOINT_NAMES,
    SMPL_PARENTS,
    Skeleton,
    bone_transforms,
    forward_kinematics,
    linear_blend_skinning,
)
from igavatar.errors import InputError

# A small branching tree: 0 -> 1 -> 2 -> 3, 0 -> 4 -> 5, 1 -> 6.
PARENTS = np.array([-1, 0, 1, 2, 0, 4, 1])
J = len(PARENTS)


def random_rotvecs(generator: torch.Generator, shape: tuple[int, ...], max_angle: float = 2.5) -> torch.Tensor:
    axis = torch.randn(shape + (3,), generator=generator, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = torch.rand(shape + (1,), generator=generator, dtype=torch.float64) * max_angle
    return axis * angle


def rest_joints(generator: torch.Generator) -> torch.Tensor:
    return torch.randn(J, 3, generator=generator, dtype=torch.float64) * 0.3


def reference_fk(rotations: torch.Tensor, rest: torch.Tensor, parents, translation: torch.Tensor) -> torch.Tensor:
    """Per-joint loop of the SMPL recursion, for one pose (J,3,3)."""
    out = []
    for j, parent in enumerate(parents):
        if parent < 0:
            out.append(rigid_matrix(rotations[j], rest[j] + translation))
        else:
            out.append(out[parent] @ rigid_matrix(rotations[j], rest[j] - rest[parent]))
    return torch.stack(out)


# ---- rotations -------------------------------------------------------------------------------


def test_axis_angle_closed_form_quarter_turn_about_z():
    rotation = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
    expected = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(rotation, expected, atol=1e-15, rtol=0)


def test_axis_angle_matrix_round_trip_including_tiny_and_near_pi():
    generator = torch.Generator().manual_seed(0)
    rotvecs = random_rotvecs(generator, (200,), max_angle=math.pi - 1e-3)
    axis = rotvecs[:4] / rotvecs[:4].norm(dim=-1, keepdim=True)
    special = torch.cat((axis * 1e-9, axis * 1e-4, axis * (math.pi - 1e-6), torch.zeros(1, 3, dtype=torch.float64)))
    rotvecs = torch.cat((rotvecs, special))
    matrices = axis_angle_to_matrix(rotvecs)
    eye = torch.eye(3, dtype=torch.float64)
    torch.testing.assert_close(matrices @ matrices.transpose(-1, -2), eye.expand_as(matrices), atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(matrices), torch.ones(len(rotvecs), dtype=torch.float64))
    back = matrix_to_axis_angle(matrices)
    torch.testing.assert_close(axis_angle_to_matrix(back), matrices, atol=1e-9, rtol=0)
    # Away from pi the rotation vector itself is unique.
    torch.testing.assert_close(back[:-5], rotvecs[:-5], atol=1e-9, rtol=0)
    torch.testing.assert_close(back[-9:-5], rotvecs[-9:-5], atol=1e-15, rtol=1e-9)


def test_rodrigues_matches_matrix_exponential():
    generator = torch.Generator().manual_seed(1)
    rotvecs = random_rotvecs(generator, (50,))
    x, y, z = rotvecs.unbind(-1)
    zero = torch.zeros_like(x)
    skew = torch.stack((zero, -z, y, z, zero, -x, -y, x, zero), -1).reshape(-1, 3, 3)
    torch.testing.assert_close(axis_angle_to_matrix(rotvecs), torch.linalg.matrix_exp(skew), atol=1e-12, rtol=0)


def test_quaternion_conversions_agree():
    generator = torch.Generator().manual_seed(2)
    rotvecs = random_rotvecs(generator, (100,), max_angle=3.1)
    quaternions = axis_angle_to_quaternion(rotvecs)
    torch.testing.assert_close(matrix_to_quaternion(axis_angle_to_matrix(rotvecs)), quaternions, atol=1e-12, rtol=0)
    torch.testing.assert_close(quaternion_to_matrix(quaternions), axis_angle_to_matrix(rotvecs), atol=1e-12, rtol=0)
    torch.testing.assert_close(quaternion_to_axis_angle(-quaternions), rotvecs, atol=1e-12, rtol=0)
    torch.testing.assert_close(rotation_angle(axis_angle_to_matrix(rotvecs)), rotvecs.norm(dim=-1), atol=1e-12, rtol=0)


def test_rotation_gradients_are_finite_and_correct_at_zero():
    zero = torch.zeros(2, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(axis_angle_to_matrix, (zero,))
    small = (torch.randn(2, 3, dtype=torch.float64) * 1e-5).requires_grad_()
    assert torch.autograd.gradcheck(axis_angle_to_matrix, (small,))
    generic = torch.tensor([[0.3, -0.2, 0.9]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: matrix_to_axis_angle(axis_angle_to_matrix(v)), (generic,))
    # d R / d v at v = 0 is the skew-matrix basis: R ~ I + [v]_x.
    jacobian = torch.autograd.functional.jacobian(axis_angle_to_matrix, torch.zeros(3, dtype=torch.float64))
    x, y, z = torch.eye(3, dtype=torch.float64)
    zero3 = torch.zeros(3, dtype=torch.float64)
    expected = torch.stack((zero3, -z, y, z, zero3, -x, -y, x, zero3)).reshape(3, 3, 3)
    torch.testing.assert_close(jacobian, expected)


def test_rigid_inverse_and_transform_points():
    generator = torch.Generator().manual_seed(3)
    transform = rigid_matrix(axis_angle_to_matrix(random_rotvecs(generator, (5,))), torch.randn(5, 3, dtype=torch.float64))
    torch.testing.assert_close(transform @ invert_rigid(transform), torch.eye(4, dtype=torch.float64).expand(5, 4, 4))
    points = torch.randn(5, 3, dtype=torch.float64)
    homogeneous = torch.cat((points, torch.ones(5, 1, dtype=torch.float64)), -1)
    torch.testing.assert_close(transform_points(transform, points), (transform @ homogeneous[..., None])[..., :3, 0])


# ---- Skeleton validation -----------------------------------------------------------------------


def test_skeleton_accepts_a_valid_tree_and_is_read_only():
    skeleton = Skeleton(parents=PARENTS, rest_joints=np.zeros((J, 3)), joint_names=tuple(f"j{i}" for i in range(J)))
    assert skeleton.num_joints == J
    assert skeleton.index("j4") == 4
    assert skeleton.descendants(1).tolist() == [1, 2, 3, 6]
    with pytest.raises(ValueError):
        skeleton.rest_joints[0, 0] = 1.0
    smpl = Skeleton(np.array(SMPL_PARENTS), np.zeros((24, 3)), SMPL_JOINT_NAMES)
    assert smpl.descendants(SMPL_JOINT_NAMES.index("left_shoulder")).tolist() == [16, 18, 20, 22]


@pytest.mark.parametrize(
    ("parents", "rest", "names", "message"),
    [
        ([-1, 0, 1], np.zeros((2, 3)), ("a", "b", "c"), r"rest_joints has shape \(2, 3\), expected \(3, 3\)"),
        ([-1, 0, 1], np.zeros((3, 3)), ("a", "b"), "2 joint_names for 3 joints"),
        ([-1, 0, 0], np.zeros((3, 3)), ("a", "b", "b"), "duplicate joint names"),
        ([0, 0, 1], np.zeros((3, 3)), ("a", "b", "c"), "expected -1"),
        ([-1, -1, 1], np.zeros((3, 3)), ("a", "b", "c"), "single root"),
        ([-1, 2, 1], np.zeros((3, 3)), ("a", "b", "c"), "cycle"),
        ([-1, 1, 0], np.zeros((3, 3)), ("a", "b", "c"), "own parent"),
        ([-1, 2, 0], np.zeros((3, 3)), ("a", "b", "c"), "comes after it"),
        ([-1, 5, 0], np.zeros((3, 3)), ("a", "b", "c"), "not a joint index"),
        ([[-1, 0]], np.zeros((2, 3)), ("a", "b"), "expected \\(J,\\)"),
        ([-1, 0], np.array([[0, 0, 0], [np.nan, 0, 0]]), ("a", "b"), "NaN"),
    ],
)
def test_skeleton_rejects_bad_input(parents, rest, names, message):
    with pytest.raises(InputError, match=message):
        Skeleton(parents=np.array(parents), rest_joints=rest, joint_names=names)


def test_unknown_joint_name_is_an_input_error():
    skeleton = Skeleton(np.array([-1, 0]), np.zeros((2, 3)), ("root", "child"))
    with pytest.raises(InputError, match="no joint named 'knee'"):
        skeleton.index("knee")


# ---- forward kinematics ------------------------------------------------------------------------


def test_identity_pose_gives_rest_joints_plus_translation():
    generator = torch.Generator().manual_seed(4)
    rest = rest_joints(generator)
    translation = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    globals_ = forward_kinematics(torch.eye(3, dtype=torch.float64).expand(J, 3, 3), rest, PARENTS, translation)
    torch.testing.assert_close(globals_, rigid_matrix(torch.eye(3, dtype=torch.float64), rest + translation))
    canonical = forward_kinematics(torch.eye(3, dtype=torch.float64).expand(J, 3, 3), rest, PARENTS)
    transforms = bone_transforms(canonical, canonical)
    torch.testing.assert_close(transforms, torch.eye(4, dtype=torch.float64).expand(J, 4, 4))
    points = torch.randn(11, 3, dtype=torch.float64, generator=generator)
    weights = torch.softmax(torch.randn(11, J, dtype=torch.float64, generator=generator), -1)
    torch.testing.assert_close(linear_blend_skinning(points, weights, transforms), points)


def test_fk_matches_per_joint_reference_with_batch_dims():
    generator = torch.Generator().manual_seed(5)
    rest = rest_joints(generator)
    rotations = axis_angle_to_matrix(random_rotvecs(generator, (2, 3, J)))
    translation = torch.randn(2, 3, 3, dtype=torch.float64, generator=generator)
    globals_ = forward_kinematics(rotations, rest, PARENTS, translation)
    assert globals_.shape == (2, 3, J, 4, 4)
    for a in range(2):
        for b in range(3):
            expected = reference_fk(rotations[a, b], rest, PARENTS, translation[a, b])
            torch.testing.assert_close(globals_[a, b], expected, atol=1e-12, rtol=0)
    # A translation without batch dims broadcasts over the rotations' batch.
    shared = forward_kinematics(rotations, rest, torch.as_tensor(PARENTS), translation[0, 0])
    torch.testing.assert_close(shared[0, 0], globals_[0, 0])


def test_single_joint_rotation_moves_only_its_subtree_rigidly():
    generator = torch.Generator().manual_seed(6)
    rest = rest_joints(generator)
    skeleton = Skeleton(PARENTS, rest.numpy(), tuple(f"j{i}" for i in range(J)))
    joint = 1
    rotation = axis_angle_to_matrix(torch.tensor([0.4, -0.7, 0.2], dtype=torch.float64))
    rotations = torch.eye(3, dtype=torch.float64).repeat(J, 1, 1)
    rotations[joint] = rotation
    posed = forward_kinematics(rotations, rest, PARENTS)
    subtree = skeleton.descendants(joint)
    outside = np.setdiff1d(np.arange(J), subtree)
    torch.testing.assert_close(posed[outside, :3, 3], rest[outside])
    torch.testing.assert_close(posed[outside, :3, :3], torch.eye(3, dtype=torch.float64).expand(len(outside), 3, 3))
    expected_positions = (rotation @ (rest[subtree] - rest[joint])[..., None])[..., 0] + rest[joint]
    torch.testing.assert_close(posed[subtree, :3, 3], expected_positions)
    torch.testing.assert_close(posed[subtree, :3, :3], rotation.expand(len(subtree), 3, 3))


def test_root_rotation_turns_about_the_root_joint():
    rest = torch.tensor([[0.0, 1.0, 0.0], [0.0, 2.0, 0.0], [1.0, 1.0, 0.0]], dtype=torch.float64)
    rotations = torch.eye(3, dtype=torch.float64).repeat(3, 1, 1)
    rotations[0] = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
    posed = forward_kinematics(rotations, rest, [-1, 0, 0])
    expected = torch.tensor([[0.0, 1.0, 0.0], [-1.0, 1.0, 0.0], [0.0, 2.0, 0.0]], dtype=torch.float64)
    torch.testing.assert_close(posed[:, :3, 3], expected, atol=1e-15, rtol=0)


def test_fk_rejects_bad_shapes():
    rest = torch.zeros(J, 3)
    with pytest.raises(InputError, match="local_rotations has shape"):
        forward_kinematics(torch.eye(3).expand(J - 1, 3, 3), rest, PARENTS)
    with pytest.raises(InputError, match="rest_joints has shape"):
        forward_kinematics(torch.eye(3).expand(J, 3, 3), torch.zeros(J, 2), PARENTS)
    with pytest.raises(InputError, match="comes after it"):
        forward_kinematics(torch.eye(3).expand(3, 3, 3), torch.zeros(3, 3), [-1, 2, 0])


# ---- linear blend skinning ---------------------------------------------------------------------


def test_lbs_with_one_hot_weights_is_the_rigid_bone_transform():
    generator = torch.Generator().manual_seed(7)
    rest = rest_joints(generator)
    canonical_rotations = axis_angle_to_matrix(random_rotvecs(generator, (J,), 0.5))
    posed_rotations = axis_angle_to_matrix(random_rotvecs(generator, (4, J)))
    translation = torch.randn(4, 3, dtype=torch.float64, generator=generator)
    transforms = bone_transforms(
        forward_kinematics(posed_rotations, rest, PARENTS, translation),
        forward_kinematics(canonical_rotations, rest, PARENTS),
    )
    points = torch.randn(20, 3, dtype=torch.float64, generator=generator)
    bones = torch.randint(0, J, (20,), generator=generator)
    weights = torch.nn.functional.one_hot(bones, J).to(torch.float64)
    posed = linear_blend_skinning(points, weights, transforms)
    assert posed.shape == (4, 20, 3)
    expected = transform_points(transforms[:, bones], points)
    torch.testing.assert_close(posed, expected, atol=1e-12, rtol=0)


def test_lbs_is_the_weighted_sum_and_weights_may_be_batched():
    generator = torch.Generator().manual_seed(8)
    transforms = rigid_matrix(
        axis_angle_to_matrix(random_rotvecs(generator, (2, J))), torch.randn(2, J, 3, dtype=torch.float64, generator=generator)
    )
    points = torch.randn(2, 9, 3, dtype=torch.float64, generator=generator)
    weights = torch.softmax(torch.randn(2, 9, J, dtype=torch.float64, generator=generator), -1)
    expected = (weights[..., None] * transform_points(transforms[:, None], points[:, :, None])).sum(-2)
    torch.testing.assert_close(linear_blend_skinning(points, weights, transforms), expected, atol=1e-12, rtol=0)
    with pytest.raises(InputError, match="weights has shape"):
        linear_blend_skinning(points, weights[..., :-1], transforms)


def test_gradients_flow_through_fk_and_lbs():
    generator = torch.Generator().manual_seed(9)
    rest = rest_joints(generator)
    points = torch.randn(6, 3, dtype=torch.float64, generator=generator)
    weights = torch.softmax(torch.randn(6, J, dtype=torch.float64, generator=generator), -1)
    canonical = forward_kinematics(torch.eye(3, dtype=torch.float64).expand(J, 3, 3), rest, PARENTS)

    def posed_points(rotvecs: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
        globals_ = forward_kinematics(axis_angle_to_matrix(rotvecs), rest, PARENTS, translation)
        return linear_blend_skinning(points, weights, bone_transforms(globals_, canonical))

    rotvecs = (random_rotvecs(generator, (J,), 1.0)).requires_grad_()
    translation = torch.randn(3, dtype=torch.float64, generator=generator).requires_grad_()
    assert torch.autograd.gradcheck(posed_points, (rotvecs, translation))
    # And from the rest pose (zero rotation vectors), where Rodrigues switches to its series.
    zero = torch.zeros(J, 3, dtype=torch.float64, requires_grad=True)
    posed_points(zero, translation).square().sum().backward()
    assert torch.isfinite(zero.grad).all() and zero.grad.abs().sum() > 0


def test_float32_and_device_follow_the_input():
    rest = np.random.default_rng(0).normal(size=(J, 3))
    rotations = torch.eye(3).expand(J, 3, 3)
    globals_ = forward_kinematics(rotations, rest, PARENTS)
    assert globals_.dtype == torch.float32 and globals_.device == rotations.device
