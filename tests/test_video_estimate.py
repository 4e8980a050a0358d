"""`preprocess --video CLIP --poses-from FILE`: WHAM's and TRAM's SMPL results read safely, placed in
the capture's world without moving the body in the image, and bad files refused with one line."""

from __future__ import annotations

import json
import pickle
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import torch

from igavatar.body.rotations import axis_angle_to_matrix
from igavatar.capture.estimator_poses import read_estimator_poses
from igavatar.errors import InputError
from igavatar.geometry.projection import project_points
from igavatar_cli.main import app
from tests.smpl_fixture import make_smpl_arrays, random_smpl_poses, write_smpl_pkl


KEEP = None  # a folder to copy the test's capture to, for a look at its contact sheet


def _write_wham(path: Path, params: dict, frames: np.ndarray, extra_track: bool = True) -> Path:
    """WHAM's wham_output.pkl (joblib): the person's track, and a passer-by's 3-frame track."""
    import joblib

    results = defaultdict(dict)
    n = len(frames)
    pose = np.concatenate((params["global_orient"], params["body_pose"]), axis=1).astype(np.float32)
    results[1] = {"pose": pose, "trans": params["transl"].astype(np.float32), "pose_world": pose,
                  "trans_world": params["transl"].astype(np.float32),
                  "betas": np.repeat(params["betas"][None], n, axis=0).astype(np.float32), "frame_ids": frames}
    if extra_track:
        results[4] = {key: value[:3] for key, value in results[1].items()}
    joblib.dump(results, path)
    return path


def _write_tram(folder: Path, params: dict, frames: np.ndarray, focal: float, center: tuple[float, float]) -> Path:
    """TRAM's hps/hps_track_0.npy: np.save of a dict of torch tensors."""
    rotvecs = np.concatenate((params["global_orient"][:, None], params["body_pose"].reshape(-1, 23, 3)), axis=1)
    n = len(frames)
    track = {"pred_rotmat": axis_angle_to_matrix(torch.as_tensor(rotvecs, dtype=torch.float32)),
             "pred_trans": torch.as_tensor(params["transl"], dtype=torch.float32)[:, None],
             "pred_shape": torch.as_tensor(np.repeat(params["betas"][None], n, axis=0), dtype=torch.float32),
             "pred_cam": torch.zeros(n, 3), "pred_pose": torch.zeros(n, 144),
             "frame": torch.as_tensor(frames), "img_focal": focal, "img_center": np.array(center)}
    folder.mkdir(parents=True, exist_ok=True)
    np.save(folder / "hps_track_0.npy", track, allow_pickle=True)
    return folder / "hps_track_0.npy"


def test_wham_and_tram_files_read_alike(tmp_path):
    params = random_smpl_poses(6, seed=3)
    frames = np.array([2, 3, 4, 6, 7, 9])
    wham = read_estimator_poses(_write_wham(tmp_path / "wham_output.pkl", params, frames))
    tram = read_estimator_poses(_write_tram(tmp_path / "hps", params, frames, 812.0, (320.0, 240.0)))
    assert wham.track == "1" and wham.tracks == 2  # the longest track, not the passer-by
    assert wham.focal_px is None and tram.focal_px == 812.0 and np.allclose(tram.center_px, (320, 240))
    for poses in (wham, tram):
        assert np.array_equal(poses.source_frames, frames)
        assert np.allclose(poses.betas, params["betas"], atol=1e-5)
        assert np.allclose(poses.transl, params["transl"], atol=1e-5)
    # TRAM's rotation matrices back to axis-angles: the same rotations as WHAM's axis-angles.
    for a, b in ((wham.global_orient, tram.global_orient), (wham.body_pose, tram.body_pose)):
        ra = axis_angle_to_matrix(torch.as_tensor(a.reshape(-1, 3)))
        rb = axis_angle_to_matrix(torch.as_tensor(b.reshape(-1, 3)))
        assert torch.allclose(ra, rb, atol=1e-5)


def test_foreign_and_unsafe_files_are_refused(tmp_path):
    import joblib

    class Runs:
        def __reduce__(self):
            return (print, ("this would run",))

    joblib.dump({1: {"pose": Runs()}}, tmp_path / "evil.pkl")
    np.savez(tmp_path / "gvhmr.npz", global_orient=np.zeros((4, 3)), body_pose=np.zeros((4, 63)))
    (tmp_path / "clip.txt").write_text("poses")
    with (tmp_path / "plain.pkl").open("wb") as stream:
        pickle.dump({1: {"pose": np.zeros((4, 70)), "trans": np.zeros((4, 3)), "betas": np.zeros((4, 10)),
                         "frame_ids": np.arange(4)}}, stream)
    cases = {"evil.pkl": "refers to builtins.print", "gvhmr.npz": "SMPL-X", "clip.txt": "expected WHAM's",
             "plain.pkl": "key 'pose' has shape (4, 70), expected (N, 72)", "missing.pkl": "no such file"}
    for name, message in cases.items():
        with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")):
            read_estimator_poses(tmp_path / name)


