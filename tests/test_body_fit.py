"""Anny fitted to a bare skeleton (igavatar.body.anny_fit, igavatar.capture.body_fit, preprocess --body-fit)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
import trimesh

pytest.importorskip("anny")

from igavatar.artifacts.manifest import read_artifact  # noqa: E402
from igavatar.body.anny_body import AnnyBody, load_anny  # noqa: E402
from igavatar.body.anny_fit import anny_bone_targets, fit_anny_to_skeleton  # noqa: E402
from igavatar.body.motions import semantic_joint_map  # noqa: E402
from igavatar.body.retarget import nominal_smpl_skeleton  # noqa: E402
from stages.preprocess import PreprocessOptions, run_preprocess  # noqa: E402
from stages.synth import SynthOptions, run_synth  # noqa: E402

SUBJECT = {"gender": 0.2, "age": 0.5, "muscle": 0.5, "weight": 0.8, "height": 0.8, "proportions": 0.5}


@pytest.fixture(scope="module")
def model():
    return load_anny()


def test_fit_to_annys_own_joints_recovers_the_proportions_not_the_girth(model):
    truth = AnnyBody(model, SUBJECT)
    fit = fit_anny_to_skeleton(model, truth.skeleton, "anny")
    assert fit.same_rig and fit.joints_compared == 104
    # Joints fix the proportions: every fitted value within 0.02 of the subject's.
    for label in ("gender", "age", "height", "proportions"):
        assert abs(fit.phenotype[label] - SUBJECT[label]) < 0.02, (label, fit.phenotype)
    # ...but not the girth, which stays at Anny's average.
    assert fit.phenotype["weight"] == 0.5 and fit.phenotype["muscle"] == 0.5
    assert fit.joint_rms_m < 0.002
    # Same rig: the weights are Anny's own, and the body stands in the skeleton's rest pose.
    torch.testing.assert_close(fit.weights, truth.skinning_weights)
    average = AnnyBody(model, fit.phenotype)
    offset = fit.vertices.double() - average.rest_vertices.double()
    assert float(offset.norm(dim=1).max()) < 0.005  # only the sub-millimetre rebinding moved it
    # A lighter girth than the subject's: the fitted body lies inside the true one around the belly.
    belly = truth.skinning_weights[:, truth.skeleton.index("spine03")] > 0.5
    assert float(fit.vertices[belly].abs()[:, 1].mean()) < float(truth.rest_vertices[belly].abs()[:, 1].mean())


def test_fit_across_rigs_puts_anny_on_the_smpl_bones(model):
    skeleton = nominal_smpl_skeleton()
    fit = fit_anny_to_skeleton(model, skeleton, "smpl")
    assert not fit.same_rig and fit.weights.shape == (fit.vertices.shape[0], 24)
    torch.testing.assert_close(fit.weights.sum(1), torch.ones(fit.vertices.shape[0]))
    # SMPL's toe and finger-tip joints name no body part: Anny's toes and fingers follow the ankle and wrist.
    for name in ("left_foot", "right_foot", "left_hand", "right_hand"):
        assert float(fit.weights[:, skeleton.index(name)].max()) == 0.0
    vertices = fit.vertices.double().numpy()
    # The body stands in SMPL's frame (+Y up) and T-pose: the head on top, the hands level with the shoulders.
    head = fit.weights[:, skeleton.index("head")].numpy() > 0.5
    assert vertices[head, 1].min() > skeleton.rest_joints[skeleton.index("neck"), 1] - 0.05
    # Every limb's vertices lie along its own bone (rebound onto the skeleton's joints).
    for joint, child in (("left_shoulder", "left_elbow"), ("left_elbow", "left_wrist"), ("right_hip", "right_knee"),
                         ("right_knee", "right_ankle")):
        start, end = skeleton.rest_joints[skeleton.index(joint)], skeleton.rest_joints[skeleton.index(child)]
        member = fit.weights[:, skeleton.index(joint)].numpy() > 0.9
        t = np.clip((vertices[member] - start) @ (end - start) / np.dot(end - start, end - start), 0.0, 1.0)
        distance = np.linalg.norm(vertices[member] - (start + t[:, None] * (end - start)), axis=1)
        assert member.sum() > 100 and np.median(distance) < 0.08, (joint, np.median(distance))
    hand = fit.weights[:, skeleton.index("left_wrist")].numpy() > 0.5
    wrist = skeleton.rest_joints[skeleton.index("left_wrist")]
    assert abs(vertices[hand, 1].mean() - wrist[1]) < 0.05 and vertices[hand, 0].mean() > wrist[0]


def test_anny_bones_hand_their_weight_to_the_joint_of_their_body_part(model):
    anny = AnnyBody(model).skeleton
    smpl = nominal_smpl_skeleton()
    targets = anny_bone_targets(anny, smpl, "smpl")
    names = semantic_joint_map("smpl")

    def target(label: str) -> str:
        return smpl.joint_names[targets[anny.index(label)]]

    assert target("root") == names["pelvis"]
    assert target("upperleg02.L") == names["left_thigh"]  # a twist bone: its limb
    assert target("lowerarm01.R") == names["right_forearm"]
    assert target("spine04") == names["spine_lower"]  # an in-between spine bone: the spine joint below it
    fingers = [label for label in anny.joint_names if label.startswith("finger") and label.endswith(".L")]
    toes = [label for label in anny.joint_names if label.startswith("toe") and label.endswith(".R")]
    assert fingers and all(target(label) == names["left_hand"] for label in fingers)
    assert toes and all(target(label) == names["right_foot"] for label in toes)
    # Anny's own skeleton: every bone keeps its own weight.
    assert (anny_bone_targets(anny, anny, "anny") == np.arange(anny.num_joints)).all()


def test_bare_skeleton_capture_gets_the_fitted_body_unless_told_not_to(tmp_path, cli_runner):
    from igavatar_cli.main import app

    capture = tmp_path / "capture"
    run_synth(SynthOptions(out=capture, resolution=96, train_frames=10, test_frames=0, skeleton="bare", seed=5,
                           phenotype=("weight=0.8", "height=0.3")))
    run_preprocess(PreprocessOptions(capture=capture, out=tmp_path / "fitted", max_size=96))
    manifest = read_artifact(tmp_path / "fitted", expected="dataset")
    fit = manifest["data"]["subject"]["body_fit"]
    assert manifest["config"]["body_fit"]["model"] == "anny" and fit["joint_rms_mm"] < 2.0
    assert abs(fit["phenotype"]["height"] - 0.3) < 0.02 and fit["phenotype"]["weight"] == 0.5
    # Tight clothes: the fitted naked body is the prior, as it is for an Anny capture.
    assert manifest["data"]["shape_prior"] == "template" and manifest["data"]["loose_clothing"]["share"] < 0.01
    prior = trimesh.load(tmp_path / "fitted" / "template.ply", process=False)
    assert prior.is_watertight and len(prior.vertices) == 13718

    run_preprocess(PreprocessOptions(capture=capture, out=tmp_path / "bare", max_size=96, body_fit="none"))
    bare = read_artifact(tmp_path / "bare", expected="dataset")
    assert bare["data"]["shape_prior"] == "visual_hull" and "body_fit" not in bare["config"]
    assert "body_fit" not in bare["data"]["subject"]

    result = cli_runner.invoke(app, ["preprocess", "--capture", str(capture), "--out", str(tmp_path / "x"),
                                     "--body-fit", "smpl"])
    assert result.exit_code == 2 and "--body-fit 'smpl'" in result.output and "anny, none" in result.output


def test_a_skeleton_of_unknown_kind_keeps_the_masks_only_path(tiny_skeleton_capture, tmp_path):
    run_preprocess(PreprocessOptions(capture=tiny_skeleton_capture, out=tmp_path / "dataset", max_size=16))
    manifest = read_artifact(tmp_path / "dataset", expected="dataset")
    assert "body_fit" not in manifest["config"] and manifest["data"]["subject"] == {"skeleton_kind": "unknown"}
    assert manifest["data"]["shape_prior"] == "capsules"


def test_a_fit_no_human_body_gives_is_not_used(model, tmp_path):
    """SMPL's tree with its rest joints in centimetres: Anny cannot reach them, so the body is dropped and said why."""
    from igavatar.body.skeleton import Skeleton
    from igavatar.capture.body_fit import MAX_JOINT_RMS_M, fitted_subject
    from igavatar.capture.posed_subject import PosedSubject

    nominal = nominal_smpl_skeleton()
    centimetres = Skeleton(nominal.parents, nominal.rest_joints * 100.0, nominal.joint_names)
    subject = PosedSubject(
        body_model="skeleton", skeleton=centimetres, local_rotations=torch.eye(3).expand(1, 24, 3, 3),
        root_translation=torch.zeros(1, 3), canonical_rotations=torch.eye(3).expand(24, 3, 3),
        template_vertices_rest=None, template_faces=None, template_weights=None,
        description={"skeleton_kind": "smpl"}, init_bones=(0,),
    )
    said = []
    kept = fitted_subject(subject, on_status=said.append)
    assert kept.template_vertices_rest is None and "meters" in kept.description["body_fit"]["rejected"]
    assert said and str(int(1000 * MAX_JOINT_RMS_M)) in said[0]
    # In meters the same skeleton is fitted.
    assert fitted_subject(replace(subject, skeleton=nominal)).template_vertices_rest is not None
