"""SMPL motions retargeted onto Anny's skeleton: bone directions, the raised arm, the root path."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from igavatar.body.motions import body_to_world, semantic_joint_map
from igavatar.body.retarget import (
    BONE_END,
    NOMINAL_SMPL_REST_JOINTS,
    nominal_smpl_skeleton,
    retarget_sequence,
    shortest_rotation,
)
from igavatar.body.rotations import axis_angle_to_matrix
from igavatar.body.skeleton import SMPL_JOINT_NAMES, SMPL_PARENTS, Skeleton, forward_kinematics
from igavatar.errors import NotAvailableError
from igavatar.body.pose_files import read_pose_sequence, sequence_local_pose

SMPL_TO_ANNY = body_to_world("anny") @ body_to_world("smpl").T  # SMPL world axes -> Anny's


@pytest.fixture(scope="module")
def anny_skeleton() -> Skeleton:
    pytest.importorskip("anny")
    from igavatar.body.anny_body import AnnyBody

    return AnnyBody.load().skeleton


def posed_joints(skeleton: Skeleton, rotations: torch.Tensor, translation: torch.Tensor) -> np.ndarray:
    """(N, J, 3) world joint positions."""
    return forward_kinematics(rotations.double(), skeleton.rest_joints, skeleton.parents, translation.double())[..., :3, 3].numpy()


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def bone(joints: np.ndarray, skeleton: Skeleton, kind: str, part: str) -> np.ndarray:
    """(N, 3) unit direction of `part`'s bone (its joint to the next named joint) per frame."""
    names = semantic_joint_map(kind)
    start, end = skeleton.index(names[part]), skeleton.index(names[BONE_END[part]])
    return unit(joints[:, end] - joints[:, start])


def test_shortest_rotation_maps_a_onto_b():
    rng = np.random.default_rng(0)
    for a, b in [rng.normal(size=(2, 3)) for _ in range(5)] + [(np.array([1.0, 0, 0]), np.array([-2.0, 0, 0]))]:
        rotation = shortest_rotation(a, b)
        np.testing.assert_allclose(rotation @ unit(a), unit(b), atol=1e-12)
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0)


def test_every_mapped_bone_points_where_the_smpl_bone_points(anny_skeleton):
    """For random SMPL poses, each named Anny bone is parallel to its SMPL bone (in Anny's axes)."""
    rng = np.random.default_rng(1)
    rotvecs = rng.normal(scale=0.4, size=(6, 24, 3))
    transl = rng.normal(size=(6, 3))
    rotations, translation = retarget_sequence(rotvecs, transl, anny_skeleton, "smpl", "anny")
    anny = posed_joints(anny_skeleton, rotations, translation)
    smpl_skeleton = nominal_smpl_skeleton()
    smpl = posed_joints(smpl_skeleton, axis_angle_to_matrix(torch.tensor(rotvecs)), torch.tensor(transl))
    for part in BONE_END:
        expected = bone(smpl, smpl_skeleton, "smpl", part) @ SMPL_TO_ANNY.T
        np.testing.assert_allclose(bone(anny, anny_skeleton, "anny", part), expected, atol=1e-9, err_msg=part)


def test_identity_smpl_pose_is_smpls_t_pose_on_anny(anny_skeleton):
    """The rest SMPL pose means 'T-pose': Anny's arms go level (its own rest is an A-pose)."""
    rotations, translation = retarget_sequence(np.zeros((1, 24, 3)), np.zeros((1, 3)), anny_skeleton, "smpl", "anny")
    anny = posed_joints(anny_skeleton, rotations, translation)
    for side, sign in (("left", 1.0), ("right", -1.0)):
        arm = bone(anny, anny_skeleton, "anny", f"{side}_upper_arm")[0]
        # Sideways (+-X) and level (Anny is +Z up) to within SMPL's own slight droop (~3 degrees).
        assert arm[0] * sign > 0.99 and abs(arm[2]) < 0.1, arm
        leg = bone(anny, anny_skeleton, "anny", f"{side}_shin")[0]
        assert leg[2] < -0.99, leg  # straight down
    # The root keeps Anny's rest orientation and position.
    np.testing.assert_allclose(rotations[0, 0].numpy(), np.eye(3), atol=1e-12)
    np.testing.assert_allclose(anny[0, 0], anny_skeleton.rest_joints[0], atol=1e-12)


