"""`preprocess --video` end to end on a synthetic clip (MediaPipe, offline), then train, export,
animate; and each bad clip gets its one line and a non-zero exit, with nothing written."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from igavatar_cli.main import app


@pytest.fixture(scope="module")
def turn_clip(tmp_path_factory) -> tuple[Path, Path]:
    """A synthetic subject turning (192 px, 18 frames) as an mp4, and its capture (true masks)."""
    import imageio.v3 as iio

    from stages.synth import SynthOptions, run_synth

    root = tmp_path_factory.mktemp("video")
    capture = root / "synth"
    run_synth(SynthOptions(out=capture, resolution=192, train_frames=18, test_frames=0, seed=2))
    names = json.loads((capture / "capture.json").read_text())["splits"]["train"]
    frames = np.stack([iio.imread(capture / "images" / f"{n}.png") for n in names])
    clip = root / "turn.mp4"
    iio.imwrite(clip, frames, fps=15, codec="libx264", quality=9)
    return clip, capture


def _invoke(cli_runner, *args: str):
    return cli_runner.invoke(app, [*args], catch_exceptions=False)


def test_video_to_dataset_train_export_animate(cli_runner, turn_clip, tmp_path):
    clip, synth = turn_clip
    run = tmp_path / "run"
    result = _invoke(cli_runner, "preprocess", "--video", str(clip), "--run-dir", str(run), "--max-size", "96",
                     "--test-every", "6", "--json")
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["video"]["frames"] == 18 and summary["train"] == 15 and summary["test"] == 3
    meta = json.loads((run / "capture" / "capture.json").read_text())
    assert meta["frames"][:2] == ["frame_000000", "frame_000001"] and meta["splits"]["test"][0] == "frame_000005"
    assert meta["video"]["fit"]["mean_residual_px"] < 5.0 and meta["video"]["camera"]["focal_from"].startswith("default")
    assert (run / "capture" / "contact_sheet.png").is_file() and (run / "capture" / "landmarks.npz").is_file()
    # The person's masks against the true ones.
    ious = []
    for i, name in enumerate(json.loads((synth / "capture.json").read_text())["splits"]["train"]):
        truth = cv2.imread(str(synth / "masks" / f"{name}.png"), cv2.IMREAD_GRAYSCALE) > 127
        found = cv2.imread(str(run / "capture" / "masks" / f"frame_{i:06d}.png"), cv2.IMREAD_GRAYSCALE) > 127
        ious.append((truth & found).sum() / (truth | found).sum())
    assert np.mean(ious) > 0.9
    dataset_manifest = json.loads((run / "dataset" / "manifest.json").read_text())
    assert dataset_manifest["data"]["poses"] == "estimated"

    again = _invoke(cli_runner, "preprocess", "--video", str(clip), "--run-dir", str(run), "--max-size", "96",
                    "--test-every", "6", "--json")
    assert again.exit_code == 0 and "skipped" in json.loads(again.stdout)["video"]

    trained = _invoke(cli_runner, "train", "--run-dir", str(run), "--preset", "tiny", "--refine-poses", "--device", "cpu",
                      "--json")
    assert trained.exit_code == 0, trained.output
    model = json.loads((run / "model" / "manifest.json").read_text())
    assert model["config"]["refine_poses"] is True and model["data"]["pose_refinement"]["frames"] == 15
    assert (run / "model" / "refined_poses.npz").is_file()

    exported = _invoke(cli_runner, "export", "--run-dir", str(run), "--resolution", "32", "--pose", str(run / "dataset"),
                       "--device", "cpu", "--json")
    assert exported.exit_code == 0, exported.output
    mesh_manifest = json.loads((run / "mesh" / "manifest.json").read_text())
    assert "refined_frames" in json.dumps(mesh_manifest)
    animated = _invoke(cli_runner, "animate", "--run-dir", str(run), "--motion", "walk", "--frames", "2",
                       "--resolution", "32", "--device", "cpu", "--json")
    assert animated.exit_code == 0, animated.output
    # A video has no scans: eval scores the held-out images and says geometry was skipped.
    scored = _invoke(cli_runner, "eval", "--run-dir", str(run), "--image-scale", "0.25", "--samples", "16",
                     "--carry-poses", "--device", "cpu", "--json")
    assert scored.exit_code == 0, scored.output
    metrics = json.loads((run / "report" / "metrics.json").read_text())
    assert len(metrics["frames"]) == 3 and metrics["frames"][0]["values"]["psnr_full_db"] is not None
    assert "geometry is not evaluated" in json.dumps(metrics)
    # The held-out frames lie between refined training frames of the clip: posed by their corrections.
    carried = [f["frame"] for f in metrics["frames"] if f.get("carried_pose")]
    assert metrics["settings"]["carry_poses"] is True and carried, metrics["frames"]
    assert any(f"{len(carried)} of 3 test frames posed by the corrections" in n for n in metrics["notes"])
    # export poses a held-out frame of the dataset as eval --carry-poses does.
    held_out = _invoke(cli_runner, "export", "--run-dir", str(run), "--out", str(run / "mesh-5"), "--resolution", "32",
                       "--formats", "ply", "--pose", str(run / "dataset"), "--frame", "5", "--device", "cpu", "--json")
    assert held_out.exit_code == 0, held_out.output
    posed = json.loads((run / "mesh-5" / "manifest.json").read_text())["data"]["posed"]
    assert posed["frames"][0]["name"] == "frame_000005"
    assert posed.get("carried_frames", 0) == int("frame_000005" in carried) and "refined_frames" not in posed
    given = _invoke(cli_runner, "eval", "--run-dir", str(run), "--image-scale", "0.25", "--samples", "16",
                    "--device", "cpu", "--json")  # by default, the dataset's poses
    assert given.exit_code == 0, given.output
    metrics_given = json.loads((run / "report" / "metrics.json").read_text())
    assert metrics_given["settings"]["carry_poses"] is False
    assert not any(f.get("carried_pose") for f in metrics_given["frames"])


def _write_clip(path: Path, frames: list[np.ndarray]) -> Path:
    import imageio.v3 as iio

    iio.imwrite(path, np.stack(frames), fps=10, codec="libx264", quality=9)
    return path


def _frames(capture: Path) -> list[np.ndarray]:
    names = json.loads((capture / "capture.json").read_text())["splits"]["train"]
    return [cv2.cvtColor(cv2.imread(str(capture / "images" / f"{n}.png")), cv2.COLOR_BGR2RGB) for n in names]


def _refused(cli_runner, clip: Path, tmp_path: Path, match: str) -> None:
    run = tmp_path / "run"
    result = cli_runner.invoke(app, ["preprocess", "--video", str(clip), "--run-dir", str(run)])
    assert result.exit_code == 2, result.output
    errors = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and match in errors[0] and "Traceback" not in result.output
    assert not (run / "capture").exists() and not (run / "dataset").exists()


def test_a_file_that_is_no_video(cli_runner, tmp_path):
    fake = tmp_path / "holiday.mp4"
    fake.write_bytes(b"\x00\x01 not a video at all")
    _refused(cli_runner, fake, tmp_path, "not a readable video")


def test_no_person(cli_runner, tmp_path):
    rng = np.random.default_rng(0)
    rooms = [cv2.GaussianBlur(rng.integers(0, 255, (160, 160, 3), dtype=np.uint8), (0, 0), 3) for _ in range(12)]
    _refused(cli_runner, _write_clip(tmp_path / "room.mp4", rooms), tmp_path, "no person found in any of 12 frames")


def test_two_people(cli_runner, turn_clip, tmp_path):
    frames = _frames(turn_clip[1])
    pairs = [np.concatenate([a, b], axis=1) for a, b in zip(frames, frames[9:] + frames[:9])]
    _refused(cli_runner, _write_clip(tmp_path / "two.mp4", pairs), tmp_path, "second person")


def test_person_cut_by_the_frame(cli_runner, turn_clip, tmp_path):
    frames = [frame[:110] for frame in _frames(turn_clip[1])]  # the legs cut off at the bottom edge
    _refused(cli_runner, _write_clip(tmp_path / "cut.mp4", frames), tmp_path, "cut by the frame's edge")


def test_too_few_frames(cli_runner, turn_clip, tmp_path):
    frames = _frames(turn_clip[1])[:6]
    _refused(cli_runner, _write_clip(tmp_path / "short.mp4", frames), tmp_path, "training needs at least")
