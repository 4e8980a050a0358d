"""Which rule of the visual-hull prior keeps or drops the cells inside and outside the true surface.

Runs `preprocess --shape-prior visual-hull` on a synthetic capture (into a temporary folder), with
`hull_prior_mesh` wrapped so that its inputs are kept, then re-applies each rule to the same grid
and counts, against the capture's true canonical surface (`ground_truth/clothed_rest.npz`):
cells inside the truth that a rule drops (lost shape) and cells more than one cell outside it
that the rules keep (webs). The walled-in rule's re-admissions are listed apart.

    python tests/benchmarks/hull_rules.py --capture RUN_DIR/checker-dress/capture
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

import numpy as np
import torch
import trimesh

import igavatar.capture.visual_hull as visual_hull
import stages.preprocess as preprocess
from igavatar.avatar.canonical_report import canonical_truth
from igavatar.avatar.dataset import read_dataset
from igavatar.capture.ghost_limbs import misplaced_votes
from igavatar.metrics.geometry import closest_points_on_mesh, contains_points


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--capture", type=Path, required=True, help="a synthetic capture (igavatar synth)")
    args = parser.parse_args()
    calls = []
    original = preprocess.hull_prior_mesh

    def recording(box, skin, views, **kwargs):
        calls.append((box, skin, views, kwargs))
        return original(box, skin, views, **kwargs)

    # The benchmark needs the preprocess stage's own skinning and views, so it listens in on the call.
    preprocess.hull_prior_mesh = recording
    with tempfile.TemporaryDirectory() as tmp:
        preprocess.run_preprocess(preprocess.PreprocessOptions(capture=args.capture, out=Path(tmp) / "dataset",
                                                               shape_prior="visual-hull"))
        subject = read_dataset(Path(tmp) / "dataset").subject
    truth = canonical_truth(args.capture, subject)
    if truth is None:
        raise SystemExit(f"{args.capture}: no ground_truth/clothed_rest.npz on this skeleton (a synthetic capture is needed)")
    box, skin, views, kwargs = calls[0]
    cell = kwargs.get("cell_size", 0.02)
    points, shape = visual_hull.grid_points(box[0], box[1], cell)
    spacing = visual_hull.grid_spacing(box[0], box[1], shape)
    votes = visual_hull.vote_masks(points, skin, views, grid=(shape, spacing))
    n = len(views.frames)
    free = visual_hull.free_points(votes.seen, votes.inside)
    crushed = votes.collapsed > 0.5 * n
    seen = votes.seen >= max(1, math.ceil(0.5 * n))
    ghost = torch.zeros_like(free)
    candidates = torch.nonzero(~free & seen).squeeze(1)
    test = kwargs["ghost_test"]
    misplaced = misplaced_votes(points[candidates], test.weights(points[candidates]), skin, views.frames, test.bones)
    ghost[candidates[misplaced > 0.5 * n]] = True
    kept = (~free & ~crushed & ~ghost & seen).reshape(shape).numpy()
    walled = visual_hull.enclosed_cells(kept, (crushed & ~free & ~ghost & seen).reshape(shape).numpy()).reshape(-1)

    x = points.numpy().astype(np.float64)
    mesh = trimesh.Trimesh(*truth, process=False)
    inside = contains_points(mesh, x, watertight=True)
    far = ~inside & (closest_points_on_mesh(x, *truth)[1] > cell)
    print(f"{args.capture}: {n} views, {len(x)} cells of {cell * 100:.0f} cm, {int(inside.sum())} inside the truth")
    print(f"{'rule':22s} {'inside truth':>13s} {'> 1 cell outside':>17s}")
    for name, dropped in (("free (masks)", free), ("crushed", crushed & ~free), ("ghost limb", ghost & ~free & ~crushed),
                          ("unseen", ~seen & ~free)):
        d = dropped.numpy()
        print(f"drops: {name:15s} {int((d & inside).sum()):13d} {int((d & far).sum()):17d}")
    print(f"re-admits: walled in    {int((walled & inside).sum()):10d} {int((walled & far).sum()):17d}")
    final = kept.reshape(-1) | walled
    print(f"kept in the end         {int((final & inside).sum()):10d} {int((final & far).sum()):17d}")


if __name__ == "__main__":
    main()
