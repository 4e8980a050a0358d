"""SMPL from the user's model file: igavatar's SMPL function equals smplx's on synthetic SMPL files.

No real SMPL file is used or needed: tests/smpl_fixture.py writes small files in the SMPL layout
(.pkl, chumpy .pkl, .npz), and the `smplx` package opens the same files as the reference.
"""

from __future__ import annotations

import fractions
import json
import pickle
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from igavatar.artifacts.manifest import read_artifact, sha256_file
from igavatar.body.rotations import invert_rigid
from tests.rotation_oracles import rotation_angle
from igavatar.body.skeleton import SMPL_JOINT_NAMES, forward_kinematics, linear_blend_skinning
from igavatar.body.smpl_model import load_smpl_model, smpl_star_pose
from igavatar.capture.capture_v1 import read_capture_v1
from igavatar.capture.subject import canonicalize, subject_from_capture
from igavatar.errors import InputError
from igavatar_cli.main import app
from smpl_fixture import (
    FakeCh,
    fake_chumpy,
    load_smplx,
    make_smpl_arrays,
    random_smpl_poses,
    smplx_posed,
    write_chumpy_smpl_pkl,
    write_smpl_capture,
    write_smpl_npz,
    write_smpl_pkl,
)
from stages.preprocess import PreprocessOptions, run_preprocess

pytest.importorskip("smplx")


@pytest.fixture(scope="module")
def smpl_arrays() -> dict:
    return make_smpl_arrays(seed=0)


@pytest.fixture(scope="module")
def smpl_pkl(tmp_path_factory, smpl_arrays) -> Path:
    return write_smpl_pkl(tmp_path_factory.mktemp("smpl") / "SMPL_NEUTRAL.pkl", smpl_arrays)


@pytest.fixture(scope="module")
def reference(smpl_pkl, smpl_arrays):
    return load_smplx(smpl_pkl, len(smpl_arrays["v_template"]))


