"""The shape prior voted again on the fitted poses: on the capture's own poses train's vote is
preprocess's (the same choice, the same hull), poses that are off refuse the hull as preprocess
does, and a dress whose prior preprocess kept as the template trains on the masks' hull after
`--refine-poses` fitted its poses, written into the model so that export meshes it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
import trimesh

from igavatar.artifacts.manifest import read_artifact
from igavatar.avatar.dataset import BODY_WEIGHTS_FILE, PRIOR_FILE, read_dataset, training_data
from igavatar.avatar.subject import SubjectArrays
from igavatar.capture import loose_clothing
from igavatar.training.prior_vote import vote_prior
from stages.preprocess import PreprocessOptions, run_preprocess
from stages.synth import SynthOptions, run_synth
from stages.train_prior import _body, _dataset_blur


@pytest.fixture(scope="module")
def dress_capture(tmp_path_factory):
    """A dress turning (96 px, 10 training frames): preprocess gives it the masks' hull."""
    run = tmp_path_factory.mktemp("dress")
    run_synth(SynthOptions(out=run / "capture", resolution=96, train_frames=10, test_frames=2, seed=7, garment="dress",
                           phenotype=("gender=0.9", "weight=0.3")))
    run_preprocess(PreprocessOptions(capture=run / "capture", out=run / "dataset", max_size=96))
    return run


@pytest.fixture(scope="module")
def kept_dataset(dress_capture, tmp_path_factory):
    """The dress's dataset with preprocess made to keep the template (its spill rule at 1000x): the
    dataset records the vote, as it does for a dress on noisy poses."""
    out = tmp_path_factory.mktemp("kept") / "dataset"
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(loose_clothing, "LOOSE_OVER_SPILL", 1000.0)
        run_preprocess(PreprocessOptions(capture=dress_capture / "capture", out=out, max_size=96))
    return out


def _vote(dataset, data):
    body = _body(dataset, data.bone_transforms)
    assert body is not None
    return vote_prior(body, data, tuple(dataset.subject.skinning_grid.shape[1:]), _dataset_blur(dataset))


def test_on_the_captures_poses_the_vote_is_preprocesss(dress_capture):
    dataset = read_dataset(dress_capture / "dataset")
    assert dataset.shape_prior == "visual_hull" and (dataset.path / BODY_WEIGHTS_FILE).is_file()
    vote = _vote(dataset, training_data(dataset))
    recorded = dataset.data["loose_clothing"]
    assert vote.report["prior"] == "visual_hull" and vote.report["views"] == 10
    assert vote.report["loose"] == pytest.approx(recorded["share"], abs=1e-4)
    assert vote.report["spill"] == pytest.approx(recorded["spill"], abs=1e-4)
    hull = trimesh.load(dataset.path / PRIOR_FILE, process=False)
    np.testing.assert_allclose(vote.prior.vertices.numpy(), np.asarray(hull.vertices), atol=1e-5)
    np.testing.assert_allclose(vote.prior.skinning_grid.numpy(), dataset.subject.skinning_grid, atol=1e-5)
    np.testing.assert_allclose(vote.prior.canonical_box().numpy(), dataset.subject.canonical_box, atol=1e-6)
    frames = dataset.frames()
    np.testing.assert_allclose(vote.prior.posed_boxes.numpy(), frames.posed_boxes, atol=1e-5)


def test_poses_that_are_off_refuse_the_hull(dress_capture):
    """Every training frame's root moved 15 cm sideways: the template spills past the masks as far as
    they reach past it, and the hull, which would carve what each frame puts elsewhere, is refused."""
    dataset = read_dataset(dress_capture / "dataset")
    data = training_data(dataset)
    moved = data.bone_transforms.clone()
    for i in data.train_indices.tolist():
        sideways = torch.linalg.inv(data.w2c[i])[:3, 0]
        moved[i, :, :3, 3] += 0.15 * sideways
    vote = _vote(dataset, dataclasses.replace(data, bone_transforms=moved))
    assert vote.prior is None and vote.report["prior"] == "template"
    assert vote.report["spill"] > 0.1 and vote.report["loose"] < loose_clothing.LOOSE_OVER_SPILL * vote.report["spill"]


def _train(dataset, out, *extra):
    return ["train", "--dataset", str(dataset), "--out", str(out), "--preset", "tiny", "--device", "cpu", "-q",
            "--steps", "6", "--refine-poses", "--pose-silhouette-steps", "20", *extra]


