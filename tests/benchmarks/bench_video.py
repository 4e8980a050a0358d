"""Video-path benchmark: synthetic subjects rendered to an mp4, against the same frames with true poses.

    python tests/benchmarks/bench_video.py --run-dir RUN                      # 3 subjects, 800 steps
    python tests/benchmarks/bench_video.py --run-dir RUN --subjects stripes-shirt --steps 300
    python tests/benchmarks/bench_video.py --run-dir RUN --write-results      # also record it in results/
    python tests/benchmarks/bench_video.py --run-dir RUN --noise 5,10 --reuse --tag pose-noise --write-results

For every subject (bench_quality's: stripes-shirt, checker-dress in a dress, plain-heavy) it
synthesises a 360-degree turn, writes it to clip.mp4 (H.264, as a phone would) and runs:
- `truth`: the same frames (renamed frame_000123, the same held-out split) with their true
  poses, camera and masks: the capture the video path tries to recover;
- `video-true`: `preprocess --video clip.mp4 --height H --focal F` with the true height and focal;
- `video-default`: `preprocess --video clip.mp4` with nothing else given;
- `video-true-refine`, `video-default-refine`: that variant's dataset (copied, not fitted again)
  trained with `--refine-poses` (run after it).
Each is trained (`--preset cpu --steps S`) and evaluated on the held-out frames: image metrics
(PSNR/SSIM in the subject's box and the full image) and posed geometry against the scans.

With --noise D1,D2 it runs the pose-noise study instead: the `truth` captures of an earlier run
with noise on the training frames' poses (D degrees a joint about a random axis, 2 cm on the
root), trained without and with `--refine-poses`, against the exact poses.

Alignment for geometry: a video capture lives in its own world (camera at the origin, scale from
--height). One similarity transform per clip (Umeyama on the 14 main joints of every frame, fitted
against true) maps the true scans into the video's world; with the true height and focal it is
nearly the identity relative to the camera. Mask IoU compares the video masks with the true ones;
PA-MPJPE aligns each frame's 14 main joints (shoulders, elbows, wrists, hips, knees, ankles, neck,
head) by a similarity before measuring.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests" / "benchmarks"))
from bench_quality import SUBJECTS  # noqa: E402
from provenance import commit  # noqa: E402

RESULTS = ROOT / "tests" / "benchmarks" / "results"
MAIN_JOINTS = ("upperarm01.L", "upperarm01.R", "lowerarm01.L", "lowerarm01.R", "wrist.L", "wrist.R", "upperleg01.L",
               "upperleg01.R", "lowerleg01.L", "lowerleg01.R", "foot.L", "foot.R", "neck01", "head")
TEST_EVERY = 8
VARIANTS = ("truth", "video-true", "video-default")
REFINED = ("video-true-refine", "video-default-refine")
ALL_VARIANTS = VARIANTS + REFINED  # the order of the tables
IMAGE_KEYS = ("psnr_mask_bbox_db", "ssim_mask_bbox", "psnr_full_db", "ssim_full")
GEOMETRY_KEYS = ("chamfer_l1_surface_mm", "volumetric_iou", "normal_consistency_surface")


def igavatar(*args: str) -> dict:
    command = [sys.executable, "-m", "igavatar_cli.main", *args, "--json"]
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed ({done.returncode}):\n{done.stderr[-3000:]}")
    return json.loads(done.stdout)


def synth_subject(run: Path, subject: str, frames: int) -> Path:
    capture = run / "synth"
    igavatar("synth", "--out", str(capture), "--resolution", "512", "--train-frames", str(frames), "--test-frames", "0",
             *SUBJECTS[subject])
    return capture


def write_clip(capture: Path, clip: Path) -> list[str]:
    import imageio.v3 as iio

    names = json.loads((capture / "capture.json").read_text())["splits"]["train"]
    images = np.stack([iio.imread(capture / "images" / f"{n}.png") for n in names])
    iio.imwrite(clip, images, fps=30, codec="libx264", quality=8)
    return names


def truth_capture(synth: Path, names: list[str], out: Path) -> None:
    """The synthetic frames as the video path names and splits them, with their true poses."""
    if out.exists():
        shutil.rmtree(out)
    for sub in ("images", "masks", "scans"):
        (out / sub).mkdir(parents=True)
    renamed = [f"frame_{i:06d}" for i in range(len(names))]
    for old, new in zip(names, renamed):
        shutil.copy(synth / "images" / f"{old}.png", out / "images" / f"{new}.png")
        shutil.copy(synth / "masks" / f"{old}.png", out / "masks" / f"{new}.png")
        shutil.copy(synth / "scans" / f"{old}.ply", out / "scans" / f"{new}.ply")
    shutil.copy(synth / "cameras.npz", out / "cameras.npz")
    poses = dict(np.load(synth / "poses.npz"))
    poses["pose_parameters"] = poses["pose_parameters"][: len(names)]
    np.savez(out / "poses.npz", **poses)
    test = [n for i, n in enumerate(renamed) if (i + 1) % TEST_EVERY == 0]
    meta = {"format": "igavatar-capture", "version": 1, "body_model": "anny", "frames": renamed,
            "splits": {"train": [n for n in renamed if n not in test], "test": test}, "image_ext": ".png"}
    (out / "capture.json").write_text(json.dumps(meta, indent=2))


def main_joints(capture: Path) -> np.ndarray:
    """(N, 14, 3) world positions of the main joints of a capture's Anny poses."""
    import torch

    from igavatar.body.anny_body import AnnyBody, load_anny
    from igavatar.body.skeleton import forward_kinematics

    poses = np.load(capture / "poses.npz")
    labels = [str(v) for v in poses["phenotype_labels"]]
    body = AnnyBody(load_anny(), dict(zip(labels, poses["phenotype_values"].tolist())))
    local, translation = body.local_rotations_from_pose_parameters(torch.as_tensor(poses["pose_parameters"]))
    joints = forward_kinematics(local, body.skeleton.rest_joints, body.skeleton.parents, translation)[..., :3, 3]
    return joints[:, [body.skeleton.index(j) for j in MAIN_JOINTS]].numpy()