def _assert_same_model(a, b) -> None:
    for name in ("v_template", "shapedirs", "posedirs", "joint_regressor", "weights", "faces"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_forward_matches_smplx(smpl_pkl, reference, seed):
    model = load_smpl_model(smpl_pkl)
    poses = random_smpl_poses(5, seed=seed, scale=0.6)
    expected_vertices, expected_joints = smplx_posed(reference, poses)
    vertices, joints = model.forward(poses["betas"], poses["global_orient"], poses["body_pose"], poses["transl"])
    assert vertices.shape == expected_vertices.shape and joints.shape == (5, 24, 3)
    np.testing.assert_allclose(vertices.numpy(), expected_vertices, atol=1e-6, rtol=0)
    np.testing.assert_allclose(joints.numpy(), expected_joints, atol=1e-6, rtol=0)


def test_fk_and_lbs_without_pose_blend_shapes_match_smplx_with_posedirs_zeroed(smpl_pkl):
    model = load_smpl_model(smpl_pkl)
    poses = random_smpl_poses(4, seed=7, scale=0.6)
    expected, _ = smplx_posed(load_smplx(smpl_pkl, model.num_vertices), poses, zero_posedirs=True)
    args = (poses["betas"], poses["global_orient"], poses["body_pose"], poses["transl"])
    vertices, _ = model.forward(*args, pose_blend_shapes=False)
    np.testing.assert_allclose(vertices.numpy(), expected, atol=1e-6, rtol=0)
    with_blend, _ = model.forward(*args)
    assert (with_blend - vertices).norm(dim=-1).max() > 1e-3, "the pose blend shapes should move the vertices"


def test_rest_shape_is_smplx_at_zero_pose_and_identity_pose_is_a_translation(smpl_pkl, reference):
    model = load_smpl_model(smpl_pkl)
    poses = random_smpl_poses(1, seed=4)
    poses |= {"global_orient": np.zeros((1, 3)), "body_pose": np.zeros((1, 69)), "transl": np.array([[0.3, -0.2, 1.0]])}
    expected_vertices, expected_joints = smplx_posed(reference, poses)
    rest_vertices, rest_joints = model.rest_shape(poses["betas"])
    # smplx stores the model's arrays as float32 (utils.to_np) even in a float64 model: 1e-7, not 1e-12.
    np.testing.assert_allclose(rest_vertices.numpy() + poses["transl"], expected_vertices[0], atol=1e-7, rtol=0)
    np.testing.assert_allclose(rest_joints.numpy() + poses["transl"], expected_joints[0], atol=1e-7, rtol=0)
    skeleton = model.skeleton(np.zeros(10))
    assert skeleton.joint_names == SMPL_JOINT_NAMES and skeleton.num_joints == 24


def test_pkl_chumpy_pkl_and_npz_load_the_same_model(tmp_path, smpl_arrays, smpl_pkl):
    plain = load_smpl_model(smpl_pkl)
    for protocol in (0, 2):
        name = f"basicModel_f_lbs_10_207_0_v1.0.0_p{protocol}.pkl"
        chumpy_file = write_chumpy_smpl_pkl(tmp_path / name, smpl_arrays, protocol)
        # The stand-in chumpy is gone again: igavatar's shim is what loads the file.
        assert getattr(sys.modules.get("chumpy.ch"), "Ch", None) is not FakeCh
        loaded = load_smpl_model(chumpy_file)
        _assert_same_model(loaded, plain)
        assert loaded.gender == "female"
    dense = load_smpl_model(write_smpl_npz(tmp_path / "SMPL_MALE.npz", smpl_arrays))
    sparse = load_smpl_model(write_smpl_npz(tmp_path / "sparse.npz", smpl_arrays, dense_regressor=False))
    _assert_same_model(dense, plain)
    _assert_same_model(sparse, plain)
    assert (plain.gender, dense.gender, sparse.gender) == ("neutral", "male", None)
    assert plain.posedirs.shape == (207, 3 * plain.num_vertices) and plain.num_betas == 10


def test_star_pose_spreads_the_legs_sideways(smpl_pkl):
    model = load_smpl_model(smpl_pkl)
    star = smpl_star_pose().double()
    skeleton = model.skeleton(np.zeros(10))
    rest = torch.tensor(skeleton.rest_joints)
    canonical = forward_kinematics(star, rest, skeleton.parents)[:, :3, 3]
    left, right = skeleton.index("left_ankle"), skeleton.index("right_ankle")
    # Legs swing out towards each side (+X is the subject's left) and so rise a little.
    assert canonical[left, 0] > rest[left, 0] + 0.2 and canonical[right, 0] < rest[right, 0] - 0.2
    assert canonical[left, 1] > rest[left, 1] and canonical[right, 1] > rest[right, 1]
    angles = rotation_angle(star.double())
    hips = [skeleton.index("left_hip"), skeleton.index("right_hip")]
    torch.testing.assert_close(angles[hips], torch.full((2,), 0.5, dtype=torch.float64), atol=1e-6, rtol=0)
    assert int((angles > 0).sum()) == 2


# --- bad inputs ---------------------------------------------------------------------------------

def _broken(arrays: dict, key: str, value) -> dict:
    out = dict(arrays)
    if value is None:
        del out[key]
    else:
        out[key] = value
    return out


@pytest.mark.parametrize(
    ("key", "make_value", "message"),
    [
        ("v_template", None, "missing key(s) 'v_template'"),
        ("shapedirs", lambda a: a["shapedirs"][:, :, 0], "key 'shapedirs' has shape"),
        ("posedirs", lambda a: a["posedirs"][:, :, :100], "key 'posedirs' has shape"),
        ("J_regressor", lambda a: a["J_regressor"].toarray()[:, :-1], "key 'J_regressor' has shape"),
        ("weights", lambda a: a["weights"] * 2, "key 'weights' is not a partition of unity"),
        ("kintree_table", lambda a: a["kintree_table"][:, :22], "key 'kintree_table' has shape"),
        ("kintree_table", lambda a: np.stack((np.r_[-1, np.zeros(23)], np.arange(24))), "not SMPL's kinematic tree"),
        ("f", lambda a: a["f"] + 10_000, "key 'f' must hold vertex indices"),
        ("v_template", lambda a: "not an array", "key 'v_template' is a str, not a numeric array"),
        ("shapedirs", lambda a: {"a": 1}, "key 'shapedirs' is a dict, not a numeric array"),
    ],
)
def test_malformed_model_files_are_clear_input_errors(tmp_path, smpl_arrays, key, make_value, message):
    value = None if make_value is None else make_value(smpl_arrays)
    path = write_smpl_pkl(tmp_path / "SMPL_NEUTRAL.pkl", _broken(smpl_arrays, key, value))
    with pytest.raises(InputError) as error:
        load_smpl_model(path)
    text = str(error.value)
    assert message in text and str(path) in text and "--smpl-model" in text, text


def test_pickles_of_another_kind_are_refused(tmp_path):
    cases = {
        "list.pkl": (pickle.dumps([np.zeros(3)]), "holds a list, not the dict of arrays"),
        "other.pkl": (pickle.dumps({"weights": np.zeros((3, 2))}), "missing key(s) 'v_template'"),
        "class.pkl": (pickle.dumps({"v_template": fractions.Fraction(1, 3)}), "class fractions.Fraction"),
        "garbage.pkl": (b"this is not a pickle", "not a readable pickle"),
    }
    for name, (content, message) in cases.items():
        path = tmp_path / name
        path.write_bytes(content)
        with pytest.raises(InputError) as error:
            load_smpl_model(path)
        assert message in str(error.value) and str(path) in str(error.value), str(error.value)
        assert "--smpl-model" in str(error.value)


def test_chumpy_expressions_are_errors_only_where_smpl_uses_them(tmp_path, smpl_arrays, smpl_pkl):
    with fake_chumpy() as (Ch, add):
        unused = dict(smpl_arrays, J=add(Ch(np.zeros((24, 3))), Ch(np.ones((24, 3)))))
        used = dict(smpl_arrays, v_template=add(Ch(smpl_arrays["v_template"]), Ch(0.0)))
        unused_path = write_chumpy_smpl_pkl(tmp_path / "SMPL_NEUTRAL.pkl", unused)
        used_path = write_chumpy_smpl_pkl(tmp_path / "SMPL_MALE.pkl", used)
    _assert_same_model(load_smpl_model(unused_path), load_smpl_model(smpl_pkl))
    with pytest.raises(InputError) as error:
        load_smpl_model(used_path)
    text = str(error.value)
    assert f"{used_path}: key 'v_template': a chumpy expression, not a chumpy array" in text, text
    assert "clean_ch.py" in text


def test_unpickling_never_runs_code_from_the_file(tmp_path):
    class Payload:
        def __reduce__(self):
            return (Path.write_text, (tmp_path / "pwned", "x"))

    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps({"v_template": Payload()}))
    with pytest.raises(InputError, match="class pathlib"):
        load_smpl_model(path)
    assert not (tmp_path / "pwned").exists()


