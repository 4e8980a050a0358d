"""The HumanNeRF / ZJU-MoCap importer on a tiny subject written here: detection, world = R(Rh) X + Th
for every joint, undistortion, splits, preprocess end to end, and clear errors for bad pickles."""

from __future__ import annotations

import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from igavatar.artifacts.manifest import read_artifact
from igavatar.body.skeleton import SMPL_PARENTS
from igavatar.capture.humannerf import humannerf_splits, read_humannerf
from igavatar.capture.images import undistort
from igavatar.capture.importers import detect_layout
from igavatar.errors import InputError
from igavatar_cli.main import app
from stages.preprocess import PreprocessOptions, run_preprocess
from tests.smpl_like_skeleton import SMPL_LIKE_REST_JOINTS

SIZE = 48
DIST = np.array([-0.08, 0.02, 0.001, -0.001, 0.0])


def smpl_joints(poses: np.ndarray, tpose_joints: np.ndarray) -> np.ndarray:
    """SMPL's posed joints in model space (a loop over the tree, as SMPL's lbs does):
    G_0 = [R_0 | J_0], G_j = G_parent [R_j | J_j - J_parent], joint j at G_j's translation."""
    rotations = Rotation.from_rotvec(poses.reshape(24, 3)).as_matrix()
    world = [None] * 24
    for j, parent in enumerate(SMPL_PARENTS):
        local = np.eye(4)
        local[:3, :3] = rotations[j]
        local[:3, 3] = tpose_joints[j] - (tpose_joints[parent] if parent >= 0 else 0.0)
        world[j] = local if parent < 0 else world[parent] @ local
    return np.stack([g[:3, 3] for g in world])


def _dump(path: Path, value) -> None:
    with path.open("wb") as file:
        pickle.dump(value, file)


def write_humannerf_subject(root: Path, n_frames: int = 6) -> dict:
    """A tiny HumanNeRF subject; returns the world joints (N, 24, 3) per frame name."""
    rng = np.random.default_rng(0)
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    K = np.array([[70.0, 0, SIZE / 2 - 0.5], [0, 70.0, SIZE / 2 - 0.5], [0, 0, 1]])
    w2c = np.eye(4)
    w2c[:3, :3] = Rotation.from_rotvec([0.1, 0.0, 0.0]).as_matrix()
    w2c[:3, 3] = [0.0, 0.1, 3.5]
    cameras, mesh_infos, world_joints = {}, {}, {}
    for i in range(n_frames):
        name = f"frame_{i:06d}"
        poses = rng.normal(0.0, 0.2, 72)
        poses[:3] = 0.0  # ZJU-MoCap: the global rotation lives in Rh
        Rh = np.array([0.0, rng.uniform(-np.pi, np.pi), 0.0]) + rng.normal(0.0, 0.1, 3)
        Th = np.array([0.1, -0.1, 0.2]) + rng.normal(0.0, 0.05, 3)
        joints = smpl_joints(poses, SMPL_LIKE_REST_JOINTS)
        mesh_infos[name] = {"Rh": Rh, "Th": Th, "poses": poses, "joints": joints, "tpose_joints": SMPL_LIKE_REST_JOINTS.copy()}
        cameras[name] = {"intrinsics": K, "extrinsics": w2c, "distortions": DIST.reshape(5, 1)}
        world_joints[name] = joints @ Rotation.from_rotvec(Rh).as_matrix().T + Th
        # The subject: joints projected and dilated; the image is noise inside, gray outside.
        uv, _ = cv2.projectPoints(world_joints[name], cv2.Rodrigues(w2c[:3, :3])[0], w2c[:3, 3], K, DIST)
        mask = np.zeros((SIZE, SIZE), np.uint8)
        for u, v in uv.reshape(-1, 2):
            cv2.circle(mask, (int(round(u)), int(round(v))), 2, 255, -1)
        image = np.where(mask[..., None] > 0, rng.integers(0, 255, (SIZE, SIZE, 3)), 128).astype(np.uint8)
        cv2.imwrite(str(root / "images" / f"{name}.png"), image)
        cv2.imwrite(str(root / "masks" / f"{name}.png"), np.repeat(mask[..., None], 3, axis=2))  # 3-channel 0/255
    _dump(root / "cameras.pkl", cameras)
    _dump(root / "mesh_infos.pkl", mesh_infos)
    _dump(root / "canonical_joints.pkl", {"joints": SMPL_LIKE_REST_JOINTS.copy()})
    return world_joints


