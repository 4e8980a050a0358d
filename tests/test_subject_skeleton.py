"""The 'skeleton' body model: poses.npz -> PosedSubject (star pose for known kinds, major bones),
its round trip from another body's subject, clear errors, and preprocess without a template."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from igavatar.artifacts.manifest import read_artifact
from igavatar.body.rotations import axis_angle_to_matrix
from igavatar.body.skeleton import SMPL_PARENTS
from igavatar.capture.capture_v1 import read_capture_v1
from igavatar.capture.subject import canonicalize, major_bones, subject_from_capture
from igavatar.capture.subject_skeleton import longest_bones, skeleton_subject
from igavatar.synth.skeleton_capture import bare_skeleton_poses
from igavatar.errors import InputError
from stages.preprocess import PreprocessOptions, run_preprocess
from tests.smpl_like_skeleton import SMPL_LIKE_REST_JOINTS, smpl_like_skeleton


def _write_poses(capture, **arrays) -> None:
    poses = dict(np.load(capture / "poses.npz"))
    poses.update(arrays)
    np.savez(capture / "poses.npz", **{k: v for k, v in poses.items() if v is not None})


def _smpl_tree_capture(capture, n_frames: int = 3) -> np.ndarray:
    rotvecs = np.random.default_rng(0).normal(0.0, 0.3, (n_frames, 24, 3))
    _write_poses(capture, parents=np.array(SMPL_PARENTS), rest_joints=SMPL_LIKE_REST_JOINTS, rotvecs=rotvecs)
    return rotvecs


def test_a_chain_of_unknown_kind_stays_in_its_rest_pose(tiny_skeleton_capture):
    subject = subject_from_capture(read_capture_v1(tiny_skeleton_capture))
    assert subject.body_model == "skeleton" and subject.template_vertices_rest is None
    assert subject.template_faces is None and subject.template_weights is None
    assert subject.skeleton.joint_names == ("joint_00", "joint_01", "joint_02")
    assert torch.equal(subject.canonical_rotations, torch.eye(3).expand(3, 3, 3))
    assert subject.init_bones == (0, 1, 2) and subject.description == {"skeleton_kind": "unknown"}


def test_smpl_tree_gets_smpl_names_a_star_pose_and_the_major_bones(tiny_skeleton_capture):
    rotvecs = _smpl_tree_capture(tiny_skeleton_capture)
    subject = subject_from_capture(read_capture_v1(tiny_skeleton_capture))
    skeleton = smpl_like_skeleton()
    assert subject.skeleton.joint_names == skeleton.joint_names
    assert subject.description == {"skeleton_kind": "smpl"}
    assert subject.init_bones == major_bones(skeleton, "smpl")
    torch.testing.assert_close(subject.local_rotations, axis_angle_to_matrix(torch.tensor(rotvecs)).float())
    canonical = canonicalize(subject).canonical_joints
    rest = torch.tensor(SMPL_LIKE_REST_JOINTS, dtype=torch.float32)
    for side, sign in (("left", 1.0), ("right", -1.0)):  # the legs spread sideways by 0.5 rad, +X is the left
        hip, ankle = (skeleton.index(f"{side}_{j}") for j in ("hip", "ankle"))
        before, after = rest[ankle] - rest[hip], canonical[ankle] - canonical[hip]
        angle = torch.atan2(sign * after[0], -after[1]) - torch.atan2(sign * before[0], -before[1])
        assert abs(float(angle) - 0.5) < 1e-4 and abs(float(after.norm() - before.norm())) < 1e-5
    torch.testing.assert_close(canonical[[0, 3]], rest[[0, 3]])  # the trunk stays


def test_skeleton_poses_round_trip(tiny_skeleton_capture):
    _smpl_tree_capture(tiny_skeleton_capture)
    subject = subject_from_capture(read_capture_v1(tiny_skeleton_capture))
    _write_poses(tiny_skeleton_capture, **bare_skeleton_poses(subject.skeleton, subject.local_rotations, subject.root_translation))
    again = subject_from_capture(read_capture_v1(tiny_skeleton_capture))
    torch.testing.assert_close(again.local_rotations, subject.local_rotations, atol=1e-5, rtol=0)
    torch.testing.assert_close(again.root_translation, subject.root_translation)
    assert again.skeleton.joint_names == subject.skeleton.joint_names


def test_longest_bones_of_an_unknown_skeleton():
    skeleton = smpl_like_skeleton()
    renamed = type(skeleton)(skeleton.parents, skeleton.rest_joints, tuple(f"j{j}" for j in range(24)))
    chosen = longest_bones(renamed)
    assert len(chosen) == 14 and chosen[0] == 0
    # Thighs, shins, upper arms and forearms move the most: all chosen; fingers-to-tips are not.
    assert {1, 2, 4, 5, 16, 17, 18, 19} <= set(chosen) and not {22, 23} & set(chosen)


@pytest.mark.parametrize(
    ("arrays", "message"),
    [
        ({"parents": np.array([-1.0, 0.0, 1.0])}, r"poses.npz: key 'parents' has dtype float64, expected integers"),
        ({"parents": np.array([-1, 2, 1])}, r"poses.npz: skeleton: .*never reaches the root|poses.npz: skeleton: joint 1 has parent 2"),
        ({"joint_names": np.array(["a", "b"])}, r"poses.npz: key 'joint_names' has shape \(2,\)"),
        ({"joint_names": np.array(["a", "a", "b"])}, r"poses.npz: skeleton: duplicate joint names"),
    ],
)
def test_bad_skeletons_name_the_file_and_key(tiny_skeleton_capture, arrays, message):
    _write_poses(tiny_skeleton_capture, **arrays)
    with pytest.raises(InputError, match=message):
        skeleton_subject(read_capture_v1(tiny_skeleton_capture))


def test_preprocess_builds_capsules_and_bone_weights_without_a_template(tiny_skeleton_capture, tmp_path):
    run_preprocess(PreprocessOptions(capture=tiny_skeleton_capture, out=tmp_path / "dataset", grid_resolution=(16, 8, 16)))
    manifest = read_artifact(tmp_path / "dataset", expected="dataset")
    data = manifest["data"]
    assert data["shape_prior"] == "capsules" and data["has_template"] and data["body_model"] == "skeleton"
    mesh = trimesh.load(tmp_path / "dataset" / "template.ply", process=False)
    assert mesh.is_watertight and mesh.volume > 0
    subject = np.load(tmp_path / "dataset" / "subject.npz")
    grid = subject["skinning_grid"]
    assert grid.shape == (3, 16, 8, 16) and grid.min() >= 0
    np.testing.assert_allclose(grid.sum(axis=0), 1.0, atol=1e-5)
    box = subject["canonical_box"]
    assert np.all(box[0] <= mesh.bounds[0] + 1e-6) and np.all(box[1] >= mesh.bounds[1] - 1e-6)
    # Posed boxes hold the capsule body in every frame (the capture does not move).
    frames = np.load(tmp_path / "dataset" / "frames.npz")
    assert np.all(frames["posed_boxes"][:, 0] <= mesh.bounds[0]) and np.all(frames["posed_boxes"][:, 1] >= mesh.bounds[1])