def test_missing_directory_and_wrong_suffix(tmp_path, smpl_arrays):
    write_smpl_pkl(tmp_path / "models" / "SMPL_NEUTRAL.pkl", smpl_arrays)
    (tmp_path / "model.txt").write_text("v_template")
    for path, message in (
        (tmp_path / "nope.pkl", "does not exist"),
        (tmp_path / "models", "is a directory (it holds SMPL_NEUTRAL.pkl); --smpl-model takes the model file itself"),
        (tmp_path / "model.txt", "unknown SMPL model file type '.txt'"),
    ):
        with pytest.raises(InputError, match="--smpl-model") as error:
            load_smpl_model(path)
        assert message in str(error.value) and str(path) in str(error.value)


# --- a capture with SMPL poses through preprocess -----------------------------------------------

@pytest.fixture(scope="module")
def smpl_run(tmp_path_factory, smpl_pkl):
    """A 3-frame, 48 px capture posed by the synthetic SMPL file, preprocessed through the CLI with
    the model given by IGAVATAR_SMPL_MODEL."""
    from typer.testing import CliRunner

    run = tmp_path_factory.mktemp("smpl_run")
    poses = write_smpl_capture(run / "capture", smpl_pkl, n_frames=3, size=48)
    result = CliRunner().invoke(
        app, ["preprocess", "--capture", str(run / "capture"), "--out", str(run / "dataset"),
              "--max-size", "48", "--grid-resolution", "8,8,8", "--quiet"],
        env={"IGAVATAR_SMPL_MODEL": str(smpl_pkl)},
    )
    assert result.exit_code == 0, result.output
    return run, poses


def test_smpl_capture_dataset_reproduces_smplx(smpl_run, smpl_pkl, reference):
    """Dataset transforms (canonical -> posed) composed with rest -> canonical skin the shaped rest
    mesh exactly onto smplx's posed vertices (pose blend shapes excluded), and its joints."""
    import trimesh

    run, poses = smpl_run
    model = load_smpl_model(smpl_pkl)
    expected, expected_joints = smplx_posed(load_smplx(smpl_pkl, model.num_vertices), poses, zero_posedirs=True)
    frames = np.load(run / "dataset" / "frames.npz")
    subject = np.load(run / "dataset" / "subject.npz")
    rest_joints = torch.tensor(subject["rest_joints"], dtype=torch.float64)
    np.testing.assert_allclose(subject["rest_joints"], model.rest_shape(poses["betas"])[1].numpy(), atol=1e-6)
    assert list(subject["joint_names"]) == list(SMPL_JOINT_NAMES)

    canonical_rotations = torch.tensor(subject["canonical_rotations"], dtype=torch.float64)
    global_canonical = forward_kinematics(canonical_rotations, rest_joints, subject["parents"])
    identity = torch.eye(3, dtype=torch.float64).expand(24, 3, 3)
    global_rest = forward_kinematics(identity, rest_joints, subject["parents"])
    rest_to_canonical = global_canonical @ invert_rigid(global_rest)
    transforms = torch.tensor(frames["bone_transforms"], dtype=torch.float64) @ rest_to_canonical
    shaped = model.shaped_vertices(poses["betas"])
    posed = linear_blend_skinning(shaped, model.weights, transforms)
    np.testing.assert_allclose(posed.numpy(), expected, atol=2e-5, rtol=0)
    np.testing.assert_allclose(frames["posed_joints"], expected_joints, atol=2e-5, rtol=0)

    template = trimesh.load(run / "dataset" / "template.ply", process=False)
    canonical_template = linear_blend_skinning(shaped, model.weights, rest_to_canonical)
    np.testing.assert_allclose(template.vertices, canonical_template.numpy(), atol=1e-5)
    assert np.array_equal(template.faces, model.faces.numpy())