def test_the_world_turn_keeps_the_body_where_the_image_has_it(tmp_path):
    """The capture's world is the camera turned to +Y up: each vertex projects to the same pixel."""
    from igavatar.body.smpl_model import load_smpl_model
    from igavatar.capture.video_frames import VideoFrames
    from stages.video_estimate import Estimate, _world_parameters, estimate_camera

    model = load_smpl_model(write_smpl_pkl(tmp_path / "SMPL_NEUTRAL.pkl", make_smpl_arrays(seed=1)))
    params = random_smpl_poses(4, seed=5)
    params["transl"][:, 2] += 3.0  # in front of the camera
    frames = np.arange(4)
    estimate = Estimate(read_estimator_poses(_write_tram(tmp_path / "hps", params, frames, 500.0, (240.0, 320.0))),
                        model)
    clip = VideoFrames([np.zeros((320, 240, 3), np.uint8)] * 4, list(frames), 4, None, (640, 480))
    camera = estimate_camera(estimate.poses, clip, None, None)
    assert np.allclose(camera.K, [[250, 0, 119.75], [0, 250, 159.75], [0, 0, 1]])  # half size
    orient, body_pose, transl = _world_parameters(estimate, frames)
    in_world = model.forward(torch.as_tensor(params["betas"]), torch.as_tensor(orient), torch.as_tensor(body_pose),
                             torch.as_tensor(transl)).vertices.numpy()
    in_camera = model.forward(torch.as_tensor(params["betas"]), torch.as_tensor(params["global_orient"]),
                              torch.as_tensor(params["body_pose"]), torch.as_tensor(params["transl"])).vertices.numpy()
    for i in range(4):
        uv_world, _ = project_points(camera.K, camera.w2c, in_world[i])
        uv_camera, _ = project_points(camera.K, np.eye(4), in_camera[i])
        assert np.abs(uv_world - uv_camera).max() < 1e-3
        assert np.allclose(in_world[i] @ np.diag([1.0, -1.0, -1.0]), in_camera[i], atol=1e-5)


def _synth_estimate(synth: Path, model, frames: np.ndarray) -> dict:
    """SMPL parameters (camera frame) that put a T-posed SMPL body where the synthetic person
    stands in each source frame: its pelvis on the person's hips, its body axes on the person's."""
    from igavatar.body.anny_body import AnnyBody, load_anny
    from igavatar.body.motions import body_to_world
    from igavatar.body.skeleton import forward_kinematics

    poses = np.load(synth / "poses.npz")
    cameras = np.load(synth / "cameras.npz")
    labels = [str(v) for v in poses["phenotype_labels"]]
    body = AnnyBody(load_anny(), dict(zip(labels, poses["phenotype_values"].tolist())))
    local, translation = body.local_rotations_from_pose_parameters(torch.as_tensor(poses["pose_parameters"]))
    world = forward_kinematics(local, body.skeleton.rest_joints, body.skeleton.parents, translation).numpy()
    hips = [body.skeleton.index(name) for name in ("upperleg01.L", "upperleg01.R")]
    w2c = cameras["w2c"]
    betas = np.zeros(10)
    root = model.rest_shape(torch.as_tensor(betas))[1][0].numpy()
    orient, transl = [], []
    for i in frames:
        rotation = w2c[:3, :3] @ world[i, 0, :3, :3] @ body_to_world("anny") @ body_to_world("smpl").T
        pelvis = w2c[:3, :3] @ world[i, hips, :3, 3].mean(axis=0) + w2c[:3, 3]
        orient.append(torch.as_tensor(rotation))
        transl.append(pelvis - root)
    from igavatar.body.rotations import matrix_to_axis_angle

    return {"betas": betas, "global_orient": matrix_to_axis_angle(torch.stack(orient)).numpy(),
            "body_pose": np.zeros((len(frames), 69)), "transl": np.array(transl), "focal": float(cameras["K"][0, 0])}


