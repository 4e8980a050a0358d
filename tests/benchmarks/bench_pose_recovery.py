"""Can a model's renders pull a perturbed pose back? A probe of pose refinement, frame by frame.

    python tests/benchmarks/bench_pose_recovery.py --model M --noisy NOISY/dataset --truth TRUTH/dataset \\
        --frames 0,10,20 --steps 120 --lr 0.003 [--name pose-recovery-sharp]

For each chosen training frame of the noisy dataset (the same frames, with poses perturbed, as the
truth dataset), it runs the held-out refinement (igavatar.training.held_out_poses: the model
frozen, the frame's root and major bones corrected against its image and mask) starting from the
noisy pose, and measures the 14 main joints (shoulders, elbows, wrists, hips, knees, ankles, neck,
head) against the true pose, before and after:
- 3D: mean joint distance (mm) in the world;
- centred: the same after removing each set's mean (depth and root shift, which one view barely
  sees, taken out);
- 2D: mean reprojection distance (px) in the frame's camera.
The model decides the answer: one trained on the true poses (a sharp avatar), one trained on the
noisy poses (the blur that training-time refinement starts from), or one right after shape
initialisation (`train --steps 1`: the body template). Writes NAME.md / NAME.json with the commit.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "benchmarks"))
from bench_video import MAIN_JOINTS  # noqa: E402
from provenance import commit  # noqa: E402

from igavatar.avatar.dataset import read_dataset  # noqa: E402
from igavatar.avatar.model import load_model  # noqa: E402
from igavatar.geometry.projection import project_points  # noqa: E402
from igavatar.training.held_out_poses import HeldOutFrame, HeldOutPoseConfig, refine_frame_pose  # noqa: E402

RESULTS = ROOT / "tests" / "benchmarks" / "results"


def joint_errors(truth: np.ndarray, pose: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> dict[str, float]:
    """3D, centred 3D (mm) and 2D (px) mean distances of joints (J, 3) to the true ones."""
    centred = (pose - pose.mean(0)) - (truth - truth.mean(0))
    uv_pose, _ = project_points(K, w2c, pose)
    uv_truth, _ = project_points(K, w2c, truth)
    return {"mm": float(1000 * np.linalg.norm(pose - truth, axis=1).mean()),
            "centred_mm": float(1000 * np.linalg.norm(centred, axis=1).mean()),
            "px": float(np.linalg.norm(uv_pose - uv_truth, axis=1).mean())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--noisy", type=Path, required=True, help="dataset with perturbed training poses")
    parser.add_argument("--truth", type=Path, required=True, help="the same frames with their true poses")
    parser.add_argument("--frames", default="0,10,20", help="indices into the datasets' frames")
    parser.add_argument("--steps", type=int, default=120)
    parser.add_argument("--lr", type=float, default=0.003)
    parser.add_argument("--prior", type=float, default=0.001)
    parser.add_argument("--name", default=None, help="write results/NAME.md and .json")
    args = parser.parse_args()
    model = load_model(args.model)
    noisy_dataset = read_dataset(args.noisy)
    noisy, truth = noisy_dataset.frames(), read_dataset(args.truth).frames()
    subject = model.subject
    main_joints = [list(subject.joint_names).index(n) for n in MAIN_JOINTS]
    canonical = np.concatenate((subject.canonical_joints, np.ones((len(subject.joint_names), 1))), axis=1)

    def joints(transforms: np.ndarray) -> np.ndarray:
        return np.einsum("jab,jb->ja", transforms, canonical)[main_joints, :3]

    rows = []
    for i in [int(v) for v in args.frames.split(",")]:
        name = noisy.names[i]
        if truth.names[i] != name:
            raise SystemExit(f"frame {i}: {name} in the noisy dataset, {truth.names[i]} in the truth")
        image, mask = noisy_dataset.image_and_mask(name)
        frame = HeldOutFrame(image, mask, noisy.K[i], noisy.w2c[i], noisy.bone_transforms[i], noisy.pose_condition[i],
                             noisy.posed_boxes[i])
        tick = time.perf_counter()
        refined = refine_frame_pose(model.avatar, model.canonical_grid, subject, frame,
                                    HeldOutPoseConfig(steps=args.steps, learning_rate=args.lr, prior_weight=args.prior),
                                    model.config, seed=0)
        seconds = time.perf_counter() - tick
        true_joints = joints(truth.bone_transforms[i])
        before = joint_errors(true_joints, joints(noisy.bone_transforms[i]), noisy.K[i], noisy.w2c[i])
        after = joint_errors(true_joints, joints(refined.bone_transforms), noisy.K[i], noisy.w2c[i])
        rows.append({"frame": name, "kept": refined.kept, "rotation_deg": refined.rotation_deg, "root_mm": refined.root_mm,
                     "seconds": seconds, **{f"before_{k}": v for k, v in before.items()},
                     **{f"after_{k}": v for k, v in after.items()}})
        print(json.dumps(rows[-1]), flush=True)
    keys = ("mm", "centred_mm", "px")
    means = {f"{when}_{k}": float(np.mean([r[f"{when}_{k}"] for r in rows])) for when in ("before", "after") for k in keys}
    command = "python tests/benchmarks/bench_pose_recovery.py " + " ".join(sys.argv[1:])
    print(json.dumps(means))
    if args.name:
        lines = [f"# Pose recovery probe: {args.name}", "", f"Commit: `{commit()}`. Command:", "", f"    {command}", "",
                 f"Model `{args.model}`; {args.steps} Adam steps at {args.lr}, prior {args.prior}.", "",
                 "| frame | kept | 3D mm before -> after | centred mm | 2D px | correction deg / root mm | s |",
                 "|---|---|---|---|---|---|---|"]
        for r in rows:
            lines.append(f"| {r['frame']} | {r['kept']} | {r['before_mm']:.1f} -> {r['after_mm']:.1f} | "
                         f"{r['before_centred_mm']:.1f} -> {r['after_centred_mm']:.1f} | {r['before_px']:.1f} -> "
                         f"{r['after_px']:.1f} | {r['rotation_deg']:.2f} / {r['root_mm']:.1f} | {r['seconds']:.1f} |")
        lines.append(f"| mean | | {means['before_mm']:.1f} -> {means['after_mm']:.1f} | {means['before_centred_mm']:.1f} -> "
                     f"{means['after_centred_mm']:.1f} | {means['before_px']:.1f} -> {means['after_px']:.1f} | | |")
        (RESULTS / f"{args.name}.md").write_text("\n".join(lines) + "\n")
        (RESULTS / f"{args.name}.json").write_text(json.dumps({"commit": commit(), "command": command, "rows": rows,
                                                               "means": means}, indent=2) + "\n")


if __name__ == "__main__":
    main()
