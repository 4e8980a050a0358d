"""The PeopleSnapshot and X-Humans importers on tiny hand-made copies of each layout.

Each test writes a few 32 px frames in the dataset's own layout, then checks detection, what is read
(frames, cameras, poses, splits, masks, scans) and the errors for malformed inputs.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest

from igavatar.capture.capture_v1 import load_mask
from igavatar.capture.importers import detect_layout, layout_names, read_layout
from igavatar.capture.peoplesnapshot import ANIM_NERF_SPLITS, DEFAULT_STEP
from igavatar.capture.xhumans import read_xhumans_scan
from igavatar.errors import InputError
from tests.conftest import write_tiny_capture

SIZE = 32


# ------------------------------------------------------------------------------------------------
# PeopleSnapshot fixtures


def subject_mask(index: int) -> np.ndarray:
    """A (SIZE, SIZE) uint8 {0,1} mask that differs per frame."""
    mask = np.zeros((SIZE, SIZE), np.uint8)
    mask[4 + index % 5 : 28, 10:22] = 1
    return mask


def write_peoplesnapshot(
    root: Path, n_frames: int = 12, masks: str = "npy", poses_file: str = "poses.npz", seed: int = 0
) -> dict[str, np.ndarray]:
    """A PeopleSnapshot subject of `n_frames` 32 px frames; returns the poses.npz arrays."""
    rng = np.random.default_rng(seed)
    (root / "images").mkdir(parents=True)
    if masks:
        (root / "masks").mkdir()
    for i in range(n_frames):
        cv2.imwrite(str(root / "images" / f"image_{i:04d}.png"), np.full((SIZE, SIZE, 3), 10 * i, np.uint8))
        if masks == "npy":
            np.save(root / "masks" / f"mask_{i:04d}.npy", subject_mask(i))
        elif masks == "png":
            cv2.imwrite(str(root / "masks" / f"mask_{i:04d}.png"), subject_mask(i) * 255)
    K = np.array([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])
    np.savez(root / "cameras.npz", intrinsic=K, extrinsic=np.eye(4), height=SIZE, width=SIZE)
    poses = {
        "betas": rng.normal(size=(1, 10)), "thetas": rng.normal(scale=0.2, size=(n_frames, 72)),
        "transl": rng.normal(size=(n_frames, 3)) + [0, 0, 3],
    }
    np.savez(root / poses_file, **poses)
    return poses


def write_split_file(path: Path, n_rows: int, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    arrays = {
        "betas": rng.normal(size=(1, 10)), "global_orient": rng.normal(size=(n_rows, 3)),
        "body_pose": rng.normal(size=(n_rows, 69)), "transl": rng.normal(size=(n_rows, 3)),
    }
    path.parent.mkdir(exist_ok=True)
    np.savez(path, **arrays)
    return arrays


def test_every_layout_is_registered_and_detected(tmp_path):
    assert {"capture-v1", "peoplesnapshot", "xhumans"} <= set(layout_names())
    write_peoplesnapshot(tmp_path / "ps")
    write_xhumans(tmp_path / "xh")
    write_tiny_capture(tmp_path / "v1")
    assert detect_layout(tmp_path / "ps") == "peoplesnapshot"
    assert detect_layout(tmp_path / "xh") == "xhumans"
    assert detect_layout(tmp_path / "v1") == "capture-v1"
    (tmp_path / "v1" / "capture.json").unlink()  # a capture v1 that lost its index
    with pytest.raises(InputError, match=r"cameras.npz: holds capture v1 cameras .*capture.json is missing"):
        read_layout(tmp_path / "v1", detect_layout(tmp_path / "v1"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="cannot detect the capture layout.*peoplesnapshot.*xhumans"):
        detect_layout(tmp_path / "empty")


def test_peoplesnapshot_default_split_poses_and_masks(tmp_path):
    root = tmp_path / "my-subject"
    poses = write_peoplesnapshot(root, n_frames=12)
    capture = read_layout(root, "peoplesnapshot")
    # Default split: the first two thirds train, the rest test, every DEFAULT_STEP-th frame.
    assert DEFAULT_STEP == 4
    assert capture.splits == {"train": ["image_0000", "image_0004"], "test": ["image_0008"]}
    assert capture.frames == ["image_0000", "image_0004", "image_0008"]
    assert capture.body_model == "smpl" and capture.input_format == "peoplesnapshot"
    assert capture.K.shape == (3, 3, 3) and capture.K[2, 0, 0] == 40.0
    np.testing.assert_array_equal(capture.w2c, np.broadcast_to(np.eye(4), (3, 4, 4)))
    np.testing.assert_allclose(capture.poses["global_orient"], poses["thetas"][[0, 4, 8], :3])
    np.testing.assert_allclose(capture.poses["body_pose"], poses["thetas"][[0, 4, 8], 3:])
    np.testing.assert_allclose(capture.poses["transl"], poses["transl"][[0, 4, 8]])
    np.testing.assert_allclose(capture.poses["betas"], poses["betas"][0])
    assert capture.has_masks
    for index, frame in zip((0, 4, 8), capture.frames):
        assert capture.image_path(frame) == root / "images" / f"image_{index:04d}.png"
        np.testing.assert_array_equal(load_mask(capture.mask_path(frame), (SIZE, SIZE)), subject_mask(index) > 0)
    assert capture.input_files()[:2] == [root / "cameras.npz", root / "poses.npz"]


def test_peoplesnapshot_anim_nerf_split_files_replace_their_frames_poses(tmp_path, monkeypatch):
    root = tmp_path / "tiny-casual"
    poses = write_peoplesnapshot(root, n_frames=14)
    monkeypatch.setitem(ANIM_NERF_SPLITS, "tiny-casual", {"train": (0, 7, 2), "test": (8, 13, 3)})
    train = write_split_file(root / "poses" / "anim_nerf_train.npz", 4, seed=1)
    capture = read_layout(root, "peoplesnapshot")
    assert capture.splits["train"] == [f"image_{i:04d}" for i in (0, 2, 4, 6)]
    assert capture.splits["test"] == [f"image_{i:04d}" for i in (8, 11)]
    # Train frames take the refined split-file poses; the test split has no file: poses.npz.
    np.testing.assert_allclose(capture.poses["body_pose"][:4], train["body_pose"])
    np.testing.assert_allclose(capture.poses["global_orient"][:4], train["global_orient"])
    np.testing.assert_allclose(capture.poses["transl"][4:], poses["transl"][[8, 11]])
    np.testing.assert_allclose(capture.poses["betas"], train["betas"][0])
    assert root / "poses" / "anim_nerf_train.npz" in capture.source_files

    test = write_split_file(root / "poses" / "anim_nerf_test.npz", 2, seed=2)
    capture = read_layout(root, "peoplesnapshot")
    np.testing.assert_allclose(capture.poses["transl"][4:], test["transl"])
    np.testing.assert_allclose(capture.poses["betas"], train["betas"][0])


def test_peoplesnapshot_benchmark_subject_frame_counts(tmp_path):
    """male-3-casual: train 0-455 step 4 (114 frames), test 456-675 step 4 (55), as DATA.md says."""
    root = tmp_path / "male-3-casual"
    (root / "images").mkdir(parents=True)
    for i in range(676):
        (root / "images" / f"image_{i:04d}.png").touch()  # only names are read before assembly
    np.savez(root / "cameras.npz", intrinsic=np.eye(3), extrinsic=np.eye(4), height=SIZE, width=SIZE)
    np.savez(root / "poses.npz", betas=np.zeros(10), thetas=np.zeros((676, 72)), transl=np.zeros((676, 3)))
    capture = read_layout(root, "peoplesnapshot")
    assert len(capture.splits["train"]) == 114 and len(capture.splits["test"]) == 55
    assert capture.splits["test"][0] == "image_0456" and capture.splits["test"][-1] == "image_0672"
    assert capture.meta["subject"]["gender"] == "male" and not capture.has_masks


def test_peoplesnapshot_custom_video_variant(tmp_path):
    root = tmp_path / "custom"
    poses = write_peoplesnapshot(root, n_frames=6, masks="png", poses_file="poses_optimized.npz")
    capture = read_layout(root, detect_layout(root))
    assert capture.splits == {"train": ["image_0000"], "test": ["image_0004"]}
    np.testing.assert_allclose(capture.poses["transl"], poses["transl"][[0, 4]])
    np.testing.assert_array_equal(load_mask(capture.mask_path("image_0004")), subject_mask(4) > 0)


def test_peoplesnapshot_without_masks_reads_and_has_none(tmp_path):
    root = tmp_path / "s"
    write_peoplesnapshot(root, n_frames=6, masks="")
    capture = read_layout(root, "peoplesnapshot")
    assert not capture.has_masks and capture.mask_files == {}


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda r: np.savez(r / "cameras.npz", extrinsic=np.eye(4), height=32, width=32),
         r"cameras.npz: key 'intrinsic' missing"),
        (lambda r: np.savez(r / "cameras.npz", intrinsic=np.eye(4), extrinsic=np.eye(4), height=32, width=32),
         r"cameras.npz: key 'intrinsic' has shape \(4, 4\), expected \(3, 3\)"),
        (lambda r: np.savez(r / "poses.npz", betas=np.zeros(10), thetas=np.zeros((12, 69)), transl=np.zeros((12, 3))),
         r"poses.npz: key 'thetas' has shape \(12, 69\), expected \(N, 72\)"),
        (lambda r: np.savez(r / "poses.npz", betas=np.zeros(10), thetas=np.zeros((11, 72)), transl=np.zeros((11, 3))),
         r"poses.npz: key 'thetas' has 11 rows, expected 12 \(one per frame\)"),
        (lambda r: np.savez(r / "poses.npz", betas=np.zeros(8), thetas=np.zeros((12, 72)), transl=np.zeros((12, 3))),
         r"poses.npz: key 'betas' has shape \(8,\), expected \(10,\)"),
        (lambda r: (r / "masks" / "mask_0003.npy").unlink(), r"masks: 11 masks for 12 images"),
        (lambda r: np.save(r / "masks" / "mask_0004.npy", np.zeros((3, 4, 5))), r"mask_0004.npy: mask array has shape"),
        (lambda r: write_split_file(r / "poses" / "anim_nerf_train.npz", 3, 0),
         r"poses: Anim-NeRF split files, but 's' is not a subject with known frame ranges"),
        (lambda r: (r / "cameras.npz").write_bytes(b"not a zip"), r"cameras.npz: not a readable .npz"),
    ],
)
def test_peoplesnapshot_bad_inputs_name_file_key_and_shape(tmp_path, edit, message):
    root = tmp_path / "s"
    write_peoplesnapshot(root)
    edit(root)
    with pytest.raises(InputError, match=message):
        capture = read_layout(root, "peoplesnapshot")
        for frame in capture.frames:  # masks are read when used: preprocess loads every one
            load_mask(capture.mask_path(frame), (SIZE, SIZE))


def test_peoplesnapshot_split_file_with_wrong_row_count(tmp_path, monkeypatch):
    root = tmp_path / "tiny"
    write_peoplesnapshot(root, n_frames=12)
    monkeypatch.setitem(ANIM_NERF_SPLITS, "tiny", {"train": (0, 7, 2), "test": (8, 11, 2)})
    write_split_file(root / "poses" / "anim_nerf_test.npz", 5, seed=0)
    with pytest.raises(InputError, match=r"anim_nerf_test.npz: key 'global_orient' has 5 rows, expected 2"):
        read_layout(root, "peoplesnapshot")
    monkeypatch.setitem(ANIM_NERF_SPLITS, "tiny", {"train": (0, 7, 2), "test": (8, 20, 2)})
    with pytest.raises(InputError, match="12 images, but the Anim-NeRF test split of tiny runs to frame 20"):
        read_layout(root, "peoplesnapshot")


# ------------------------------------------------------------------------------------------------
# X-Humans fixtures

FAR = 1000.0  # aitviewer clears the depth buffer to the far plane


def xh_depth(number: int) -> np.ndarray:
    """(SIZE, SIZE) float32 depth: the subject at ~6 m on a far-plane background."""
    depth = np.full((SIZE, SIZE), FAR, np.float32)
    depth[6 + number % 4 : 26, 12:20] = 6.0 + 0.01 * np.arange(8, dtype=np.float32)
    return depth


def write_xh_take(take: Path, numbers: list[int], seed: int) -> dict:
    """One take: renders, depths, cameras, SMPL pickles and scans for frame `numbers`."""
    rng = np.random.default_rng(seed)
    for folder in ("render/image", "render/depth", "SMPL", "meshes_pkl"):
        (take / folder).mkdir(parents=True)
    params, extrinsics = {}, []
    for i, number in enumerate(numbers):
        cv2.imwrite(str(take / "render" / "image" / f"color_{number:06d}.png"), np.full((SIZE, SIZE, 3), 50, np.uint8))
        cv2.imwrite(str(take / "render" / "depth" / f"depth_{number:06d}.tiff"), xh_depth(number))
        params[number] = {
            "global_orient": rng.normal(size=3).astype(np.float32), "body_pose": rng.normal(size=69).astype(np.float32),
            "transl": rng.normal(size=3).astype(np.float32), "betas": rng.normal(size=10).astype(np.float32),
        }
        (take / "SMPL" / f"mesh-f{number:05d}_smpl.pkl").write_bytes(pickle.dumps(params[number]))
        scan = {"vertices": rng.normal(size=(4, 3)), "faces": np.array([[0, 1, 2], [0, 2, 3]]),
                "normals": np.zeros((4, 3)), "uvs": np.zeros((4, 2))}
        (take / "meshes_pkl" / f"mesh-f{number:05d}.pkl").write_bytes(pickle.dumps(scan))
        w2c = np.eye(4)
        angle = 0.3 * i
        w2c[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
        w2c[2, 3] = 6.0
        extrinsics.append(w2c)
    K = np.array([[60.0, 0, 16], [0, 60.0, 16], [0, 0, 1]])
    np.savez(take / "render" / "cameras.npz", intrinsic=K, extrinsic=np.stack(extrinsics))
    return params


def write_xhumans(root: Path) -> dict:
    """A subject with train takes 2 and 10 and test take 5; returns params[take_path][number]."""
    root.mkdir(parents=True)
    (root / "gender.txt").write_text("female\n")
    np.save(root / "mean_shape_smpl.npy", np.linspace(-1, 1, 10))
    takes = {root / "train" / "Take10": [1, 2], root / "train" / "Take2": [1, 2, 3], root / "test" / "Take5": [4, 5]}
    return {take: write_xh_take(take, numbers, seed) for seed, (take, numbers) in enumerate(takes.items())}


def test_xhumans_takes_frames_cameras_and_poses(tmp_path):
    root = tmp_path / "00036"
    params = write_xhumans(root)
    capture = read_layout(root, "xhumans")
    # The first train take by number (Take2, not Take10) trains; every test take tests.
    assert capture.splits == {
        "train": ["train-Take2-000001", "train-Take2-000002", "train-Take2-000003"],
        "test": ["test-Take5-000004", "test-Take5-000005"],
    }
    assert capture.frames == capture.splits["train"] + capture.splits["test"]
    assert capture.meta["subject"]["gender"] == "female" and capture.meta["subject"]["takes"]["train"] == ["Take2"]
    np.testing.assert_allclose(capture.poses["betas"], np.linspace(-1, 1, 10))
    take2, take5 = params[root / "train" / "Take2"], params[root / "test" / "Take5"]
    np.testing.assert_allclose(capture.poses["body_pose"][1], take2[2]["body_pose"], rtol=1e-6)
    np.testing.assert_allclose(capture.poses["global_orient"][4], take5[5]["global_orient"], rtol=1e-6)
    np.testing.assert_allclose(capture.poses["transl"][3], take5[4]["transl"], rtol=1e-6)
    # Extrinsic row i belongs to the i-th render of its take.
    cameras = np.load(root / "test" / "Take5" / "render" / "cameras.npz")
    np.testing.assert_allclose(capture.w2c[3:], cameras["extrinsic"])
    np.testing.assert_allclose(capture.K[4], cameras["intrinsic"])
    assert (capture.height, capture.width) == (SIZE, SIZE)
    assert capture.image_path("test-Take5-000005") == root / "test" / "Take5" / "render" / "image" / "color_000005.png"


def test_xhumans_masks_come_from_the_depth_renders(tmp_path):
    root = tmp_path / "00036"
    write_xhumans(root)
    capture = read_layout(root, "xhumans")
    assert capture.has_masks
    mask = load_mask(capture.mask_path("train-Take2-000003"), (SIZE, SIZE))
    np.testing.assert_array_equal(mask, xh_depth(3) < FAR)
    # A render whose background is 0 rather than the far plane reads the same way.
    zero_background = np.where(xh_depth(3) < FAR, xh_depth(3), 0).astype(np.float32)
    cv2.imwrite(str(tmp_path / "zero.tiff"), zero_background)
    np.testing.assert_array_equal(load_mask(tmp_path / "zero.tiff"), xh_depth(3) < FAR)


def test_xhumans_scans_are_read_by_eval(tmp_path):
    from igavatar.capture.scans import load_scan, match_scans

    root = tmp_path / "00036"
    write_xhumans(root)
    capture = read_layout(root, "xhumans")
    assert set(capture.scans) == set(capture.frames)
    path = capture.scans["test-Take5-000004"]
    vertices, faces = read_xhumans_scan(path)
    assert vertices.shape == (4, 3) and faces.dtype == np.int64 and faces.shape == (2, 3)
    np.testing.assert_array_equal(load_scan(path)[1], faces)
    matching = match_scans(root, capture.splits["test"], capture.frames)
    assert matching.matched == {f: capture.scans[f] for f in capture.splits["test"]} and not matching.missing


def _smpl_pkl(root: Path) -> Path:
    return root / "train" / "Take2" / "SMPL" / "mesh-f00002_smpl.pkl"


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda r: _smpl_pkl(r).write_bytes(pickle.dumps([1, 2, 3])),
         r"mesh-f00002_smpl.pkl: holds a list, expected a dict with global_orient"),
        (lambda r: _smpl_pkl(r).write_bytes(pickle.dumps({"vertices": np.zeros((4, 3)), "faces": np.zeros((2, 3))})),
         r"mesh-f00002_smpl.pkl: key 'global_orient' missing \(keys present: faces, vertices\)"),
        (lambda r: _smpl_pkl(r).write_bytes(pickle.dumps({"global_orient": np.zeros(3), "body_pose": np.zeros(63),
                                                          "transl": np.zeros(3)})),
         r"mesh-f00002_smpl.pkl: key 'body_pose' has shape \(63,\), expected \(69,\) or \(1, 69\)"),
        (lambda r: _smpl_pkl(r).write_bytes(pickle.dumps({"global_orient": Path("x")})),
         r"mesh-f00002_smpl.pkl: the pickle refers to pathlib"),
        (lambda r: _smpl_pkl(r).unlink(), r"mesh-f00002_smpl.pkl: missing"),
        (lambda r: np.savez(r / "train" / "Take2" / "render" / "cameras.npz", intrinsic=np.eye(3), extrinsic=np.zeros((2, 4, 4))),
         r"Take2/render/cameras.npz: key 'extrinsic' has shape \(2, 4, 4\), expected \(3, 4, 4\)"),
        (lambda r: np.save(r / "mean_shape_smpl.npy", np.zeros(16)),
         r"mean_shape_smpl.npy: key 'mean_shape' has shape \(16,\), expected \(10,\)"),
        (lambda r: (r / "test" / "Take5" / "render" / "depth" / "depth_000005.tiff").unlink(),
         r"depth_000005.tiff: missing; the masks come from the depth renders"),
        (lambda r: [p.rename(p.with_name("x" + p.name)) for p in (r / "train").iterdir()],
         r"train: no TakeN folders"),
    ],
)
def test_xhumans_bad_inputs_name_file_key_and_shape(tmp_path, edit, message):
    root = tmp_path / "00036"
    write_xhumans(root)
    edit(root)
    with pytest.raises(InputError, match=message):
        read_layout(root, "xhumans")


def test_xhumans_scan_of_another_kind_is_refused(tmp_path):
    path = tmp_path / "mesh-f00001.pkl"
    path.write_bytes(pickle.dumps({"vertices": np.zeros((4, 3)), "faces": np.array([[0, 1, 7]])}))
    with pytest.raises(InputError, match=r"key 'faces' indexes vertices outside \[0, 3\]"):
        read_xhumans_scan(path)
    path.write_bytes(pickle.dumps({"global_orient": np.zeros(3)}))
    with pytest.raises(InputError, match=r"key 'vertices' missing"):
        read_xhumans_scan(path)


# ------------------------------------------------------------------------------------------------
# End to end: preprocess an imported capture with a synthetic SMPL-layout model file


@pytest.fixture
def smpl_model_file(tmp_path) -> Path:
    from tests.smpl_fixture import make_smpl_arrays, write_smpl_pkl

    return write_smpl_pkl(tmp_path / "model" / "SMPL_NEUTRAL.pkl", make_smpl_arrays(seed=0))


def preprocess_cli(cli_runner, capture: Path, out: Path, smpl_model: Path):
    from igavatar_cli.main import app

    return cli_runner.invoke(app, ["preprocess", "--capture", str(capture), "--out", str(out), "--max-size", "32",
                                   "--grid-resolution", "8,4,8", "--smpl-model", str(smpl_model)])


def test_preprocess_reads_a_peoplesnapshot_subject(tmp_path, cli_runner, smpl_model_file):
    from igavatar.artifacts.manifest import read_artifact

    root = tmp_path / "subject"
    write_peoplesnapshot(root, n_frames=12)
    result = preprocess_cli(cli_runner, root, tmp_path / "dataset", smpl_model_file)
    assert result.exit_code == 0, result.output
    manifest = read_artifact(tmp_path / "dataset", expected="dataset")
    data = manifest["data"]
    assert data["source_format"] == "peoplesnapshot" and data["body_model"] == "smpl" and data["masks"] == "given"
    assert data["frames"] == ["image_0000", "image_0004", "image_0008"] and data["splits"]["test"] == ["image_0008"]
    recorded = [Path(record["path"]).name for record in manifest["inputs"]]
    assert recorded[:2] == ["cameras.npz", "poses.npz"] and "mask_0008.npy" in recorded
    written = cv2.imread(str(tmp_path / "dataset" / "masks" / "image_0004.png"), cv2.IMREAD_GRAYSCALE) > 127
    np.testing.assert_array_equal(written, subject_mask(4) > 0)
    frames = np.load(tmp_path / "dataset" / "frames.npz")
    assert frames["bone_transforms"].shape == (3, 24, 4, 4) and frames["is_test"].tolist() == [False, False, True]


def test_preprocess_reads_an_xhumans_subject_and_eval_finds_its_scans(tmp_path, cli_runner, smpl_model_file):
    from igavatar.artifacts.manifest import read_artifact
    from igavatar.capture.scans import default_gt_dir, match_scans

    root = tmp_path / "00036"
    write_xhumans(root)
    result = preprocess_cli(cli_runner, root, tmp_path / "dataset", smpl_model_file)
    assert result.exit_code == 0, result.output
    manifest = read_artifact(tmp_path / "dataset", expected="dataset")
    data = manifest["data"]
    assert data["source_format"] == "xhumans" and data["has_scans"] and data["masks"] == "given"
    written = cv2.imread(str(tmp_path / "dataset" / "masks" / "test-Take5-000004.png"), cv2.IMREAD_GRAYSCALE) > 127
    np.testing.assert_array_equal(written, xh_depth(4) < FAR)
    # eval's default ground truth: the subject directory, whose scans the importer lists.
    gt_dir = default_gt_dir(tmp_path / "dataset", manifest)
    assert gt_dir == root
    matching = match_scans(gt_dir, data["splits"]["test"], data["frames"])
    assert sorted(matching.matched) == data["splits"]["test"]


def test_preprocess_estimates_masks_of_a_peoplesnapshot_subject_without_them(tmp_path, cli_runner, smpl_model_file):
    """No masks/: each frame's mask is cut around the projected SMPL template; the sheet shows them."""
    from igavatar.artifacts.manifest import read_artifact

    root = tmp_path / "subject"
    write_peoplesnapshot(root, n_frames=6, masks="")
    # Put the body 3 m in front of the camera (the default fixture's translations wander off-screen).
    poses = dict(np.load(root / "poses.npz"))
    poses["transl"] = np.tile([0.0, 0.0, 3.0], (6, 1))
    np.savez(root / "poses.npz", **poses)
    result = preprocess_cli(cli_runner, root, tmp_path / "dataset", smpl_model_file)
    assert result.exit_code == 0, result.output
    data = read_artifact(tmp_path / "dataset", expected="dataset")["data"]
    assert data["masks"] == "estimated (grabcut)"
    for frame in data["frames"]:
        assert (cv2.imread(str(tmp_path / "dataset" / "masks" / f"{frame}.png"), cv2.IMREAD_GRAYSCALE) > 127).any()
    assert (tmp_path / "dataset" / "contact_sheet.png").is_file()


@pytest.mark.parametrize("protocol", [2, 4, 5])
def test_array_pickles_of_every_protocol_are_read(tmp_path, protocol):
    from igavatar.capture.pickles import load_array_pickle

    scan = {"vertices": np.arange(12.0).reshape(4, 3), "faces": np.array([[0, 1, 2]], np.int32), "scale": np.float32(2.0)}
    path = tmp_path / "mesh-f00001.pkl"
    path.write_bytes(pickle.dumps(scan, protocol=protocol))
    loaded = load_array_pickle(path)
    np.testing.assert_array_equal(loaded["vertices"], scan["vertices"])
    assert loaded["faces"].dtype == np.int32 and loaded["scale"] == np.float32(2.0)
    path.write_bytes(b"\x80\x04garbage")
    with pytest.raises(InputError, match="not a readable pickle"):
        load_array_pickle(path)
