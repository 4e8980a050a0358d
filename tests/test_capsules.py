"""The capsule shape prior: an exact capsule SDF, a closed outward mesh of the right volume, a body
that holds its joints, and per-frame boxes that hold the posed capsules."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from igavatar.body.capsules import (
    CAPSULE_RADII_M,
    Capsules,
    capsule_mesh,
    capsule_prior,
    capsule_radii,
    posed_capsule_boxes,
    skeleton_capsules,
)
from igavatar.body.skeleton import Skeleton, bone_transforms, forward_kinematics
from igavatar.body.rotations import axis_angle_to_matrix
from igavatar.capture.subject_skeleton import star_pose
from igavatar.errors import InputError
from tests.smpl_like_skeleton import smpl_like_skeleton


def _one_capsule(radius: float = 0.1, length: float = 0.5) -> Capsules:
    return Capsules(torch.zeros(1, dtype=torch.long), torch.zeros(1, 3), torch.tensor([[0.0, length, 0.0]]), torch.tensor([radius]))


def test_capsule_sdf_is_the_distance_to_the_segment_minus_the_radius():
    capsule = _one_capsule()
    points = torch.tensor([[0.0, 0.25, 0.0], [0.3, 0.25, 0.0], [0.0, -0.2, 0.0], [0.0, 0.7, 0.4], [0.05, 0.0, 0.0]])
    expected = torch.tensor([-0.1, 0.2, 0.1, np.hypot(0.2, 0.4) - 0.1, -0.05])
    torch.testing.assert_close(capsule.sdf(points), expected.float(), atol=1e-6, rtol=0)


def test_capsule_mesh_is_closed_outward_and_of_the_capsule_volume():
    vertices, faces = capsule_mesh(_one_capsule(), voxel_m=0.01)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    analytic = np.pi * 0.1**2 * 0.5 + 4 / 3 * np.pi * 0.1**3
    assert mesh.volume > 0, "normals point inwards"
    assert abs(mesh.volume - analytic) / analytic < 0.03, (mesh.volume, analytic)
    with pytest.raises(InputError, match="voxel_m"):
        capsule_mesh(_one_capsule(), voxel_m=0.0)


def test_smpl_capsule_body_holds_its_joints_and_reaches_the_crown():
    skeleton = smpl_like_skeleton()
    canonical = star_pose(skeleton, "smpl")
    global_canonical = forward_kinematics(canonical, skeleton.rest_joints_tensor(), skeleton.parents)
    joints = global_canonical[:, :3, 3]
    rotvecs = torch.zeros(3, 24, 3)
    rotvecs[1, skeleton.index("left_shoulder")] = torch.tensor([0.0, 0.0, -1.2])  # arm down
    rotvecs[2, skeleton.index("right_knee")] = torch.tensor([1.4, 0.0, 0.0])  # knee bent
    posed = forward_kinematics(axis_angle_to_matrix(rotvecs), skeleton.rest_joints_tensor(), skeleton.parents,
                               torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 2.0], [0.0, 0.9, 0.0]]))
    prior = capsule_prior(skeleton, joints, bone_transforms(posed, global_canonical))
    mesh = trimesh.Trimesh(prior.vertices.numpy(), prior.faces.numpy(), process=False)
    assert mesh.is_watertight and mesh.volume > 0
    assert len(mesh.split(only_watertight=False)) == 1, "the capsules of a tree form one body"
    assert mesh.contains(joints.numpy()).all()
    # The crown is ~0.2 m above SMPL's head joint; the body is an adult's (0.06-0.09 m^3).
    head = joints[skeleton.index("head")]
    assert 0.15 < float(prior.vertices[:, 1].max() - head[1]) < 0.3
    assert 0.05 < mesh.volume < 0.1, mesh.volume
    # Boxes hold the posed joints, with room for the flesh around them.
    posed_joints = posed[:, :, :3, 3]
    assert prior.posed_boxes.shape == (3, 2, 3)
    assert (posed_joints >= prior.posed_boxes[:, None, 0] + 0.03).all()
    assert (posed_joints <= prior.posed_boxes[:, None, 1] - 0.03).all()


def test_posed_boxes_are_exact_for_rigidly_moved_capsules():
    capsules = _one_capsule()
    turn = torch.eye(4).repeat(1, 1, 1, 1)
    turn[0, 0, :3, :3] = axis_angle_to_matrix(torch.tensor([0.0, 0.0, np.pi / 2]))  # y axis -> -x
    turn[0, 0, :3, 3] = torch.tensor([1.0, 2.0, 3.0])
    box = posed_capsule_boxes(capsules, turn)[0]
    torch.testing.assert_close(box, torch.tensor([[1.0 - 0.6, 1.9, 2.9], [1.1, 2.1, 3.1]]), atol=1e-6, rtol=0)


def test_radii_follow_the_part_table_and_the_tree():
    skeleton = smpl_like_skeleton()
    radii = dict(zip(skeleton.joint_names, capsule_radii(skeleton)))
    scale = radii["left_hip"] / CAPSULE_RADII_M["thigh"]
    assert 0.9 < scale < 1.1  # an adult leg: about the table's scale
    assert radii["left_hand"] == radii["left_wrist"]  # a joint the table does not name: its parent's
    assert radii["spine1"] > radii["left_hip"] > radii["left_knee"] > radii["left_elbow"]
    child = capsule_radii(smpl_like_skeleton(scale=0.6))
    np.testing.assert_allclose(child, capsule_radii(skeleton) * 0.6, rtol=1e-6)  # radii scale with the legs
    # Unknown kind: thicker where more of the tree hangs, all positive.
    chain = Skeleton(np.array([-1, 0, 1, 2]), np.array([[0, 0, 0], [0, 0.4, 0], [0, 0.8, 0], [0, 1.2, 0.0]]), tuple("abcd"))
    generic = capsule_radii(chain)
    assert np.all(generic > 0) and np.all(np.diff(generic) < 0)
    with pytest.raises(InputError, match=r"radii \(3,\)"):
        skeleton_capsules(chain.rest_joints, chain, generic[:3])
