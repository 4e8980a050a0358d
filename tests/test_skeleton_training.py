"""A skeleton-only capture (the synthetic subject with its body model dropped, no body fitted to it)
goes through preprocess and tiny training: capsule prior, bone weights, a learning avatar with a body inside."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from scipy.spatial import cKDTree

from igavatar.artifacts.manifest import read_artifact
from igavatar.body.capsules import capsule_radii, skeleton_capsules
from igavatar.body.skeleton import Skeleton
from igavatar.capture.capture_v1 import read_capture_v1
from igavatar.capture.subject import subject_from_capture
from igavatar.synth.skeleton_capture import bare_skeleton_poses
from igavatar.training.shape_init import template_sdf_samples
from stages.preprocess import PreprocessOptions, run_preprocess
from stages.train import TrainOptions, run_train


def skeleton_capture_from(capture: Path, out: Path) -> Path:
    """A hand-made copy of a capture whose poses.npz is the bare skeleton of its body model."""
    shutil.copytree(capture, out)
    (out / "manifest.json").unlink(missing_ok=True)  # edited by hand: no longer the synth artifact
    poses = _bare(subject_from_capture(read_capture_v1(capture)))
    (out / "poses.npz").unlink()
    np.savez(out / "poses.npz", **poses)
    meta = json.loads((out / "capture.json").read_text())
    meta["body_model"] = "skeleton"
    (out / "capture.json").write_text(json.dumps(meta))
    return out


def skeleton_of(subject: dict) -> Skeleton:
    """The Skeleton of a dataset's subject.npz arrays."""
    return Skeleton(subject["parents"], subject["rest_joints"], tuple(str(n) for n in subject["joint_names"]))


@pytest.fixture(scope="module")
def skeleton_run(small_run, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("skeleton_run")
    skeleton_capture_from(small_run / "capture", run / "capture")
    # The masks-only path (no Anny fitted to the joints), whose prior here is capsules: 4 training frames vote too few.
    run_preprocess(PreprocessOptions(capture=run / "capture", out=run / "dataset", max_size=64, body_fit="none"))
    run_train(TrainOptions(dataset=run / "dataset", out=run / "model", preset="tiny", steps=16, device="cpu"))
    return run


def test_dataset_has_a_capsule_prior_around_the_skeleton(skeleton_run, small_run):
    data = read_artifact(skeleton_run / "dataset", expected="dataset")["data"]
    assert data["body_model"] == "skeleton" and data["shape_prior"] == "capsules"
    assert data["subject"] == {"skeleton_kind": "anny"}  # Anny's bone labels: star pose and major bones
    subject = np.load(skeleton_run / "dataset" / "subject.npz")
    anny = np.load(small_run / "dataset" / "subject.npz")
    # Same skeleton, same canonical (star) pose, same root-finding bones as the Anny dataset.
    np.testing.assert_allclose(subject["canonical_joints"], anny["canonical_joints"], atol=1e-5)
    np.testing.assert_array_equal(subject["init_bones"], anny["init_bones"])
    grid = subject["skinning_grid"]
    assert grid.shape == anny["skinning_grid"].shape and grid.min() >= 0
    np.testing.assert_allclose(grid.sum(axis=0), 1.0, atol=1e-5)
    prior = trimesh.load(skeleton_run / "dataset" / "template.ply", process=False)
    template = trimesh.load(small_run / "dataset" / "template.ply", process=False)
    assert prior.is_watertight and prior.volume > 0
    # Capsules are a coarse body: most of Anny's template lies within 5 cm of them.
    distance, _ = cKDTree(prior.sample(100_000, seed=0)).query(np.asarray(template.vertices)[::20])
    assert np.median(distance) < 0.05, np.median(distance)
    # Shape initialization's targets from this mesh are the capsules' own signs (inside = negative).
    targets = template_sdf_samples(np.asarray(prior.vertices), np.asarray(prior.faces), subject["canonical_box"], n_points=4000)
    capsules = skeleton_capsules(subject["canonical_joints"], skeleton_of(subject), capsule_radii(skeleton_of(subject)))
    exact = capsules.sdf(targets.points)
    clear = exact.abs() > 0.01  # away from the marching-cubes surface
    assert bool(((targets.sdf < 0) == (exact < 0))[clear].all())
    frames = np.load(skeleton_run / "dataset" / "frames.npz")
    anny_frames = np.load(small_run / "dataset" / "frames.npz")
    np.testing.assert_allclose(frames["bone_transforms"], anny_frames["bone_transforms"], atol=1e-4)


def test_tiny_training_learns_and_the_sdf_has_a_body_inside_the_capsules(skeleton_run):
    from igavatar.avatar.model import load_model

    manifest = read_artifact(skeleton_run / "model", expected="model")
    assert manifest["data"]["body_model"] == "skeleton" and manifest["data"]["steps"] == 16
    with open(skeleton_run / "model" / "training_log.csv") as file:
        losses = [float(row["loss"]) for row in csv.DictReader(file)]
    assert len(losses) == 16 and all(np.isfinite(losses))
    assert np.mean(losses[-4:]) < np.mean(losses[:4]), losses

    model = load_model(skeleton_run / "model")
    subject = model.subject
    with torch.no_grad():
        sdf_inside, _ = model.avatar.sdf_field(torch.tensor(subject.canonical_joints[subject.init_bones], dtype=torch.float32))
        box = torch.tensor(subject.canonical_box, dtype=torch.float32)
        corners = torch.stack(torch.meshgrid(*[box[:, a] for a in range(3)], indexing="ij"), dim=-1).reshape(-1, 3)
        sdf_corners, _ = model.avatar.sdf_field(corners)
    # Tiny trains 5 shape-init and 16 photometric steps: the body is rough, but the root is inside
    # and the box's corners outside, so there is a surface between them.
    assert float(sdf_inside[0]) < 0 and int(subject.init_bones[0]) == 0, sdf_inside
    assert bool((sdf_corners > 0).all()), sdf_corners


def test_a_bare_anny_skeleton_keeps_annys_world_axes(skeleton_run):
    """Anny's joints come in Anny's +Z-up world: the GLB and the orbit cameras must turn it as they
    turn an Anny avatar, not as SMPL's Y-up (assumed only for skeletons of unknown kind)."""
    from igavatar.avatar.model import load_model
    from igavatar.body.motions import body_to_world
    from igavatar.mesh.gltf import gltf_axes

    model = load_model(skeleton_run / "model")
    assert model.body_model == "skeleton" and model.axes_kind == "anny"
    np.testing.assert_array_equal(model.body_axes, body_to_world("anny"))
    head_up = gltf_axes(model.axes_kind) @ body_to_world("anny")[:, 1]  # the body's up, in glTF
    np.testing.assert_allclose(head_up, [0.0, 1.0, 0.0])


def _bare(subject):
    """The subject's skeleton and motion as capture v1 'skeleton' arrays (its body model dropped)."""
    return bare_skeleton_poses(subject.skeleton, subject.local_rotations, subject.root_translation)