@pytest.fixture(scope="module")
def estimated_clip(tmp_path_factory) -> dict:
    """A synthetic subject turning (192 px, 18 frames) as an mp4, a T-posed SMPL-like body placed on
    it per frame as WHAM would save it (frames 1-17: frame 0 has no estimate), and the model file."""
    import imageio.v3 as iio

    from stages.synth import SynthOptions, run_synth

    root = tmp_path_factory.mktemp("estimate")
    synth = root / "synth"
    run_synth(SynthOptions(out=synth, resolution=192, train_frames=18, test_frames=0, seed=2))
    names = json.loads((synth / "capture.json").read_text())["splits"]["train"]
    clip = root / "turn.mp4"
    iio.imwrite(clip, np.stack([iio.imread(synth / "images" / f"{n}.png") for n in names]), fps=15, codec="libx264",
                quality=9)
    from igavatar.body.smpl_model import load_smpl_model

    model_path = write_smpl_pkl(root / "SMPL_NEUTRAL.pkl", make_smpl_arrays(seed=1, points_per_bone=12, tube_radius=0.07))
    frames = np.arange(1, 18)
    params = _synth_estimate(synth, load_smpl_model(model_path), frames)
    wham = _write_wham(root / "wham_output.pkl", params, frames)
    return {"clip": clip, "model": model_path, "wham": wham, "params": params, "frames": frames, "root": root}


def test_video_with_wham_poses_to_dataset_and_training(cli_runner, estimated_clip, tmp_path):
    case = estimated_clip
    run = tmp_path / "run"
    result = cli_runner.invoke(app, ["preprocess", "--video", str(case["clip"]), "--poses-from", str(case["wham"]),
                                     "--smpl-model", str(case["model"]), "--focal", str(case["params"]["focal"]),
                                     "--run-dir", str(run), "--max-size", "96", "--test-every", "6", "--json"])
    assert result.exit_code == 0, result.output
    meta = json.loads((run / "capture" / "capture.json").read_text())
    video = meta["video"]
    assert meta["body_model"] == "smpl" and meta["frames"][0] == "frame_000001"
    assert video["dropped"]["no_estimate"] == [0] and video["poses_from"]["estimator"] == "wham"
    assert video["poses_from"]["track"] == "1" and video["poses_from"]["tracks_in_file"] == 2
    assert video["camera"]["focal_from"] == "--focal"
    # A T-posed tube body on a person with lowered arms: well above the refusal line.
    assert video["fit"]["body_mask_iou_mean"] > 0.35
    assert (run / "capture" / "contact_sheet.png").is_file()
    if KEEP:
        import shutil

        shutil.copytree(run / "capture", KEEP, dirs_exist_ok=True)
    dataset = json.loads((run / "dataset" / "manifest.json").read_text())["data"]
    assert dataset["poses"] == "estimated" and dataset["body_model"] == "smpl"
    trained = cli_runner.invoke(app, ["train", "--run-dir", str(run), "--preset", "tiny", "--steps", "20", "--device",
                                      "cpu", "--json"])
    assert trained.exit_code == 0, trained.output
    model = json.loads((run / "model" / "manifest.json").read_text())
    assert model["data"]["body_model"] == "smpl" and model["data"]["steps"] == 20


def _refused(cli_runner, run: Path, args: list[str], match: str) -> None:
    result = cli_runner.invoke(app, ["preprocess", *args, "--run-dir", str(run)])
    assert result.exit_code == 2, result.output
    errors = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and match in errors[0] and "Traceback" not in result.output, result.output
    assert not (run / "capture").exists() and not (run / "dataset").exists()


def test_poses_that_are_not_this_clips_are_refused(cli_runner, estimated_clip, tmp_path):
    case = estimated_clip
    shifted = dict(case["params"], transl=case["params"]["transl"] + np.array([1.5, 0.0, 0.0]))
    elsewhere = _write_wham(tmp_path / "elsewhere.pkl", shifted, case["frames"])
    later = _write_wham(tmp_path / "later.pkl", case["params"], case["frames"] + 100)
    common = ["--video", str(case["clip"]), "--smpl-model", str(case["model"]), "--max-size", "96"]
    _refused(cli_runner, tmp_path / "a", [*common, "--poses-from", str(elsewhere)], "overlaps the person's masks by IoU")
    _refused(cli_runner, tmp_path / "b", [*common, "--poses-from", str(later)], "covers source frames 101-117, none")
    _refused(cli_runner, tmp_path / "c", ["--video", str(case["clip"]), "--poses-from", str(case["wham"])],
             "SMPL model")
    _refused(cli_runner, tmp_path / "d", ["--poses-from", str(case["wham"])], "needs --video")