def test_raising_the_left_arm_raises_anny_s_left_arm(anny_skeleton, tmp_path):
    """An SMPL file whose left shoulder turns the arm up by 0..80 degrees, read like any pose file."""
    n_frames = 5
    angles = np.radians(np.linspace(0.0, 80.0, n_frames))
    poses = np.zeros((n_frames, 72))
    poses[:, 3 * SMPL_JOINT_NAMES.index("left_shoulder") + 2] = angles  # about +Z (forward): +X arm goes up
    trans = np.zeros((n_frames, 3))
    np.savez(tmp_path / "raise.npz", poses=poses, trans=trans)
    sequence = read_pose_sequence(tmp_path / "raise.npz")
    rotations, translation = sequence_local_pose(sequence, anny_skeleton, "anny", phenotype={})
    anny = posed_joints(anny_skeleton, rotations, translation)
    names = semantic_joint_map("anny")
    wrist = {side: anny[:, anny_skeleton.index(names[f"{side}_hand"])] for side in ("left", "right")}
    shoulder = anny[:, anny_skeleton.index(names["left_upper_arm"])]
    # Anny is +Z up: the left wrist rises frame by frame, to the arm's angle above level.
    assert np.all(np.diff(wrist["left"][:, 2]) > 0.02)
    elevation = np.degrees(np.arcsin(unit(wrist["left"] - shoulder)[:, 2]))
    np.testing.assert_allclose(elevation, np.degrees(angles), atol=3.0)
    # The right arm and the root do not move.
    np.testing.assert_allclose(wrist["right"], wrist["right"][:1].repeat(n_frames, 0), atol=1e-6)
    np.testing.assert_allclose(anny[:, 0], anny[:1, 0].repeat(n_frames, 0), atol=1e-6)


def test_root_trajectory_and_facing_are_preserved(anny_skeleton):
    """Walking forward (+Z in SMPL) and turning left moves Anny forward (-Y) and turns it about +Z."""
    n_frames = 4
    transl = np.stack([np.zeros(n_frames), 0.02 * np.arange(n_frames), 0.5 * np.arange(n_frames)], axis=1)
    rotvecs = np.zeros((n_frames, 24, 3))
    rotvecs[:, 0, 1] = np.radians(30.0) * np.arange(n_frames)  # yaw about SMPL's up (+Y)
    rotations, translation = retarget_sequence(rotvecs, transl, anny_skeleton, "smpl", "anny")
    anny = posed_joints(anny_skeleton, rotations, translation)
    np.testing.assert_allclose(anny[:, 0] - anny[0, 0], (transl - transl[0]) @ SMPL_TO_ANNY.T, atol=1e-9)
    np.testing.assert_allclose(anny[-1, 0] - anny[0, 0], [0.0, -1.5, 0.06], atol=1e-9)  # forward is -Y, up +Z
    expected_yaw = axis_angle_to_matrix(torch.tensor([[0.0, 0.0, np.radians(90.0)]], dtype=torch.float64))[0]
    np.testing.assert_allclose(rotations[-1, 0].numpy(), expected_yaw.numpy(), atol=1e-9)


@pytest.mark.parametrize(("world", "orient"), [("z-up (AMASS)", [np.pi / 2, 0, 0]), ("y-down (camera)", [np.pi, 0, 0]),
                                               ("y-up (AIST++)", [0, 0, 0])])
def test_sequences_from_any_upright_world_stand_upright_on_anny(anny_skeleton, world, orient):
    """The pelvis' up axis picks the world's up: Anny's head ends above its pelvis (+Z) every time."""
    rng = np.random.default_rng(3)
    rotvecs = rng.normal(scale=0.05, size=(4, 24, 3))  # a little bend in every joint
    rotvecs[:, 0] = orient
    transl = np.zeros((4, 3))
    transl[:, 0] = np.arange(4) * 0.3  # sideways steps: their length survives the world turn
    rotations, translation = retarget_sequence(rotvecs, transl, anny_skeleton, "smpl", "anny")
    anny = posed_joints(anny_skeleton, rotations, translation)
    names = semantic_joint_map("anny")
    up = unit(anny[:, anny_skeleton.index(names["head"])] - anny[:, anny_skeleton.index(names["pelvis"])])
    assert np.all(up[:, 2] > 0.85), (world, up)  # upright but for the bent spine and neck
    steps = np.linalg.norm(np.diff(anny[:, 0], axis=0), axis=1)
    np.testing.assert_allclose(steps, 0.3, atol=1e-9)


def test_no_retarget_is_a_clear_error():
    target = Skeleton(np.array(SMPL_PARENTS), NOMINAL_SMPL_REST_JOINTS, SMPL_JOINT_NAMES)
    with pytest.raises(NotAvailableError, match="no retarget from anny skeletons to smpl skeletons"):
        retarget_sequence(np.zeros((1, 24, 3)), np.zeros((1, 3)), target, "anny", "smpl")