@pytest.fixture
def subject(tmp_path: Path) -> tuple[Path, dict]:
    root = tmp_path / "377"
    return root, write_humannerf_subject(root)


def _edit(path: Path, change) -> None:
    with path.open("rb") as file:
        data = pickle.load(file)  # the test's own file
    _dump(path, change(data))


def test_reads_a_skeleton_capture_whose_joints_land_on_the_world_joints(subject):
    from igavatar.capture.subject import canonicalize, subject_from_capture

    root, world_joints = subject
    assert detect_layout(root) == "humannerf"
    capture = read_humannerf(root)
    assert capture.body_model == "skeleton" and capture.input_format == "humannerf"
    assert capture.frames == sorted(world_joints) and capture.splits == humannerf_splits(capture.frames)
    assert capture.splits["test"] == capture.frames[-1:] and len(capture.splits["train"]) == 5
    assert capture.dist.shape == (6, 5) and np.allclose(capture.frame_dist(2), DIST)
    assert (capture.height, capture.width) == (SIZE, SIZE) and capture.has_masks
    np.testing.assert_allclose(capture.poses["rest_joints"], SMPL_LIKE_REST_JOINTS)
    canonical = canonicalize(subject_from_capture(capture))
    expected = np.stack([world_joints[f] for f in capture.frames])
    np.testing.assert_allclose(canonical.posed_joints.numpy(), expected, atol=1e-5)


def test_nonzero_root_pose_and_per_frame_shapes_still_match(subject):
    """A root rotation in poses composes with Rh; per-frame tpose joints move the root."""
    from igavatar.capture.subject import canonicalize, subject_from_capture

    root, _ = subject
    expected = {}

    def change(mesh):
        for k, (name, info) in enumerate(sorted(mesh.items())):
            info["poses"][:3] = [0.3, -0.2, 0.1]
            info["tpose_joints"] = SMPL_LIKE_REST_JOINTS + [0.0, 0.002 * k, 0.0]  # shape drift: 2 mm per frame
            info["joints"] = smpl_joints(info["poses"], info["tpose_joints"])
            expected[name] = info["joints"] @ Rotation.from_rotvec(info["Rh"]).as_matrix().T + info["Th"]
        return mesh

    _edit(root / "mesh_infos.pkl", change)
    (root / "canonical_joints.pkl").unlink()  # then the rest joints are the frames' mean
    capture = read_humannerf(root)
    posed = canonicalize(subject_from_capture(capture)).posed_joints.numpy()
    error = np.linalg.norm(posed - np.stack([expected[f] for f in capture.frames]), axis=-1)
    assert error[:, 0].max() < 1e-5  # the root exactly; the rest within the shape drift
    assert error.max() < 0.006


def test_preprocess_undistorts_and_keeps_the_joints(subject, tmp_path):
    root, world_joints = subject
    summary = run_preprocess(PreprocessOptions(capture=root, out=tmp_path / "dataset", grid_resolution=(16, 8, 16)))
    assert summary["frames"] == 6 and summary["train"] == 5 and summary["test"] == 1
    manifest = read_artifact(tmp_path / "dataset", expected="dataset")
    data = manifest["data"]
    # SMPL's skeleton without the SMPL file: Anny is fitted to it and is the template (igavatar.capture.body_fit).
    assert data["source_format"] == "humannerf" and data["shape_prior"] == "template"
    assert data["subject"]["skeleton_kind"] == "smpl" and data["subject"]["body_fit"]["model"] == "anny"
    assert data["image_size"] == [SIZE, SIZE]
    hashed = {Path(record["path"]).name for record in manifest["inputs"]}
    assert {"cameras.pkl", "mesh_infos.pkl", "canonical_joints.pkl", "frame_000000.png"} <= hashed
    frames = np.load(tmp_path / "dataset" / "frames.npz")
    names = [str(n) for n in frames["frame_names"]]
    np.testing.assert_allclose(frames["posed_joints"], np.stack([world_joints[n] for n in names]), atol=1e-5)
    raw = cv2.imread(str(root / "masks" / "frame_000003.png"))[..., 0] > 127
    image = cv2.cvtColor(cv2.imread(str(root / "images" / "frame_000003.png")), cv2.COLOR_BGR2RGB)
    want_rgb, want_mask = undistort(image, raw, frames["K"][3].astype(np.float64), DIST)
    got_mask = cv2.imread(str(tmp_path / "dataset" / "masks" / "frame_000003.png"), cv2.IMREAD_GRAYSCALE) > 127
    got_rgb = cv2.cvtColor(cv2.imread(str(tmp_path / "dataset" / "images" / "frame_000003.png")), cv2.COLOR_BGR2RGB)
    assert np.array_equal(got_mask, want_mask) and np.array_equal(got_rgb, want_rgb)
    assert np.abs(got_rgb.astype(int) - image).max() > 20, "the image was not undistorted"
    # Undistorted, the joints project into the subject's mask.
    from igavatar.geometry.projection import project_points

    uv, _ = project_points(frames["K"][3].astype(np.float64), frames["w2c"][3].astype(np.float64), world_joints["frame_000003"])
    inside = got_mask[np.clip(np.round(uv[:, 1]).astype(int), 0, SIZE - 1), np.clip(np.round(uv[:, 0]).astype(int), 0, SIZE - 1)]
    assert inside.mean() > 0.9