def similarity(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama: (s, R, t) minimizing |s R source + t - target|^2 over points (P, 3)."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    a, b = source - mu_s, target - mu_t
    u, sigma, vt = np.linalg.svd(b.T @ a / len(a))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ d @ vt
    scale = float(np.trace(np.diag(sigma) @ d) / (a**2).sum(1).mean())
    return scale, rotation, mu_t - scale * rotation @ mu_s


def pa_mpjpe_mm(true: np.ndarray, fitted: np.ndarray) -> list[float]:
    errors = []
    for t, f in zip(true, fitted):
        s, r, shift = similarity(f, t)
        errors.append(1000 * float(np.linalg.norm(f @ (s * r).T + shift - t, axis=1).mean()))
    return errors


def mask_iou(truth: Path, video: Path, names: list[str]) -> list[float]:
    ious = []
    for name in names:
        a = cv2.imread(str(truth / "masks" / f"{name}.png"), cv2.IMREAD_GRAYSCALE) > 127
        b = cv2.imread(str(video / "masks" / f"{name}.png"), cv2.IMREAD_GRAYSCALE) > 127
        ious.append(float((a & b).sum() / max(1, (a | b).sum())))
    return ious


def kept_indices(video: Path) -> list[int]:
    """Source indices of the frames the video path kept (frame_000123 -> 123)."""
    return [int(name.split("_")[1]) for name in json.loads((video / "capture.json").read_text())["frames"]]


def aligned_scans(truth: Path, video: Path, out: Path) -> dict:
    """The true scans moved into the video capture's world by one similarity from the joints of
    the frames the video path kept."""
    true_joints, fitted = main_joints(truth)[kept_indices(video)], main_joints(video)
    scale, rotation, shift = similarity(true_joints.reshape(-1, 3), fitted.reshape(-1, 3))
    out.mkdir(parents=True, exist_ok=True)
    for scan in sorted((truth / "scans").glob("*.ply")):
        mesh = trimesh.load(scan, process=False)
        mesh.vertices = mesh.vertices @ (scale * rotation).T + shift
        mesh.export(out / scan.name)
    return {"scale": scale, "pa_mpjpe_mm": pa_mpjpe_mm(true_joints, fitted)}


def frame_aligned_scans(truth: Path, video: Path, out: Path) -> None:
    """The true scans moved into the video capture's world by one similarity per frame, from that
    frame's joints: what is left is the avatar's shape and the fit's articulation, not the frame's
    global placement (depth from a single view is off by centimetres)."""
    kept = kept_indices(video)
    true_joints, fitted = main_joints(truth)[kept], main_joints(video)
    out.mkdir(parents=True, exist_ok=True)
    for scan in sorted((truth / "scans").glob("*.ply")):
        index = int(scan.stem.split("_")[1])
        if index not in kept:
            continue
        slot = kept.index(index)
        scale, rotation, shift = similarity(true_joints[slot], fitted[slot])
        mesh = trimesh.load(scan, process=False)
        mesh.vertices = mesh.vertices @ (scale * rotation).T + shift
        mesh.export(out / scan.name)


def extra_evals(run: Path, truth: Path | None, args: argparse.Namespace) -> dict:
    """--extra-evals: image metrics after test-time pose refinement and, for a video run, geometry
    against per-frame aligned scans (reports beside the main one; reused with --reuse)."""
    row: dict = {}
    refined = run / "report-refined"
    if not (args.reuse and (refined / "metrics.json").is_file()):
        igavatar("eval", "--run-dir", str(run), "--out", str(refined), "--no-geometry", "--image-frames", "0",
                 "--image-scale", "0.5", "--refine-test-poses", "--seed", str(args.seed), "--device", "cpu")
    values = frame_values(json.loads((refined / "metrics.json").read_text()))
    row.update({f"refined_{key}": statistics.mean(values[key]) for key in IMAGE_KEYS if key in values})
    if truth is not None:
        aligned, report = run / "scans-frame-aligned", run / "report-frame-aligned"
        if not (args.reuse and (report / "metrics.json").is_file()):
            frame_aligned_scans(truth, run / "capture", aligned)
            igavatar("eval", "--run-dir", str(run), "--out", str(report), "--gt", str(aligned), "--no-images",
                     "--mesh-resolution", "256", "--iou-open-meshes", "--seed", str(args.seed), "--device", "cpu")
        values = frame_values(json.loads((report / "metrics.json").read_text()))
        row.update({f"frame_aligned_{key}": statistics.mean(values[key]) for key in GEOMETRY_KEYS if key in values})
    return row


def train_and_eval(run: Path, gt: Path, args: argparse.Namespace, extra: list[str] | tuple = ()) -> dict:
    report = run / "report"
    started = time.perf_counter()
    if args.reuse and (report / "metrics.json").is_file():
        return _report_row(report, None)
    igavatar("train", "--run-dir", str(run), "--preset", "cpu", "--steps", str(args.steps), "--seed", str(args.seed),
             "--device", "cpu", *args.train_args, *extra)
    train_s = time.perf_counter() - started
    igavatar("eval", "--run-dir", str(run), "--gt", str(gt), "--mesh-resolution", "256", "--image-frames", "0",
             "--image-scale", "0.5", "--iou-open-meshes", "--seed", str(args.seed), "--device", "cpu")
    return _report_row(report, train_s)


def frame_values(metrics: dict) -> dict[str, list[float]]:
    """metrics.json's per-frame values, by metric (frames without a value left out)."""
    values: dict[str, list[float]] = {}
    for record in metrics["frames"]:
        for key, value in record["values"].items():
            if value is not None:
                values.setdefault(key, []).append(value)
    return values


def write_results(tag: str, made: str, command: str, rows, text: str) -> None:
    """results/<tag>.json (commit, command, rows) and results/<tag>.md (the table)."""
    (RESULTS / f"{tag}.json").write_text(json.dumps({"commit": made, "command": command, "rows": rows}, indent=2))
    (RESULTS / f"{tag}.md").write_text(text)


def _report_row(report: Path, train_s: float | None) -> dict:
    metrics = json.loads((report / "metrics.json").read_text())
    values = frame_values(metrics)
    canonical = metrics.get("canonical") or {}
    limbs = canonical.get("limb_check")
    return {"train_s": train_s, "limbs_ok": None if limbs is None else limbs["passed"],
            **{key: statistics.mean(values[key]) for key in IMAGE_KEYS + GEOMETRY_KEYS if key in values}}


def video_summary(capture: Path) -> dict:
    """The video path's fit residual and seconds a frame, from the capture it wrote."""
    manifest = json.loads((capture / "manifest.json").read_text())
    frames = manifest["data"]["video"]["kept_frames"]
    return {"fit_residual_px": manifest["data"]["video"]["fit"]["mean_residual_px"],
            "seconds_per_frame": manifest["timings"]["total_s"] / frames}


def run_subject(subject: str, args: argparse.Namespace) -> dict:
    base = args.run_dir / subject
    base.mkdir(parents=True, exist_ok=True)
    synth = base / "synth" if args.reuse and (base / "synth" / "manifest.json").is_file() else \
        synth_subject(base, subject, args.frames)
    clip = base / "clip.mp4"
    names = write_clip(synth, clip)
    truth = base / "truth" / "capture"
    truth_capture(synth, names, truth)
    meta = json.loads((synth / "capture.json").read_text())
    labels = [str(v) for v in np.load(synth / "poses.npz")["phenotype_labels"]]
    from igavatar.body.anny_body import AnnyBody, load_anny

    body = AnnyBody(load_anny(), dict(zip(labels, np.load(synth / "poses.npz")["phenotype_values"].tolist())))
    height = float(body.rest_vertices[:, 2].max() - body.rest_vertices[:, 2].min())
    focal = float(np.load(synth / "cameras.npz")["K"][0, 0])
    row: dict = {"subject": subject, "frames": len(names), "true_height_m": height, "true_focal_px": focal,
                 "garment": meta["subject"]["garment"]}
    video_flags = {"video-true": ["--height", f"{height:.4f}", "--focal", f"{focal:.3f}"], "video-default": []}
    for variant in args.variants.split(","):
        run = base / variant
        if variant == "truth":
            if not (args.reuse and (run / "report" / "metrics.json").is_file()):
                igavatar("preprocess", "--run-dir", str(run), "--force")
            gt, extra = truth / "scans", {}
        else:
            started, video_s = time.perf_counter(), None
            if not (args.reuse and (run / "report" / "metrics.json").is_file()):
                if variant in REFINED:  # no preprocess of its own: no preprocess_s
                    copy_video_dataset(base / variant.removesuffix("-refine"), run)
                else:
                    igavatar("preprocess", "--video", str(clip), "--run-dir", str(run), "--force",
                             "--test-every", str(TEST_EVERY), *video_flags[variant])
                    video_s = time.perf_counter() - started
            capture = run / "capture"
            summary = {"video": video_summary(capture)}
            ious = mask_iou(truth, capture, [f"frame_{i:06d}" for i in kept_indices(capture)])
            alignment = aligned_scans(truth, capture, run / "scans-aligned")
            gt = run / "scans-aligned"
            extra = {"mask_iou": statistics.mean(ious), "mask_iou_min": min(ious),
                     "pa_mpjpe_mm": statistics.mean(alignment["pa_mpjpe_mm"]),
                     "pa_mpjpe_mm_max": max(alignment["pa_mpjpe_mm"]), "alignment_scale": alignment["scale"],
                     "fit_residual_px": summary["video"]["fit_residual_px"],
                     "video_s_per_frame": summary["video"]["seconds_per_frame"], "preprocess_s": video_s}
        refine = ["--refine-poses"] if variant in REFINED else []
        row[variant] = {**extra, **train_and_eval(run, gt, args, extra=refine)}
        if args.extra_evals:
            row[variant].update(extra_evals(run, None if variant == "truth" else truth, args))
        print(json.dumps({subject: {variant: row[variant]}}), flush=True)
    return row


def copy_video_dataset(source: Path, run: Path) -> None:
    """`source`'s video capture and dataset copied into `run`, so that a refined variant trains on
    exactly the poses and masks of the variant it refines."""
    if run.exists():
        shutil.rmtree(run)
    run.mkdir(parents=True)
    for part in ("capture", "dataset"):
        shutil.copytree(source / part, run / part)


def noisy_capture(truth: Path, out: Path, degrees: float, root_m: float, seed: int) -> None:
    """`truth` with every training frame's fitted bones (and root) turned by `degrees` about a
    random axis and its root moved `root_m` in a random direction; test frames keep their poses."""
    import torch

    from igavatar.body.anny_body import AnnyBody, load_anny
    from igavatar.body.rotations import axis_angle_to_matrix
    from igavatar.capture.video_fit import FREE_BONES

    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(truth, out)
    poses = dict(np.load(truth / "poses.npz"))
    meta = json.loads((truth / "capture.json").read_text())
    labels = [str(v) for v in poses["phenotype_labels"]]
    body = AnnyBody(load_anny(), dict(zip(labels, poses["phenotype_values"].tolist())))
    local, translation = body.local_rotations_from_pose_parameters(torch.as_tensor(poses["pose_parameters"]))
    rng = np.random.default_rng(seed)
    joints = [0] + [body.skeleton.index(b) for b in FREE_BONES]
    train = [i for i, name in enumerate(meta["frames"]) if name in set(meta["splits"]["train"])]
    for i in train:
        axes = rng.normal(size=(len(joints), 3))
        axes /= np.linalg.norm(axes, axis=1, keepdims=True)
        turn = axis_angle_to_matrix(torch.as_tensor(axes * np.radians(degrees), dtype=local.dtype))
        local[i, joints] = local[i, joints] @ turn
        direction = rng.normal(size=3)
        translation[i] += torch.as_tensor(root_m * direction / np.linalg.norm(direction), dtype=translation.dtype)
    poses["pose_parameters"] = body.pose_parameters_from_local_rotations(local, translation).numpy()
    np.savez(out / "poses.npz", **poses)


def run_noise(subject: str, args: argparse.Namespace) -> dict:
    """Exact poses against poses with noise on the training frames, trained with and without refinement."""
    base = args.run_dir / subject
    truth = base / "truth" / "capture"
    row: dict = {"subject": subject, "truth": train_and_eval(base / "truth", truth / "scans", args)}
    for degrees in args.noise:
        capture = base / f"noise{degrees:g}" / "capture"
        noisy_capture(truth, capture, degrees, 0.02, seed=args.seed + 100)
        for refine in (False, True):
            name = f"noise{degrees:g}" + ("-refine" if refine else "")
            run = base / name
            if not (args.reuse and (run / "report" / "metrics.json").is_file()):
                igavatar("preprocess", "--capture", str(capture), "--run-dir", str(run), "--force")
            flag = "--refine-poses" if refine else "--no-refine-poses"
            row[name] = train_and_eval(run, truth / "scans", args, extra=[flag])
            print(json.dumps({subject: {name: row[name]}}), flush=True)
    return row


def noise_markdown(rows: list[dict], args: argparse.Namespace, command: str, made: str) -> str:
    lines = ["# Pose noise on the training frames, trained with and without pose refinement", "",
             f"Commit `{made}`; command: `{command}`. CPU (2 cores), `--preset cpu --steps {args.steps}`, seed {args.seed}.",
             "Noise: each training frame's root and 15 fitted bones turned by the angle about a random axis, the root moved "
             "2 cm; held-out frames keep their exact poses. Geometry on the held-out frames against the scans.", "",
             "| subject | variant | CD-L1 mm | vs exact | IoU | NC surf | PSNR box | SSIM box |", "|---|---|---|---|---|---|---|---|"]
    for row in rows:
        exact = row["truth"].get("chamfer_l1_surface_mm")
        for name, v in row.items():
            if name == "subject":
                continue
            cd = v.get("chamfer_l1_surface_mm")
            ratio = "-" if cd is None or not exact else f"{100 * (cd / exact - 1):+.0f} %"
            lines.append(f"| {row['subject']} | {name} | {number(cd)} | {ratio} | {number(v.get('volumetric_iou'), 3)} | "
                         f"{number(v.get('normal_consistency_surface'), 3)} | {number(v.get('psnr_mask_bbox_db'))} | "
                         f"{number(v.get('ssim_mask_bbox'), 3)} |")
    return "\n".join(lines) + "\n"


def number(value, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def markdown(rows: list[dict], args: argparse.Namespace, command: str, made: str) -> str:
    lines = [f"# Video path against true poses (synthetic turns, {args.frames} frames, 512 px)", "",
             f"Commit `{made}`; command: `{command}`. CPU (2 cores), `--preset cpu --steps {args.steps}`, seed {args.seed}.",
             f"Held out: every {TEST_EVERY}th frame. Image metrics at half the dataset's size. Alignment: see the script's docstring.",
             "", "| subject | variant | mask IoU | PA-MPJPE mm | fit px | s/frame | PSNR box | SSIM box | PSNR | "
             "CD-L1 mm | IoU | NC surf | limbs |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    extra = [(row["subject"], variant, row[variant]) for row in rows for variant in ALL_VARIANTS
             if variant in row and "refined_psnr_mask_bbox_db" in row[variant]]
    for row in rows:
        for variant in ALL_VARIANTS:
            if variant not in row:
                continue
            v = row[variant]
            lines.append(f"| {row['subject']} | {variant} | {number(v.get('mask_iou'), 3)} | {number(v.get('pa_mpjpe_mm'), 1)} | "
                         f"{number(v.get('fit_residual_px'))} | {number(v.get('video_s_per_frame'), 3)} | "
                         f"{number(v.get('psnr_mask_bbox_db'))} | {number(v.get('ssim_mask_bbox'), 3)} | "
                         f"{number(v.get('psnr_full_db'))} | {number(v.get('chamfer_l1_surface_mm'))} | "
                         f"{number(v.get('volumetric_iou'), 3)} | {number(v.get('normal_consistency_surface'), 3)} | "
                         f"{v.get('limbs_ok')} |")
    if extra:
        lines += ["", "With test-time pose refinement (`eval --refine-test-poses`, image metrics only) and, for video "
                  "runs, geometry against scans aligned by one similarity per frame from its joints:", "",
                  "| subject | variant | PSNR box refined | SSIM box refined | PSNR refined | CD-L1 mm frame-aligned | "
                  "IoU frame-aligned | NC surf frame-aligned |", "|---|---|---|---|---|---|---|---|"]
        for subject, variant, v in extra:
            lines.append(f"| {subject} | {variant} | {number(v.get('refined_psnr_mask_bbox_db'))} | "
                         f"{number(v.get('refined_ssim_mask_bbox'), 3)} | {number(v.get('refined_psnr_full_db'))} | "
                         f"{number(v.get('frame_aligned_chamfer_l1_surface_mm'))} | "
                         f"{number(v.get('frame_aligned_volumetric_iou'), 3)} | "
                         f"{number(v.get('frame_aligned_normal_consistency_surface'), 3)} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run-dir", type=Path, required=True)
    parser.add_argument("--subjects", default=",".join(SUBJECTS))
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--steps", type=int, default=800)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--train-args", nargs="*", default=[], help="extra `train` options for every variant")
    parser.add_argument("--tag", default="video-path")
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--write-results", action="store_true")
    parser.add_argument("--reuse", action="store_true", help="keep variants already trained and evaluated in RUN")
    parser.add_argument("--extra-evals", action="store_true",
                        help="also eval with --refine-test-poses, and video runs against per-frame aligned scans")
    parser.add_argument("--noise", type=lambda text: [float(v) for v in text.split(",")], default=[],
                        help="degrees, e.g. 5,10: the pose-noise study on the truth captures of a previous run instead")
    args = parser.parse_args()
    made, command = commit(), "python " + " ".join([str(Path(sys.argv[0]).relative_to(ROOT)
                                                       if Path(sys.argv[0]).is_absolute() else sys.argv[0]), *sys.argv[1:]])
    if args.noise:
        rows = [run_noise(subject, args) for subject in args.subjects.split(",")]
        text = noise_markdown(rows, args, command, made)
    else:
        rows = [run_subject(subject, args) for subject in args.subjects.split(",")]
        text = markdown(rows, args, command, made)
    print(text)
    if args.write_results:
        write_results(args.tag, made, command, rows, text)


if __name__ == "__main__":
    main()
