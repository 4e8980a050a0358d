"""Canonical-shape checks on analytic meshes: a lost hand fails the limb check, a web between the
legs fails the gap check, the rest -> canonical transfer is exact for a rigid skeleton."""

from __future__ import annotations

import numpy as np
import trimesh

from igavatar.metrics.canonical import (
    LIMB_PARTS,
    canonical_from_rest,
    canonical_shape_report,
    leg_gap_check,
    leg_gap_points,
    limb_check,
    limb_labels,
    rest_to_canonical_transforms,
)


def _sphere(center, radius, subdivisions=3) -> trimesh.Trimesh:
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    mesh.apply_translation(center)
    return mesh


def _union(*meshes: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    mesh = trimesh.util.concatenate(meshes)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def test_limb_labels_follow_the_chain_to_the_nearest_part():
    names = ["root", "spine", "wrist.L", "finger.L", "head"]
    parents = np.array([-1, 0, 1, 2, 1])
    joint_map = {"pelvis": "root", "left_hand": "wrist.L", "head": "head"}
    labels = limb_labels(parents, names, joint_map, np.array([0, 1, 2, 3, 4]))
    part = {name: LIMB_PARTS.index(name) for name in ("pelvis", "left_hand", "head")}
    assert labels.tolist() == [part["pelvis"], part["pelvis"], part["left_hand"], part["left_hand"], part["head"]]


def test_limb_check_fails_exactly_the_part_whose_surface_is_missing():
    torso, hand = _sphere((0, 0, 0), 0.2), _sphere((0.6, 0, 0), 0.05)
    template_v = np.concatenate([torso.vertices * 0.95, hand.vertices - (0.6, 0, 0)])  # slightly inside
    template_v[len(torso.vertices):] = (hand.vertices - (0.6, 0, 0)) * 0.9 + (0.6, 0, 0)
    labels = np.concatenate([np.full(len(torso.vertices), LIMB_PARTS.index("pelvis")),
                             np.full(len(hand.vertices), LIMB_PARTS.index("left_hand"))])
    whole = limb_check(*_union(torso, hand), template_v, labels)
    assert whole["passed"] and whole["parts"]["left_hand"]["covered"] == 1.0
    no_hand = limb_check(np.asarray(torso.vertices), np.asarray(torso.faces), template_v, labels)
    assert not no_hand["passed"] and no_hand["failed_parts"] == ["left_hand"]
    assert no_hand["parts"]["pelvis"]["covered"] == 1.0 and no_hand["parts"]["left_hand"]["covered"] == 0.0


def test_leg_gap_check_finds_a_web_and_accepts_open_legs():
    index = {"left_thigh": 0, "right_thigh": 1, "left_shin": 2, "right_shin": 3}
    joints = np.array([[0.1, 0, 0], [-0.1, 0, 0], [0.25, 0, -0.45], [-0.25, 0, -0.45]])
    gap = leg_gap_points(joints, index)
    assert np.allclose(gap[:, 0], 0.0) and gap[:, 2].max() < 0 and gap[:, 2].min() >= -0.45
    legs = [trimesh.creation.cylinder(radius=0.06, segment=(joints[i], joints[i + 2])) for i in (0, 1)]
    open_legs = _union(*legs)
    assert leg_gap_check(*open_legs, gap, open_legs)["passed"]
    web = trimesh.creation.box(extents=(0.5, 0.05, 0.45))
    web.apply_translation((0, 0, -0.25))
    webbed = _union(*legs, web)
    result = leg_gap_check(*webbed, gap, open_legs)
    assert not result["passed"] and result["webbed"] > 0.5
    # A dress fills the gap in the truth too: then nothing there counts as a web.
    assert leg_gap_check(*webbed, gap, webbed)["points"] == 0


def test_leg_gap_check_does_not_judge_points_next_to_the_true_crotch():
    """A crotch 2 cm low fills the gap point 1 cm under the true one: a misplaced crotch, not a web."""
    index = {"left_thigh": 0, "right_thigh": 1, "left_shin": 2, "right_shin": 3}
    joints = np.array([[0.1, 0, 0], [-0.1, 0, 0], [0.25, 0, -0.45], [-0.25, 0, -0.45]])
    gap = leg_gap_points(joints, index)
    legs = [trimesh.creation.cylinder(radius=0.06, segment=(joints[i], joints[i + 2])) for i in (0, 1)]

    def with_shorts(bottom: float):
        shorts = trimesh.creation.box(bounds=((-0.2, -0.06, bottom), (0.2, 0.06, 0.05)))
        return _union(*legs, shorts)

    first = gap[:, 2].max()
    truth = with_shorts(first + 0.01)  # the true crotch 1 cm above the first gap point
    low = leg_gap_check(*with_shorts(first - 0.01), gap, truth)  # the crotch 2 cm low
    assert low["passed"] and low["near_points"] >= 1 and low["near_filled"] >= 1
    assert low["points"] == len(gap) - low["near_points"] and low["clearance_m"] == 0.02
    web = leg_gap_check(*with_shorts(-0.3), gap, truth)  # down to two thirds of the thighs
    assert not web["passed"] and web["webbed"] > 0.3
    # Judged strictly (no clearance) the low crotch is a web.
    assert not leg_gap_check(*with_shorts(first - 0.01), gap, truth, clearance=0.0)["passed"]


def test_rest_to_canonical_is_exact_for_a_rotated_joint():
    rest_joints = np.array([[0.0, 0, 0], [0.0, 0, 0.5]])
    parents = np.array([-1, 0])
    quarter = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # 90 degrees about z at joint 1
    transforms = rest_to_canonical_transforms(rest_joints, parents, np.stack([np.eye(3), quarter]))
    points = np.array([[1.0, 0, 0.5], [1.0, 0, 0.0]])
    moved = canonical_from_rest(points, np.array([[1, 0], [0, 1]]), np.array([[1.0, 0.0], [1.0, 0.0]]), transforms)
    assert np.allclose(moved, [[0.0, 1.0, 0.5], [1.0, 0.0, 0.0]])


def test_canonical_report_against_the_truth_itself_is_perfect():
    body = _sphere((0, 0, 0), 0.3, subdivisions=4)
    truth = (np.asarray(body.vertices), np.asarray(body.faces))
    labels = np.full(len(truth[0]), LIMB_PARTS.index("pelvis"))
    report = canonical_shape_report(truth, (truth[0] * 0.9, truth[1]), labels, None, truth, n_surface=2000, n_iou=20000)
    assert report["limb_check"]["passed"] and report["leg_gap"] is None
    assert report["against_truth"]["chamfer_l1_mm"] < 1e-6 and report["against_truth"]["volumetric_iou"] > 0.999