def test_splits_of_short_sequences():
    assert humannerf_splits(["a", "b", "c"]) == {"train": ["a", "b", "c"], "test": []}
    ten = [f"f{i}" for i in range(10)]
    assert humannerf_splits(ten) == {"train": ten[:8], "test": ten[8:]}


class _Evil:
    def __reduce__(self):
        return (print, ("this must never run",))


@pytest.mark.parametrize(
    ("file", "change", "message"),
    [
        ("mesh_infos.pkl", lambda d: [d], r"mesh_infos.pkl: holds a list, expected a non-empty dict"),
        ("mesh_infos.pkl", lambda d: {k: {**v, "poses": v["poses"][:69]} for k, v in d.items()},
         r"mesh_infos.pkl \[frame 'frame_000000'\]: key 'poses' has shape \(69,\), expected \(72,\)"),
        ("mesh_infos.pkl", lambda d: {k: {kk: vv for kk, vv in v.items() if kk != "Th"} for k, v in d.items()},
         r"mesh_infos.pkl \[frame 'frame_000000'\]: key 'Th' missing"),
        ("mesh_infos.pkl", lambda d: {**d, "frame 7": d["frame_000000"]}, r"frame key 'frame 7' is not a frame name"),
        ("mesh_infos.pkl", lambda d: {k: {**v, "joints": v["joints"] + [0, 0, 0.2]} for k, v in d.items()},
         r"mesh_infos.pkl: frame '.*': SMPL's kinematic tree .* m from R\(Rh\) joints \+ Th"),
        ("cameras.pkl", lambda d: {k: {**v, "intrinsics": np.eye(4)} for k, v in d.items()},
         r"cameras.pkl \[frame 'frame_000000'\]: key 'intrinsics' has shape \(4, 4\), expected \(3, 3\)"),
        ("cameras.pkl", lambda d: {k: v for k, v in d.items() if k != "frame_000004"},
         r"cameras.pkl: no camera for 1 frame\(s\) of mesh_infos.pkl, e.g. 'frame_000004'"),
        ("cameras.pkl", lambda d: {k: "camera" for k in d}, r"cameras.pkl: frame 'frame_000000' holds a str, expected a dict"),
        ("canonical_joints.pkl", lambda d: {"joints": d["joints"][:23]}, r"canonical_joints.pkl: key 'joints' has shape \(23, 3\)"),
        ("canonical_joints.pkl", lambda d: _Evil(), r"canonical_joints.pkl: the pickle refers to builtins.print"),
    ],
)
def test_bad_pickles_name_the_file_frame_key_and_shape(subject, file, change, message, capsys):
    root, _ = subject
    _edit(root / file, change)
    with pytest.raises(InputError, match=message):
        read_humannerf(root)
    assert "must never run" not in capsys.readouterr().out


def test_missing_masks_and_a_cli_error(subject, cli_runner, tmp_path):
    root, _ = subject
    (root / "masks" / "frame_000002.png").unlink()
    with pytest.raises(InputError, match=r"masks: no file for frame 'frame_000002'"):
        read_humannerf(root)
    (root / "mesh_infos.pkl").write_bytes(b"not a pickle")
    result = cli_runner.invoke(app, ["preprocess", "--capture", str(root), "--format", "humannerf", "--out", str(tmp_path / "d")])
    assert result.exit_code == 2 and "mesh_infos.pkl: not a readable pickle" in result.output
    assert not (tmp_path / "d").exists()
