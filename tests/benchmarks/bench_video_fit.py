"""Video fit alone (no training): the body fitted to a clip's BlazePose landmarks, with and without
the silhouette stage, against the true joints of synthetic clips.

    python tests/benchmarks/bench_video_fit.py --run-dir RUN                 # bench_video's turns in RUN
    python tests/benchmarks/bench_video_fit.py --run-dir RUN --motion        # also a walk/arm-raise/squat clip
    python tests/benchmarks/bench_video_fit.py --run-dir RUN --write-results --tag video-fit-silhouette

It reads what `bench_video.py --variants truth,video-true` left in RUN/<subject>/ (the video
capture's landmarks.npz as fitted, its masks and camera; the truth capture's poses) and refits
the same landmarks, so the detector's output is held fixed and only the fit differs. With
--motion it first makes RUN/motion: `synth --train-frames 1 --test-frames 60` (a walk, an arm
raise and a squat, 20 frames each, one fixed camera) written to an mp4 and read by
`preprocess --video` with the true height and focal.

Variants: the landmarks alone; the silhouette stage (the body inside the mask) without the
optical-flow term; that stage with the flow term, as the video path runs it (the frames are the
capture's images); and the stage with the optional outline coverage term (coverage_weight 2), no flow.

Scores over the clip's frames (14 main joints, bench_video.MAIN_JOINTS):
- 2D px: joints projected into the frame against the true joints projected (after the clip's
  similarity below), what the avatar's rays see;
- MPJPE mm: after one similarity for the whole clip (Umeyama over every frame's joints);
- PA-MPJPE mm: after one similarity per frame (articulation only);
- depth mm: the frame's mean joint depth against the truth's, after the clip's similarity;
- fit px: the landmarks' reprojection residual.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests" / "benchmarks"))
from bench_video import (MAIN_JOINTS, RESULTS, TEST_EVERY, igavatar, kept_indices, main_joints,  # noqa: E402
                         pa_mpjpe_mm, similarity)
from provenance import commit  # noqa: E402

VARIANTS = {"landmarks only": {"silhouette_weight": 0.0}, "body inside the mask": {"flow_weight": 0.0},
            "inside + optical flow (default)": {}, "inside + outline coverage": {"coverage_weight": 2.0, "flow_weight": 0.0}}


def motion_clip(run: Path) -> tuple[Path, Path]:
    """RUN/motion/{truth/capture, video-true/capture}: a synthetic clip of motion (not a turn)."""
    import imageio.v3 as iio

    base = run / "motion"
    truth, video = base / "truth" / "capture", base / "video-true" / "capture"
    if (video / "landmarks.npz").is_file():
        return truth, video
    synth = base / "synth"
    igavatar("synth", "--out", str(synth), "--resolution", "512", "--train-frames", "1", "--test-frames", "60", "--force")
    meta = json.loads((synth / "capture.json").read_text())
    names = meta["splits"]["test"]
    iio.imwrite(base / "clip.mp4", np.stack([iio.imread(synth / "images" / f"{n}.png") for n in names]),
                fps=30, codec="libx264", quality=8)
    if truth.exists():
        shutil.rmtree(truth)
    truth.mkdir(parents=True)
    poses = dict(np.load(synth / "poses.npz"))
    poses["pose_parameters"] = poses["pose_parameters"][[meta["frames"].index(n) for n in names]]
    np.savez(truth / "poses.npz", **poses)
    shutil.copy(synth / "cameras.npz", truth / "cameras.npz")
    from igavatar.body.anny_body import AnnyBody, load_anny

    labels = [str(v) for v in poses["phenotype_labels"]]
    body = AnnyBody(load_anny(), dict(zip(labels, poses["phenotype_values"].tolist())))
    height = float(body.rest_vertices[:, 2].max() - body.rest_vertices[:, 2].min())
    focal = float(np.load(synth / "cameras.npz")["K"][0, 0])
    igavatar("preprocess", "--video", str(base / "clip.mp4"), "--run-dir", str(base / "video-true"), "--force",
             "--test-every", str(TEST_EVERY), "--height", f"{height:.4f}", "--focal", f"{focal:.3f}")
    return truth, video


def load_clip(truth: Path, video: Path):
    """(body, tracks, camera, true joints (N, 14, 3) of the kept frames, frames (N, H, W, 3) uint8
    RGB) of a bench_video clip."""
    import cv2

    from igavatar.body.anny_body import AnnyBody, load_anny
    from igavatar.capture.person_landmarks import PersonTracks
    from igavatar.capture.video_fit import VideoCamera

    landmarks = np.load(video / "landmarks.npz")
    names = json.loads((video / "capture.json").read_text())["frames"]
    masks = np.stack([cv2.imread(str(video / "masks" / f"{n}.png"), cv2.IMREAD_GRAYSCALE) / 255.0 for n in names])
    poses = np.load(video / "poses.npz")
    labels = [str(v) for v in poses["phenotype_labels"]]
    body = AnnyBody(load_anny(), dict(zip(labels, poses["phenotype_values"].tolist())))
    cameras = np.load(video / "cameras.npz")
    camera = VideoCamera(cameras["K"], cameras["w2c"], masks.shape[1], masks.shape[2], "the capture's")
    tracks = PersonTracks(np.ones(len(names), bool), masks.astype(np.float32), masks.astype(np.float32),
                          landmarks["image_xy"], landmarks["visibility"], landmarks["world_xyz"])
    images = [cv2.cvtColor(cv2.imread(str(video / "images" / f"{n}.png")), cv2.COLOR_BGR2RGB) for n in names]
    return body, tracks, camera, main_joints(truth)[kept_indices(video)], images


def scores(body, fit, true_joints: np.ndarray, camera) -> dict:
    import torch

    from igavatar.body.skeleton import forward_kinematics

    posed = forward_kinematics(torch.as_tensor(fit.local_rotations), body.skeleton.rest_joints, body.skeleton.parents,
                               torch.as_tensor(fit.root_translation))[..., :3, 3]
    fitted = posed[:, [body.skeleton.index(j) for j in MAIN_JOINTS]].numpy()
    scale, rotation, shift = similarity(true_joints.reshape(-1, 3), fitted.reshape(-1, 3))
    truth = true_joints @ (scale * rotation).T + shift

    def camera_frame(x: np.ndarray) -> np.ndarray:
        return x @ camera.w2c[:3, :3].T + camera.w2c[:3, 3]

    def pixels(x: np.ndarray) -> np.ndarray:
        uv = camera_frame(x) @ camera.K.T
        return uv[..., :2] / uv[..., 2:]

    depth = camera_frame(fitted)[..., 2].mean(1) - camera_frame(truth)[..., 2].mean(1)
    return {"joints_2d_px": float(np.linalg.norm(pixels(fitted) - pixels(truth), axis=-1).mean()),
            "mpjpe_mm": 1000 * float(np.linalg.norm(fitted - truth, axis=-1).mean()),
            "pa_mpjpe_mm": float(np.mean(pa_mpjpe_mm(true_joints, fitted))),
            "frame_depth_mm": 1000 * float(np.abs(depth).mean()), "fit_px": fit.mean_residual_px()}


def run_clip(name: str, truth: Path, video: Path, variants: list[str]) -> list[dict]:
    import dataclasses

    from igavatar.body.landmark_fit import LandmarkFitConfig
    from igavatar.capture.video_fit import HINGE_BONES, fit_anny_to_tracks

    body, tracks, camera, true_joints, images = load_clip(truth, video)
    rows = []
    for variant in variants:
        changes = VARIANTS[variant]
        config = LandmarkFitConfig(hinge_joints=tuple(body.skeleton.index(b) for b in HINGE_BONES))
        started = time.perf_counter()
        fit = fit_anny_to_tracks(body, tracks, camera, dataclasses.replace(config, **changes), images=images)
        row = {"clip": name, "variant": variant, "frames": len(true_joints), "fit_s": time.perf_counter() - started,
               **scores(body, fit, true_joints, camera)}
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


def markdown(rows: list[dict], command: str, made: str) -> str:
    lines = ["# Video fit: the silhouette stage, with and without the optical flow (no training)\n",
             f"Commit `{made}`; command: `{command}`. CPU (2 cores). The same BlazePose landmarks and masks "
             "(each clip's `preprocess --video` capture with the true height and focal), refitted; see the "
             "script's docstring for the scores.\n",
             "| clip | fit | frames | 2D px | MPJPE mm | PA-MPJPE mm | frame depth mm | fit px | fit s |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['clip']} | {r['variant']} | {r['frames']} | {r['joints_2d_px']:.2f} | {r['mpjpe_mm']:.1f} | "
                     f"{r['pa_mpjpe_mm']:.1f} | {r['frame_depth_mm']:.1f} | {r['fit_px']:.2f} | {r['fit_s']:.1f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dir", type=Path, required=True)
    parser.add_argument("--subjects", default="stripes-shirt,checker-dress,plain-heavy")
    parser.add_argument("--variants", default=",".join(VARIANTS), help="which of the fits, by name, comma-separated")
    parser.add_argument("--motion", action="store_true", help="also make and fit RUN/motion")
    parser.add_argument("--tag", default="video-fit-silhouette")
    parser.add_argument("--write-results", action="store_true")
    args = parser.parse_args()
    made, command = commit(), "python tests/benchmarks/bench_video_fit.py " + " ".join(sys.argv[1:])
    clips = [(s, args.run_dir / s / "truth" / "capture", args.run_dir / s / "video-true" / "capture")
             for s in args.subjects.split(",") if s]
    if args.motion:
        clips.append(("motion", *motion_clip(args.run_dir)))
    variants = [v for v in args.variants.split(",") if v]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        parser.error(f"--variants: unknown {unknown}; known: {list(VARIANTS)}")
    rows = [row for name, truth, video in clips for row in run_clip(name, truth, video, variants)]
    text = markdown(rows, command, made)
    print(text)
    if args.write_results:
        (RESULTS / f"{args.tag}.md").write_text(text)
        (RESULTS / f"{args.tag}.json").write_text(json.dumps({"commit": made, "command": command, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
