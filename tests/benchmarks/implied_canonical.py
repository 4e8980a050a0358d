"""The canonical shape a dataset's skinning weights imply, and how close training could get to the truth.

The true clothed surface is posed into every Nth training frame by its own per-vertex weights (as
the images were made) and root-found back with the dataset's weight grid (Fast-SNARF, the `cpu`
preset's deformer), taking the root nearest the truth. Where the grid's weights differ from the
truth's, that root differs from the true canonical point; the IoU of the implied shape against the
truth is the most training can reach with these weights. The share of the implied shape's inside
that the grid forward-skins outside the posed truth tells whether that shape is consistent with the
training masks (near 0: it is).

    python tests/benchmarks/implied_canonical.py --run RUN_DIR/checker-dress [--every 10]
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
import trimesh

from igavatar.avatar.canonical_report import canonical_truth
from igavatar.avatar.dataset import read_dataset
from igavatar.body.skeleton import linear_blend_skinning
from igavatar.metrics.canonical import REST_SURFACE_FILE
from igavatar.metrics.geometry import contains_points, volumetric_iou
from igavatar.model.deformer import FastSnarfDeformer, init_parts
from igavatar.skinning.grid import sample_grid
from igavatar.training.config import preset


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, required=True, help="a subject's run dir (capture/ and dataset/)")
    parser.add_argument("--every", type=int, default=10, help="use every Nth training frame")
    args = parser.parse_args()
    dataset = read_dataset(args.run / "dataset")
    subject = dataset.subject
    truth = canonical_truth(args.run / "capture", subject)
    if truth is None:
        raise SystemExit(f"{args.run}: needs {REST_SURFACE_FILE} on the dataset's skeleton (a synthetic capture)")
    truth_v, truth_f = truth
    with np.load(args.run / "capture" / REST_SURFACE_FILE) as rest:
        own = np.zeros((len(truth_v), subject.n_joints))
        np.put_along_axis(own, rest["weights_index"], rest["weights_value"], axis=1)
    own = torch.from_numpy(own / own.sum(axis=1, keepdims=True))
    box_min, box_max = torch.from_numpy(subject.grid_box_min).float(), torch.from_numpy(subject.grid_box_max).float()
    grid = torch.as_tensor(subject.skinning_grid).float()
    starts = tuple(int(b) for b in subject.init_bones)
    config = replace(preset("cpu").avatar.deformer, init_bones=starts, init_parts=init_parts(subject.parents, starts))
    deformer = FastSnarfDeformer(grid, box_min, box_max, config)
    frames = dataset.frames()
    train = [i for i, name in enumerate(frames.names) if name.startswith("train_")][:: args.every]
    implied, posed_truth = [], {}
    for i in train:
        transforms = torch.from_numpy(frames.bone_transforms[i]).double()
        posed = linear_blend_skinning(torch.from_numpy(truth_v), own, transforms)
        posed_truth[i] = posed.numpy()
        with torch.no_grad():
            candidates, valid = deformer.canonicalize(posed.float(), deformer.prepare(transforms.float()))
        error = np.linalg.norm(candidates.numpy() - truth_v[:, None], axis=-1)
        error[~valid.numpy()] = np.inf
        nearest = candidates.numpy()[np.arange(len(truth_v)), error.argmin(axis=1)]
        missed = ~np.isfinite(error.min(axis=1))
        nearest[missed] = truth_v[missed]  # no root at all: counted as right (the table says how many)
        implied.append(nearest)
        found = error.min(axis=1)[~missed] * 1e3
        print(f"{frames.names[i]}: root nearest the truth {found.mean():.2f} mm mean, {np.percentile(found, 95):.1f} p95; "
              f"no valid root {missed.mean():.3f}", flush=True)
    implied_v = np.mean(implied, axis=0)
    iou = volumetric_iou((implied_v, truth_f), (truth_v, truth_f), n_points=200_000, require_watertight=False)["iou"]
    print(f"implied canonical shape (mean over {len(train)} frames): IoU {iou:.3f} against the truth")
    implied_mesh = trimesh.Trimesh(implied_v, truth_f, process=False)
    rng = np.random.default_rng(0)
    x = rng.uniform(implied_v.min(axis=0), implied_v.max(axis=0), size=(400_000, 3))
    x = x[contains_points(implied_mesh, x, watertight=True)]
    weights = sample_grid(grid, box_min, box_max, torch.from_numpy(x).float()).double()
    outside = []
    for i in train:
        x_posed = linear_blend_skinning(torch.from_numpy(x), weights, torch.from_numpy(frames.bone_transforms[i]).double())
        posed_mesh = trimesh.Trimesh(posed_truth[i], truth_f, process=False)
        outside.append(float((~contains_points(posed_mesh, x_posed.numpy(), watertight=True)).mean()))
    print(f"its inside forward-skinned by the grid: {np.mean(outside):.4f} lands outside the posed truth")


if __name__ == "__main__":
    main()
