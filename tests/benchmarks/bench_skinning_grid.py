"""How much error a skinning-weight grid alone puts on a perfect surface (no training).

Two tables per grid, from a synthetic capture's true clothed surface in the canonical pose:

1. Posing: the surface posed into every test frame by the grid's weights (sampled at its vertices)
   against its own per-vertex weights (which is how the scans were made): the floor that grid sets
   on posed geometry, mean / p95 vertex error in mm per motion.
2. Root finding: the surface posed by its own weights into every 10th training frame and root-found
   back with the grid (the `cpu` preset's deformer with the subject's start bones, ranked by
   part): per body part, the share of points with no root at their true canonical place ("missed":
   training can never put that surface where it belongs) and with a second valid root elsewhere
   ("spurious": training may put it there instead).

    python tests/benchmarks/bench_skinning_grid.py --run RUN_DIR/plain-heavy --grids p30,p15,s1
    (RUN_DIR/<subject> holds capture/ and dataset/ as bench_quality.py makes them;
     pN = inverse distance + N blur passes, sA = --weight-spread A over the default 15 passes)
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from igavatar.body.skeleton import linear_blend_skinning
from igavatar.avatar.canonical_report import canonical_truth
from igavatar.avatar.dataset import read_dataset
from igavatar.capture.importers import detect_layout, read_layout
from igavatar.capture.subject import canonicalize, subject_from_capture
from igavatar.metrics.canonical import REST_SURFACE_FILE
from igavatar.model.deformer import FastSnarfDeformer, init_parts
from igavatar.skinning.grid import build_skinning_grid, sample_grid
from igavatar.training.config import preset

#: Body parts of the root-finding table, by the prefix of an Anny bone name.
PARTS = {"foot": ("toe", "foot"), "shin": ("lowerleg",), "thigh": ("upperleg",), "hand": ("finger", "metacarpal", "wrist")}


def _posed(weights: torch.Tensor, transforms: np.ndarray, x: torch.Tensor) -> np.ndarray:
    """(V, J) weights, (J, 4, 4) transforms, (V, 3) points (float64) -> (V, 3) posed points."""
    return linear_blend_skinning(x, weights, torch.from_numpy(transforms).double()).numpy()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, required=True, help="a subject's run dir (capture/ and dataset/)")
    parser.add_argument("--grids", default="p30,p15,s1", help="comma-separated grids: pN or sA")
    args = parser.parse_args()
    dataset = read_dataset(args.run / "dataset")
    capture_dir = args.run / "capture"
    subject = subject_from_capture(read_layout(capture_dir, detect_layout(capture_dir)), None, None, None)
    template = canonicalize(subject).template_vertices
    truth = canonical_truth(capture_dir, dataset.subject)
    if template is None or truth is None:
        raise SystemExit(f"{args.run}: needs a body-model template and {REST_SURFACE_FILE} (a synthetic capture)")
    with np.load(capture_dir / REST_SURFACE_FILE) as rest:
        own = np.zeros((len(truth[0]), dataset.subject.n_joints))
        np.put_along_axis(own, rest["weights_index"], rest["weights_value"], axis=1)
        dominant = rest["weights_index"][np.arange(len(own)), rest["weights_value"].argmax(axis=1)]
    own = torch.from_numpy(own / own.sum(axis=1, keepdims=True))
    truth_v = torch.from_numpy(truth[0])
    names = dataset.subject.joint_names
    part_of = np.array([next((part for part, prefixes in PARTS.items() if names[j].startswith(prefixes)), "other")
                        for j in dominant])
    box_min = torch.from_numpy(dataset.subject.grid_box_min).float()
    box_max = torch.from_numpy(dataset.subject.grid_box_max).float()
    resolution = dataset.subject.skinning_grid.shape[1:]
    frames = dataset.frames()
    motions: dict[str, list[int]] = {}
    for i, name in enumerate(frames.names):
        if name.startswith("test_"):
            motions.setdefault(name.removeprefix("test_").rsplit("_", 1)[0], []).append(i)
    train = [i for i, name in enumerate(frames.names) if name.startswith("train_")][::10]
    # The surface posed by its own weights, once per frame (the reference every grid is held to).
    truth_posed = {i: _posed(own, frames.bone_transforms[i], truth_v) for ids in [*motions.values(), train] for i in ids}
    grids = {}
    for spec in args.grids.split(","):
        kind, value = spec[0], float(spec[1:])
        grids[spec] = build_skinning_grid(template, subject.template_weights, box_min, box_max, resolution,
                                          smoothing_iterations=int(value) if kind == "p" else 15,
                                          spread=value if kind == "s" else None)
    print("1. posing error of the true surface (mean / p95 mm)")
    print(f"{'grid':8s}", "  ".join(f"{m:>16s}" for m in sorted(motions)))
    for spec, grid in grids.items():
        weights = sample_grid(grid, box_min, box_max, truth_v.float()).double()
        cells = []
        for motion in sorted(motions):
            error = np.concatenate([
                np.linalg.norm(_posed(weights, frames.bone_transforms[i], truth_v) - truth_posed[i], axis=1)
                for i in motions[motion]
            ]) * 1e3
            cells.append(f"{error.mean():7.2f} / {np.percentile(error, 95):5.1f}")
        print(f"{spec:8s}", "  ".join(f"{c:>16s}" for c in cells), flush=True)
    starts = tuple(int(b) for b in dataset.subject.init_bones)
    config = replace(preset("cpu").avatar.deformer, init_bones=starts, init_parts=init_parts(dataset.subject.parents, starts))
    print(f"\n2. root finding of the true surface in {len(train)} training frames (share of points: missed / spurious)")
    print(f"{'grid':8s}", "  ".join(f"{part:>13s}" for part in [*PARTS, "other"]))
    for spec, grid in grids.items():
        deformer = FastSnarfDeformer(grid, box_min, box_max, config)
        missed, spurious = [], []
        for i in train:
            frame = deformer.prepare(torch.from_numpy(frames.bone_transforms[i]).float())
            with torch.no_grad():
                candidates, valid = deformer.canonicalize(torch.from_numpy(truth_posed[i]).float(), frame)
            error = np.linalg.norm(candidates.numpy() - truth[0][:, None], axis=-1)
            valid = valid.numpy()
            missed.append(~(valid & (error < 0.01)).any(axis=1))
            spurious.append((valid & (error > 0.01)).any(axis=1))
        missed, spurious = np.mean(missed, axis=0), np.mean(spurious, axis=0)
        cells = [f"{missed[part_of == p].mean():.2f} / {spurious[part_of == p].mean():.2f}" for p in [*PARTS, "other"]]
        print(f"{spec:8s}", "  ".join(f"{c:>13s}" for c in cells), flush=True)


if __name__ == "__main__":
    main()
