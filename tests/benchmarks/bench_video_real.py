"""Video path on a real capture: frames alone against the same frames with the dataset's own poses.

    python tests/benchmarks/bench_video_real.py --frames DATA/377/images --humannerf DATA/377 --run-dir RUN
    python tests/benchmarks/bench_video_real.py --frames clip.mp4 --run-dir RUN --name my-clip --write-results

`video`: `preprocess --video FRAMES --every E --test-every 8` (nothing else given), trained with
`train`'s defaults (no pose refinement). With `--humannerf DIR` (the same subject in the HumanNeRF /
ZJU-MoCap layout) it also builds a capture of the *same* frames and held-out split from that
layout's own camera and poses (its SMPL skeleton, Anny fitted to it by preprocess) and trains it
without (`dataset-poses`) and with (`dataset-poses-refine`) pose refinement. Every run is scored on
the held-out frames (image metrics only: a real capture has no scans), in the subject's box and in
the full image, at half the dataset's size, once in the given poses and once after
`eval --refine-test-poses` (each held-out pose refined against its image, the avatar fixed). Research-only data stays outside the repo.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests" / "benchmarks"))
from bench_video import IMAGE_KEYS, commit, frame_values, igavatar, number, write_results  # noqa: E402


def dataset_pose_capture(humannerf: Path, video_capture: Path, out: Path) -> None:
    """A capture v1 of the video capture's frames and splits, with the HumanNeRF layout's cameras,
    masks and skeleton poses (its images as they are: the camera's distortion is undistorted by
    preprocess, as for the layout itself)."""
    from igavatar.capture.importers import read_layout

    source = read_layout(humannerf, "humannerf")
    meta = json.loads((video_capture / "capture.json").read_text())
    frames = meta["frames"]
    index = {name: i for i, name in enumerate(source.frames)}
    missing = [f for f in frames if f not in index]
    if missing:
        raise SystemExit(f"{humannerf}: frames {missing[:3]} of the video capture are not in the layout")
    keep = [index[f] for f in frames]
    if out.exists():
        shutil.rmtree(out)
    for sub in ("images", "masks"):
        (out / sub).mkdir(parents=True)
    for name in frames:
        shutil.copy(source.image_path(name), out / "images" / f"{name}.png")
        shutil.copy(source.mask_path(name), out / "masks" / f"{name}.png")
    cameras = {"K": source.K[keep], "w2c": source.w2c[keep], "height": np.int64(source.height),
               "width": np.int64(source.width)}
    if source.dist is not None:
        dist = source.dist if source.dist.ndim == 1 else source.dist[keep]
        if dist.ndim == 2:  # a capture's cameras.npz holds one (5,) set (DATA.md): a still camera's rows agree
            if np.abs(dist - dist[0]).max() > 1e-9:
                raise SystemExit(f"{humannerf}: the frames' distortion coefficients differ; capture v1 holds one set")
            dist = dist[0]
        cameras["dist"] = dist
    np.savez(out / "cameras.npz", **cameras)
    poses = {key: (value[keep] if key in ("rotvecs", "transl") else value) for key, value in source.poses.items()}
    np.savez(out / "poses.npz", **poses)
    (out / "capture.json").write_text(json.dumps({
        "format": "igavatar-capture", "version": 1, "body_model": source.body_model, "frames": frames,
        "splits": meta["splits"], "image_ext": ".png", "subject": {"source": str(humannerf)}}, indent=2))


def train_and_score(run: Path, args: argparse.Namespace, extra: list[str]) -> dict:
    started = time.perf_counter()
    if not (args.reuse and (run / "report" / "metrics.json").is_file()):
        igavatar("train", "--run-dir", str(run), "--preset", "cpu", "--steps", str(args.steps), "--seed", str(args.seed),
                 "--device", "cpu", *extra)
        igavatar("eval", "--run-dir", str(run), "--no-geometry", "--image-frames", "0", "--image-scale", "0.5",
                 "--seed", str(args.seed), "--device", "cpu")
    refined = run / "report-refined"
    if not (args.reuse and (refined / "metrics.json").is_file()):
        igavatar("eval", "--run-dir", str(run), "--out", str(refined), "--no-geometry", "--image-frames", "0",
                 "--image-scale", "0.5", "--refine-test-poses", "--seed", str(args.seed), "--device", "cpu")
    metrics = json.loads((run / "report" / "metrics.json").read_text())
    values = frame_values(metrics)
    refined_values = frame_values(json.loads((refined / "metrics.json").read_text()))
    model = json.loads((run / "model" / "manifest.json").read_text())
    return {"wall_s": time.perf_counter() - started, "frames_scored": len(metrics["frames"]),
            "pose_refinement": model["data"].get("pose_refinement"),
            **{key: statistics.mean(values[key]) for key in IMAGE_KEYS if key in values},
            **{f"refined_{key}": statistics.mean(refined_values[key]) for key in IMAGE_KEYS if key in refined_values}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=Path, required=True, help="a video file or a folder of frames")
    parser.add_argument("--humannerf", type=Path, help="the same subject in the HumanNeRF layout (its own poses)")
    parser.add_argument("--run-dir", type=Path, required=True)
    parser.add_argument("--name", default="zju-377")
    parser.add_argument("--every", type=int, default=2)
    parser.add_argument("--steps", type=int, default=800)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--video-args", nargs="*", default=[], help="extra `preprocess --video` options (--height ...)")
    parser.add_argument("--reuse", action="store_true")
    parser.add_argument("--write-results", action="store_true")
    args = parser.parse_args()
    made = commit()
    command = "python tests/benchmarks/bench_video_real.py " + " ".join(sys.argv[1:])
    video_run = args.run_dir / "video"
    rows: dict[str, dict] = {}
    if not (args.reuse and (video_run / "report" / "metrics.json").is_file()):
        summary = igavatar("preprocess", "--video", str(args.frames), "--run-dir", str(video_run), "--every",
                           str(args.every), "--test-every", "8", "--force", *args.video_args)
        (video_run / "preprocess-summary.json").write_text(json.dumps(summary, indent=2))
    summary = json.loads((video_run / "preprocess-summary.json").read_text())
    rows["video"] = {**train_and_score(video_run, args, []), "fit_residual_px": summary["video"]["fit_residual_px"],
                     "video_s_per_frame": summary["video"]["seconds_per_frame"]}
    if args.humannerf is not None:
        for name, extra in (("dataset-poses", ["--no-refine-poses"]), ("dataset-poses-refine", ["--refine-poses"])):
            run = args.run_dir / name
            if not (args.reuse and (run / "report" / "metrics.json").is_file()):
                dataset_pose_capture(args.humannerf, video_run / "capture", run / "capture")
                igavatar("preprocess", "--run-dir", str(run), "--force")
            rows[name] = train_and_score(run, args, extra)
    lines = [f"# Video path on a real capture: {args.name}", "", f"Commit `{made}`; command: `{command}`.",
             f"CPU (2 cores), `--preset cpu --steps {args.steps}`, seed {args.seed}; every {args.every}th source frame, "
             "every 8th kept frame held out; image metrics on the held-out frames at half the dataset's size.", "",
             "| run | frames scored | PSNR box | SSIM box | PSNR | SSIM | PSNR box, test poses refined | SSIM box, refined | "
             "fit px | s/frame (video path) | training pose refinement |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, v in rows.items():
        refine = v.get("pose_refinement")
        refined = "-" if not refine else f"{refine['pose_rot_deg']:.2f} deg, {refine['pose_root_mm']:.1f} mm"
        lines.append(f"| {name} | {v['frames_scored']} | {number(v.get('psnr_mask_bbox_db'))} | "
                     f"{number(v.get('ssim_mask_bbox'), 3)} | {number(v.get('psnr_full_db'))} | {number(v.get('ssim_full'), 3)} | "
                     f"{number(v.get('refined_psnr_mask_bbox_db'))} | {number(v.get('refined_ssim_mask_bbox'), 3)} | "
                     f"{number(v.get('fit_residual_px'))} | {number(v.get('video_s_per_frame'), 3)} | "
                     f"{refined} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.write_results:
        write_results(f"video-real-{args.name}", made, command, rows, text)


if __name__ == "__main__":
    main()
