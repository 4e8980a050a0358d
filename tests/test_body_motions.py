"""Procedural motions on the Anny and SMPL skeletons: shapes, determinism, and body-level checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from igavatar.body.motions import (
    MOTION_NAMES,
    NEUTRAL_ARM_ABDUCTION,
    SKELETON_KINDS,
    Motion,
    body_to_world,
    measure_proportions,
    motion_by_name,
    semantic_joint_map,
    turntable,
    walk,
)
from igavatar.body.rotations import axis_angle_to_matrix
from tests.rotation_oracles import rotation_angle
from igavatar.body.skeleton import NOMINAL_SMPL_REST_JOINTS, SMPL_JOINT_NAMES, SMPL_PARENTS, Skeleton, forward_kinematics
from igavatar.errors import InputError

SMPL_TPOSE_JOINTS = NOMINAL_SMPL_REST_JOINTS
SMPL_SKELETON = Skeleton(np.array(SMPL_PARENTS), SMPL_TPOSE_JOINTS, SMPL_JOINT_NAMES)
N_FRAMES = 24


@pytest.fixture(scope="module")
def anny_body():
    pytest.importorskip("anny")
    from igavatar.body.anny_body import AnnyBody

    return AnnyBody.load()


def skeleton_for(kind: str, anny_body_getter) -> Skeleton:
    return SMPL_SKELETON if kind == "smpl" else anny_body_getter().skeleton


def joint_positions(motion: Motion, skeleton: Skeleton) -> torch.Tensor:
    """(N, J, 3) posed joint positions, float64."""
    rotations = motion.local_rotations_for(skeleton, torch.float64)
    translation = motion.root_translation_tensor(torch.float64)
    return forward_kinematics(rotations, skeleton.rest_joints, skeleton.parents, translation)[..., :3, 3]


def body_axis(kind: str, name: str) -> np.ndarray:
    return body_to_world(kind)[:, ("left", "up", "forward").index(name)]


@pytest.mark.parametrize("kind", SKELETON_KINDS)
@pytest.mark.parametrize("name", MOTION_NAMES)
def test_motion_shapes_determinism_and_neutral_start(name: str, kind: str):
    motion = motion_by_name(name, kind, N_FRAMES, seed=3)
    joints = len(motion.joint_names)
    assert motion.local_rotvecs.shape == (N_FRAMES, joints, 3)
    assert motion.root_translation.shape == (N_FRAMES, 3)
    assert np.isfinite(motion.local_rotvecs).all() and np.isfinite(motion.root_translation).all()
    assert motion.fps == 30.0 and motion.name == name and motion.skeleton_kind == kind
    assert set(motion.joint_names) <= set(semantic_joint_map(kind).values())
    assert semantic_joint_map(kind)["pelvis"] in motion.joint_names
    again = motion_by_name(name, kind, N_FRAMES, seed=3)
    np.testing.assert_array_equal(again.local_rotvecs, motion.local_rotvecs)
    np.testing.assert_array_equal(again.root_translation, motion.root_translation)
    # The first frame is the neutral stance: Anny's rest pose; SMPL's T-pose with lowered arms.
    np.testing.assert_allclose(motion.root_translation[0], 0.0, atol=1e-12)
    first = dict(zip(motion.joint_names, np.linalg.norm(motion.local_rotvecs[0], axis=-1)))
    arms = {semantic_joint_map(kind)[f"{side}_upper_arm"] for side in ("left", "right")}
    for joint, angle in first.items():
        if kind == "smpl" and joint in arms:
            expected = measure_proportions("smpl").arm_abduction - NEUTRAL_ARM_ABDUCTION
            assert angle == pytest.approx(expected, abs=1e-9)
        else:
            assert angle < 1e-9, joint


def test_seeds_change_the_motion_and_lengths_follow_n_frames():
    a, b = walk("anny", 40, seed=0), walk("anny", 40, seed=1)
    assert np.abs(a.local_rotvecs - b.local_rotvecs).max() > 0.01
    assert motion_by_name("squat", "smpl", 7, seed=0).n_frames == 7
    assert motion_by_name("turn", "anny", 1, seed=0).n_frames == 1


def test_smpl_neutral_stance_lowers_the_t_pose_arms():
    motion = turntable("smpl", 8, small_motion=False)
    positions = joint_positions(motion, SMPL_SKELETON)[0].numpy()
    for side in ("left", "right"):
        shoulder = positions[SMPL_JOINT_NAMES.index(f"{side}_shoulder")]
        wrist = positions[SMPL_JOINT_NAMES.index(f"{side}_wrist")]
        arm = (wrist - shoulder) / np.linalg.norm(wrist - shoulder)
        assert math.acos(-arm[1]) == pytest.approx(NEUTRAL_ARM_ABDUCTION, abs=0.05)
        assert np.sign(arm[0]) == (1.0 if side == "left" else -1.0)
    proportions = measure_proportions("smpl", SMPL_SKELETON)
    assert proportions.arm_abduction == pytest.approx(measure_proportions("smpl").arm_abduction, abs=0.05)


@pytest.mark.parametrize("kind", SKELETON_KINDS)
def test_knees_flex_about_the_body_left_axis_on_every_skeleton(kind: str):
    motion = walk(kind, 45, seed=0)
    for side in ("left", "right"):
        knee = motion.local_rotvecs[:, motion.joint_names.index(semantic_joint_map(kind)[f"{side}_shin"])]
        np.testing.assert_allclose(knee @ body_axis(kind, "left"), np.linalg.norm(knee, axis=-1), atol=1e-9)
        assert np.linalg.norm(knee, axis=-1).max() > 0.6


@pytest.mark.parametrize("kind", SKELETON_KINDS)
def test_squat_keeps_the_feet_in_place_and_lowers_the_pelvis(kind: str, anny_body):
    skeleton = skeleton_for(kind, lambda: anny_body)
    motion = motion_by_name("squat", kind, 45, seed=0, skeleton=skeleton)
    positions = joint_positions(motion, skeleton).numpy()
    names = semantic_joint_map(kind)
    up = body_axis(kind, "up")
    for side in ("left", "right"):
        ankle = positions[:, skeleton.index(names[f"{side}_foot"])]
        assert np.abs(ankle - skeleton.rest_joints[skeleton.index(names[f"{side}_foot"])]).max() < 0.02
    pelvis_drop = (skeleton.rest_joints[0] - positions[:, 0]) @ up
    assert pelvis_drop.max() > 0.25


def test_walk_moves_forward_with_the_anny_mesh_on_the_ground(anny_body):
    motion = motion_by_name("walk", "anny", 60, seed=0, skeleton=anny_body.skeleton)
    rotations = motion.local_rotations_for(anny_body.skeleton)
    vertices = anny_body.posed_vertices(rotations, motion.root_translation_tensor())
    ground = float(anny_body.rest_vertices[:, 2].min())
    lowest = vertices[..., 2].min(dim=-1).values
    assert float(lowest.min()) > ground - 0.03  # not sinking into the floor
    assert float(lowest.max()) < ground + 0.03  # nor floating: one foot is always down
    travelled = motion.root_translation[-1] @ body_axis("anny", "forward")
    assert 0.8 < travelled < 2.5  # about 0.8 m/s for 2 s, towards the face (-Y)
    in_place = walk("anny", 60, seed=0, in_place=True)
    assert np.abs(in_place.root_translation @ body_axis("anny", "forward")).max() < 1e-12


def test_walk_keeps_smpl_ankles_above_their_rest_height():
    motion = walk("smpl", 60, seed=2, skeleton=SMPL_SKELETON)
    positions = joint_positions(motion, SMPL_SKELETON).numpy()
    ankles = [SMPL_JOINT_NAMES.index("left_ankle"), SMPL_JOINT_NAMES.index("right_ankle")]
    rest_height = SMPL_TPOSE_JOINTS[ankles, 1].min()
    lowest = positions[:, ankles, 1].min(axis=1)
    assert lowest.min() > rest_height - 0.01 and lowest.max() < rest_height + 0.03
    assert motion.root_translation[-1, 2] > 0.8  # SMPL faces +Z


@pytest.mark.parametrize("kind", SKELETON_KINDS)
def test_turntable_half_way_faces_the_opposite_direction(kind: str, anny_body):
    skeleton = skeleton_for(kind, lambda: anny_body)
    motion = turntable(kind, 40, seed=1, skeleton=skeleton)
    rotations = motion.local_rotations_for(skeleton, torch.float64)
    globals_ = forward_kinematics(rotations, skeleton.rest_joints, skeleton.parents)
    head = skeleton.index(semantic_joint_map(kind)["head"])
    forward = torch.as_tensor(body_axis(kind, "forward"))
    facing = globals_[:, head, :3, :3] @ forward
    assert float(facing[0] @ forward) > 0.95
    assert float(facing[20] @ forward) < -0.9  # half way: facing back (small head motion aside)
    assert float(facing[10] @ torch.as_tensor(body_axis(kind, "left"))) > 0.9  # quarter way: turned to its left
    # The pelvis turns in place and the whole turn is 360 degrees over the sequence.
    np.testing.assert_allclose(motion.root_translation, 0.0, atol=1e-12)
    root_angles = rotation_angle(axis_angle_to_matrix(torch.tensor(motion.local_rotvecs[:, 0])))
    assert float(root_angles[20]) == pytest.approx(math.pi, abs=1e-6)


def test_turntable_mesh_half_way_is_the_rest_mesh_rotated_by_pi(anny_body):
    motion = turntable("anny", 8, small_motion=False)
    vertices = anny_body.posed_vertices(motion.local_rotations_for(anny_body.skeleton, torch.float64))[4]
    rest = anny_body.rest_vertices.double()
    pivot = anny_body.skeleton.rest_joints_tensor(torch.float64)[0]
    flipped = (rest - pivot) * torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64) + pivot
    assert float((vertices - flipped).abs().max()) < 1e-5


def test_turn_ends_turned_by_90_to_180_degrees():
    for seed in range(4):
        motion = motion_by_name("turn", "smpl", 30, seed=seed)
        final = float(rotation_angle(axis_angle_to_matrix(torch.tensor(motion.local_rotvecs[-1, 0]))))
        assert math.pi / 2 - 1e-6 <= final <= math.pi + 1e-6


def test_measured_anny_proportions_match_the_nominal_ones(anny_body):
    measured = measure_proportions("anny", anny_body.skeleton)
    nominal = measure_proportions("anny")
    assert measured.arm_abduction == pytest.approx(nominal.arm_abduction, abs=0.01)
    assert measured.leg_height == pytest.approx(nominal.leg_height, abs=0.01)


def test_unknown_names_are_input_errors_that_list_the_valid_ones():
    with pytest.raises(InputError, match="unknown motion 'moonwalk'; valid motions: turntable, walk"):
        motion_by_name("moonwalk", "anny", 10)
    with pytest.raises(InputError, match="unknown skeleton kind 'mano'; valid kinds: anny, smpl"):
        motion_by_name("walk", "mano", 10)
    with pytest.raises(InputError, match="n_frames = 0"):
        motion_by_name("walk", "anny", 0)


def test_motion_validation_and_scattering_onto_a_skeleton():
    with pytest.raises(InputError, match=r"local_rotvecs has shape \(4, 2, 3\), expected \(N, 1, 3\)"):
        Motion(("root",), np.zeros((4, 2, 3)), np.zeros((4, 3)), fps=30.0)
    with pytest.raises(InputError, match=r"root_translation has shape \(3, 3\)"):
        Motion(("root",), np.zeros((4, 1, 3)), np.zeros((3, 3)), fps=30.0)
    with pytest.raises(InputError, match="NaN"):
        Motion(("root",), np.full((1, 1, 3), np.nan), np.zeros((1, 3)), fps=30.0)
    with pytest.raises(InputError, match="fps"):
        Motion(("root",), np.zeros((1, 1, 3)), np.zeros((1, 3)), fps=0.0)
    motion = Motion(("b", "root"), np.array([[[0.1, 0.0, 0.0], [0.0, 0.2, 0.0]]]), np.zeros((1, 3)), fps=24.0)
    skeleton = Skeleton(np.array([-1, 0, 1]), np.zeros((3, 3)), ("root", "a", "b"))
    np.testing.assert_allclose(motion.rotvecs_for(skeleton.joint_names)[0], [[0, 0.2, 0], [0, 0, 0], [0.1, 0, 0]])
    rotations = motion.local_rotations_for(skeleton)
    assert rotations.shape == (1, 3, 3, 3) and rotations.dtype == torch.float32
    torch.testing.assert_close(rotations[0, 1], torch.eye(3))
    with pytest.raises(InputError, match=r"drives joints \['b'\]"):
        motion.rotvecs_for(("root", "a"))