def test_a_dress_kept_on_the_template_trains_on_the_hull_after_the_fit(dress_capture, kept_dataset, tmp_path,
                                                                      monkeypatch, cli_runner):
    """preprocess made to keep the template (its spill rule at 1000x): the dataset records the vote,
    and `train --refine-poses` asks it again with the rule as it is, and trains on the hull; a run
    resumed after Ctrl-C votes the same and ends bit for bit as the straight one."""
    import os
    import signal

    import igavatar.training.trainer as trainer_module
    from igavatar_cli.main import app

    dataset = read_dataset(kept_dataset)
    assert dataset.shape_prior == "template" and "loose_clothing" in dataset.data
    straight = tmp_path / "model"
    result = cli_runner.invoke(app, _train(dataset.path, straight))
    assert result.exit_code == 0, result.output
    manifest = read_artifact(straight, expected="model")
    vote = manifest["data"]["pose_refinement"]["prior_vote"]
    assert vote["prior"] == "visual_hull" and vote["before"] == dataset.data["loose_clothing"]
    hull = trimesh.load(straight / "prior.ply", process=False)
    template = trimesh.load(dataset.path / PRIOR_FILE, process=False)
    assert hull.is_watertight and hull.volume > 1.2 * template.volume  # the skirt's space is in it
    subject = SubjectArrays.read(straight / "subject.npz")
    np.testing.assert_allclose(subject.canonical_box, manifest["data"]["canonical_box"], atol=1e-6)
    assert not np.allclose(subject.canonical_box, dataset.subject.canonical_box)
    assert subject.same_skeleton(dataset.subject)

    real_step = trainer_module.Trainer.train_step

    def interrupted_at_3(self):
        if self.step == 3:
            os.kill(os.getpid(), signal.SIGINT)
        return real_step(self)

    resumed = tmp_path / "resumed"
    with monkeypatch.context() as patch:
        patch.setattr(trainer_module.Trainer, "train_step", interrupted_at_3)
        assert cli_runner.invoke(app, _train(dataset.path, resumed)).exit_code == 130
    result = cli_runner.invoke(app, _train(dataset.path, resumed, "--resume"))
    assert result.exit_code == 0, result.output
    for name in ("weights.npz", "subject.npz"):
        with np.load(resumed / name) as got, np.load(straight / name) as want:
            for key in want.files:
                np.testing.assert_array_equal(got[key], want[key], err_msg=f"{name}: {key}")

    # Off: the dataset's prior, and the model records no vote.
    off = tmp_path / "off"
    assert cli_runner.invoke(app, _train(dataset.path, off, "--no-pose-prior-vote")).exit_code == 0
    assert read_artifact(off, expected="model")["data"]["pose_refinement"]["prior_vote"] is None
    assert not (off / "prior.ply").exists()
    np.testing.assert_array_equal(SubjectArrays.read(off / "subject.npz").canonical_box, dataset.subject.canonical_box)

    # eval's canonical picture shows the prior the model was trained from, not the dataset's.
    from igavatar.avatar.canonical_report import canonical_section

    pred = (np.asarray(hull.vertices), np.asarray(hull.faces))
    _, dataset_picture = canonical_section(dataset, dress_capture / "capture", pred, n_iou=2000)
    _, model_picture = canonical_section(dataset, dress_capture / "capture", pred, n_iou=2000,
                                         trained_prior=straight / "prior.ply")
    assert model_picture.shape == dataset_picture.shape and not np.array_equal(model_picture, dataset_picture)


def test_a_dataset_made_before_the_weights_keeps_its_prior_and_says_why(kept_dataset, tmp_path, monkeypatch):
    from igavatar.avatar.dataset import DatasetArtifact
    from igavatar.training.config import preset
    from igavatar.training.pose_refine import PoseRefiner
    from stages.progress import NULL_PROGRESS
    from stages.train_prior import revote_prior

    dataset = read_dataset(kept_dataset)
    data = training_data(dataset)
    subject = dataset.subject
    refiner = PoseRefiner(data.bone_transforms, subject.parents, subject.rest_joints, subject.canonical_rotations,
                          data.train_indices, np.union1d([0], subject.init_bones))
    config = dataclasses.replace(preset("tiny"), refine_poses=True)
    fitted = object()  # the fit's record: only whether it ran matters here
    monkeypatch.setattr(DatasetArtifact, "body_weights", lambda self, n_vertices: None)
    vote = revote_prior(config, dataset, data, refiner, fitted, tmp_path, NULL_PROGRESS)
    assert vote.subject is None and vote.mesh_path is None and "preprocess --force" in vote.report["skipped"]
    assert vote.with_boxes(data) is data
    # No fit, or the vote turned off: nothing to vote on.
    assert revote_prior(config, dataset, data, refiner, None, tmp_path, NULL_PROGRESS) is None
    off = dataclasses.replace(config, pose_prior_vote=False)
    assert revote_prior(off, dataset, data, refiner, fitted, tmp_path, NULL_PROGRESS) is None
