"""The training poses' fit to the masks alone (igavatar.training.pose_silhouette), no training: how
far its poses land from the true ones, for each weight of its temporal term.

    python tests/benchmarks/pose_fit_probe.py --truth TRUTH_DATASET --dataset NOISY_DATASET --smoothness 0,0.3
    python tests/benchmarks/pose_fit_probe.py --truth D --dataset D --split test --smoothness 0,0.3   # exact poses: the drag

Prints, per weight, the mean distance (mm) of all the posed joints and of the refined (major) ones
to the truth dataset's, and the fit's report (frames kept, neighbour triplets). The shape prior is
the dataset's template.ply, the skinning weights those of an untrained avatar of the `cpu` preset
(the same grid a run starts from). --split test fits the test frames instead of the training ones
(the synthetic captures' walk, arm raise and squat).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
import torch
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from igavatar.avatar.dataset import PRIOR_FILE, read_dataset, training_data  # noqa: E402
from igavatar.avatar.model import build_avatar  # noqa: E402
from igavatar.training.config import preset  # noqa: E402
from igavatar.training.pose_refine import PoseRefiner  # noqa: E402
from igavatar.training.pose_silhouette import fit_poses_to_masks  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--truth", type=Path, required=True, help="dataset with the true poses")
    parser.add_argument("--dataset", type=Path, required=True, help="the same frames with the poses to fit")
    parser.add_argument("--smoothness", default="0,0.3", help="pose_silhouette_smoothness values, comma-separated")
    parser.add_argument("--split", default="train", help="the frames to fit: train or test")
    parser.add_argument("--steps", type=int, default=None, help="pose_silhouette_steps (default: the preset's)")
    args = parser.parse_args()
    truth = training_data(read_dataset(args.truth, check_hashes=False))
    dataset = read_dataset(args.dataset, check_hashes=False)
    data, subject = training_data(dataset), dataset.subject
    names = list(data.frame_names)
    split = json.loads((args.dataset / "manifest.json").read_text())["data"]["splits"][args.split]
    frames = torch.tensor([names.index(name) for name in split])
    data = dataclasses.replace(data, train_indices=frames)
    config = dataclasses.replace(preset("cpu"), refine_poses=True)
    if args.steps is not None:
        config = dataclasses.replace(config, pose_silhouette_steps=args.steps)
    avatar = build_avatar(config, subject, dataset.pose_dim)
    prior = np.asarray(trimesh.load(args.dataset / PRIOR_FILE, process=False).vertices)
    major = np.union1d([0], subject.init_bones)
    joints = torch.as_tensor(subject.canonical_joints, dtype=torch.float64)

    def error(transforms: torch.Tensor) -> str:
        def posed(t):
            return (t[..., :3, :3] @ joints[None, :, :, None])[..., 0] + t[..., :3, 3]
        distance = (posed(transforms.double()) - posed(truth.bone_transforms[frames].double())).norm(dim=-1)
        return f"all {1000 * float(distance.mean()):.1f} mm, major {1000 * float(distance[:, major].mean()):.1f} mm"

    print(f"{args.split} frames {len(frames)}; the poses given: {error(data.bone_transforms[frames])}")
    for weight in [float(v) for v in args.smoothness.split(",")]:
        refiner = PoseRefiner(data.bone_transforms, subject.parents, subject.rest_joints, subject.canonical_rotations,
                              frames, major)
        fit = fit_poses_to_masks(refiner, data, avatar.deformer, prior,
                                 dataclasses.replace(config, pose_silhouette_smoothness=weight))
        report = {k: round(v, 3) if isinstance(v, float) else v for k, v in fit.report.items()}
        print(f"smoothness {weight:g}: {error(refiner.all_bone_transforms())}  {report}", flush=True)


if __name__ == "__main__":
    main()