def test_smpl_capture_manifest_records_the_model_file(smpl_run, smpl_pkl):
    run, poses = smpl_run
    manifest = read_artifact(run / "dataset", expected="dataset")
    assert {"path": str(smpl_pkl), "sha256": sha256_file(smpl_pkl)} in manifest["inputs"]
    subject = manifest["data"]["subject"]
    assert subject["smpl_model"] == "SMPL_NEUTRAL.pkl" and subject["gender"] == "neutral"
    np.testing.assert_allclose(subject["betas"], poses["betas"])
    assert manifest["data"]["body_model"] == "smpl" and manifest["data"]["pose_dim"] == 69


def test_another_smpl_file_makes_the_dataset_stale(smpl_run, smpl_arrays, tmp_path):
    run, _ = smpl_run
    options = PreprocessOptions(
        capture=run / "capture", out=run / "dataset", max_size=48, grid_resolution=(8, 8, 8),
        smpl_model=write_smpl_pkl(tmp_path / "SMPL_NEUTRAL.pkl", smpl_arrays),
    )
    assert "skipped" in run_preprocess(options), "the same file content at another path is the same input"
    other = write_smpl_npz(tmp_path / "SMPL_NEUTRAL.npz", smpl_arrays)
    out = tmp_path / "dataset"
    assert "skipped" not in run_preprocess(PreprocessOptions(**{**options.__dict__, "smpl_model": other, "out": out}))
    inputs = read_artifact(out, expected="dataset")["inputs"]
    assert inputs[-1]["path"] == str(other)


def test_smpl_capture_without_the_model_file_names_the_flag(smpl_run, cli_runner, tmp_path, monkeypatch):
    run, _ = smpl_run
    monkeypatch.delenv("IGAVATAR_SMPL_MODEL", raising=False)
    result = cli_runner.invoke(app, ["preprocess", "--capture", str(run / "capture"), "--out", str(tmp_path / "d")])
    assert result.exit_code == 2 and "Traceback" not in result.output
    text = " ".join(result.output.split())
    assert "poses.npz: holds SMPL body parameters" in text and "--smpl-model PATH" in text, text
    assert "IGAVATAR_SMPL_MODEL" in text and "never ships or downloads" in text
    assert not (tmp_path / "d").exists()

    capture = read_capture_v1(run / "capture")
    with pytest.raises(InputError, match="--smpl-model"):
        subject_from_capture(capture, smpl_model=None)
    with pytest.raises(InputError, match="does not exist"):
        subject_from_capture(capture, smpl_model=tmp_path / "SMPL_NEUTRAL.pkl")


def test_smpl_subject_is_the_posed_smpl_body(smpl_run, smpl_pkl):
    run, poses = smpl_run
    subject = subject_from_capture(read_capture_v1(run / "capture"), smpl_model=smpl_pkl)
    assert subject.body_model == "smpl" and subject.local_rotations.shape == (3, 24, 3, 3)
    torch.testing.assert_close(subject.root_translation, torch.tensor(poses["transl"], dtype=torch.float32))
    names = [subject.skeleton.joint_names[i] for i in subject.init_bones]
    assert {"pelvis", "spine2", "head", "left_hip", "right_knee", "left_shoulder", "right_elbow"} <= set(names)
    canonical = canonicalize(subject)
    assert canonical.pose_condition.shape == (3, 69)
    body_pose = torch.tensor(poses["body_pose"], dtype=torch.float32)
    torch.testing.assert_close(canonical.pose_condition, body_pose, atol=1e-5, rtol=0)
    assert json.loads(json.dumps(subject.description))["smpl_model"] == "SMPL_NEUTRAL.pkl"
