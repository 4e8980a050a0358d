"""Skinning weights from bones: a partition of unity that follows the bones, keeps the legs
apart and the arms off the torso, and poses Anny's template almost as its own weights do."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from igavatar.body.bones import bone_segments, leaf_lengths, skeleton_kind
from igavatar.body.skeleton import Skeleton, forward_kinematics
from igavatar.capture.subject_skeleton import star_pose
from igavatar.errors import InputError
from igavatar.skinning.bone_weights import BoneWeightConfig, bone_skinning_weights, build_bone_skinning_grid
from igavatar.skinning.grid import grid_point_positions, sample_skinning_weights
from tests.smpl_like_skeleton import smpl_like_skeleton


def _canonical_joints(skeleton: Skeleton) -> np.ndarray:
    rotations = star_pose(skeleton, skeleton_kind(skeleton))
    return forward_kinematics(rotations.double(), skeleton.rest_joints, skeleton.parents)[:, :3, 3].numpy()


@pytest.fixture(scope="module")
def smpl_canonical():
    skeleton = smpl_like_skeleton()
    return skeleton, _canonical_joints(skeleton)


def _leg(skeleton: Skeleton, side: str) -> list[int]:
    return [skeleton.index(f"{side}_{part}") for part in ("hip", "knee", "ankle", "foot")]


def test_grid_is_a_partition_of_unity_in_the_grid_layout(smpl_canonical):
    skeleton, joints = smpl_canonical
    box_min, box_max = torch.tensor([-0.9, -1.2, -0.3]), torch.tensor([0.9, 0.6, 0.3])
    raw = build_bone_skinning_grid(joints, skeleton, box_min, box_max, (12, 8, 20), BoneWeightConfig(smoothing_iterations=0))
    assert raw.shape == (24, 12, 8, 20) and raw.dtype == torch.float32
    assert float(raw.min()) >= 0.0
    torch.testing.assert_close(raw.sum(dim=0), torch.ones(12, 8, 20), atol=1e-5, rtol=0)
    # Voxel (d, h, w) holds the weights of the point grid_point_positions puts there, and
    # grid_sample's lookup at that point returns them (the (J, D, H, W) <-> (z, y, x) layout).
    positions = grid_point_positions(box_min.double(), box_max.double(), (12, 8, 20)).reshape(-1, 3)
    direct = bone_skinning_weights(positions, joints, skeleton, BoneWeightConfig(smoothing_iterations=0))
    torch.testing.assert_close(raw.reshape(24, -1).T, direct)
    sampled = sample_skinning_weights(raw, box_min, box_max, positions.float())
    torch.testing.assert_close(sampled, direct, atol=1e-4, rtol=0)
    smoothed = build_bone_skinning_grid(joints, skeleton, box_min, box_max, (12, 8, 20))
    torch.testing.assert_close(smoothed.sum(dim=0), torch.ones(12, 8, 20), atol=1e-5, rtol=0)


def test_the_middle_of_each_bone_belongs_to_that_bone(smpl_canonical):
    skeleton, joints = smpl_canonical
    segments = bone_segments(joints, skeleton.parents, leaf_lengths(skeleton, "smpl"))
    # Bones of 10 cm or more: shorter ones (SMPL's spine2) have neighbours within a temperature or two.
    long = np.linalg.norm(segments.end - segments.start, axis=1) >= 0.1
    assert long.sum() >= 18
    middles = 0.5 * (segments.start + segments.end)[long]
    weights = bone_skinning_weights(middles, joints, skeleton).numpy()
    own = weights[np.arange(len(middles)), segments.joint[long]]
    for b in np.flatnonzero(own < 0.9):
        raise AssertionError(f"middle of {skeleton.joint_names[segments.joint[long][b]]}'s bone: own weight {own[b]:.2f}")


def test_thighs_share_no_weight_and_arms_stay_off_the_torso(smpl_canonical):
    skeleton, joints = smpl_canonical
    left, right = _leg(skeleton, "left"), _leg(skeleton, "right")
    hip, knee = joints[skeleton.index("left_hip")], joints[skeleton.index("left_knee")]
    axis = (knee - hip) / np.linalg.norm(knee - hip)
    ring = []  # points on a 7 cm tube around the upper two thirds of the left thigh, inner side included
    for t in np.linspace(0.1, 0.66, 6):
        for angle in np.linspace(0, 2 * np.pi, 12, endpoint=False):
            radial = np.cos(angle) * np.cross(axis, [0, 0, 1]) + np.sin(angle) * np.array([0, 0, 1.0])
            ring.append(hip + t * (knee - hip) + 0.07 * radial / np.linalg.norm(radial))
    ring = np.array(ring)
    weights = bone_skinning_weights(ring, joints, skeleton).numpy()
    assert weights[:, right].sum(axis=1).max() < 1e-3
    mirrored = bone_skinning_weights(ring * [-1, 1, 1], joints, skeleton).numpy()
    assert mirrored[:, left].sum(axis=1).max() < 1e-3
    # The torso's side under the armpit (T-pose): not the upper arm's.
    shoulder = joints[skeleton.index("left_shoulder")]
    torso_side = shoulder + np.array([[-0.04, -0.10, 0.0], [-0.05, -0.15, 0.02], [-0.05, -0.20, -0.02]])
    arm = [skeleton.index(n) for n in ("left_shoulder", "left_elbow", "left_wrist", "left_hand")]
    assert bone_skinning_weights(torso_side, joints, skeleton).numpy()[:, arm].sum(axis=1).max() < 0.1


def test_skeletons_of_unknown_kind_and_a_single_joint():
    chain = Skeleton(np.array([-1, 0, 1]), np.array([[0, 0, 0], [0, 0.3, 0], [0, 0.6, 0.0]]), ("a", "b", "c"))
    assert skeleton_kind(chain) is None
    points = np.array([[0.0, 0.15, 0.0], [0.0, 0.45, 0.05], [0.0, 0.75, 0.0]])
    weights = bone_skinning_weights(points, chain.rest_joints, chain).numpy()
    assert weights.argmax(axis=1).tolist() == [0, 1, 2]  # the leaf moves the part beyond it
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=1e-6)
    lone = Skeleton(np.array([-1]), np.zeros((1, 3)), ("root",))
    grid = build_bone_skinning_grid(np.zeros((1, 3)), lone, torch.full((3,), -1.0), torch.ones(3), (2, 3, 4))
    assert torch.equal(grid, torch.ones(1, 2, 3, 4))


def test_bad_inputs_name_the_shape(smpl_canonical):
    skeleton, joints = smpl_canonical
    with pytest.raises(InputError, match=r"joints have shape \(23, 3\), expected \(24, 3\)"):
        bone_skinning_weights(np.zeros((1, 3)), joints[:23], skeleton)
    with pytest.raises(InputError, match=r"points have shape \(4,\), expected \(P, 3\)"):
        bone_skinning_weights(np.zeros(4), joints, skeleton)
    with pytest.raises(InputError, match="temperature_m"):
        bone_skinning_weights(np.zeros((1, 3)), joints, skeleton, BoneWeightConfig(temperature_m=0.0))


def test_bone_weights_pose_annys_template_almost_like_its_own_weights():
    """Anny's canonical template posed for the synthetic test motions with bone-derived grid weights
    lands within a few centimeters of the template posed with Anny's real skinning weights."""
    from igavatar.body.anny_body import AnnyBody
    from igavatar.body.motions import motion_by_name
    from igavatar.body.rotations import invert_rigid
    from igavatar.body.skeleton import bone_transforms, linear_blend_skinning
    from igavatar.skinning.grid import build_skinning_grid, canonical_grid_box

    body = AnnyBody.load({})
    skeleton = body.skeleton
    assert skeleton_kind(skeleton) == "anny"
    canonical = star_pose(skeleton, "anny")
    torch.testing.assert_close(canonical, body.canonical_star_pose())  # one canonical space for both
    rest = skeleton.rest_joints_tensor()
    global_rest = forward_kinematics(torch.eye(3).expand(skeleton.num_joints, 3, 3), rest, skeleton.parents)
    global_canonical = forward_kinematics(canonical, rest, skeleton.parents)
    weights = body.skinning_weights.float()
    template = linear_blend_skinning(body.rest_vertices.float(), weights, global_canonical @ invert_rigid(global_rest))
    rotations = torch.cat([
        motion_by_name(name, "anny", n_frames=6, seed=1).local_rotations_for(skeleton) for name in ("walk", "arm_raise", "squat")
    ])
    transforms = bone_transforms(forward_kinematics(rotations, rest, skeleton.parents), global_canonical)
    truth = linear_blend_skinning(template, weights, transforms)

    box_min, box_max = canonical_grid_box(template, squeeze_axis=1)
    bone_grid = build_bone_skinning_grid(global_canonical[:, :3, 3], skeleton, box_min, box_max, (64, 16, 64))
    template_grid = build_skinning_grid(template, weights, box_min, box_max, (64, 16, 64))
    errors = {}
    for name, grid in (("bones", bone_grid), ("template", template_grid)):
        posed = linear_blend_skinning(template, sample_skinning_weights(grid, box_min, box_max, template), transforms)
        errors[name] = (posed - truth).norm(dim=-1)
    bones, reference = errors["bones"], errors["template"]
    assert bones.median() < 0.01 and bones.quantile(0.95) < 0.03, (bones.median(), bones.quantile(0.95))
    # No worse than the grid made from the template's own (blurred) weights, where most of the body is.
    assert bones.quantile(0.95) <= reference.quantile(0.95), (bones.quantile(0.95), reference.quantile(0.95))
