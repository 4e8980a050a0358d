"""Which rule of the visual-hull prior keeps or drops the cells inside and outside the true surface.

Runs `preprocess --shape-prior visual-hull` on a synthetic capture (into a temporary folder), with
`hull_prior_mesh` wrapped so that the rules' verdicts it meshes (`HullCells`) are kept, and counts,
against the capture's true canonical surface (`ground_truth/clothed_rest.npz`):
cells inside the truth that a rule drops (lost shape) and cells more than one cell outside it
that the rules keep (webs). The walled-in rule's re-admissions are listed apart.

    python tests/benchmarks/hull_rules.py --capture RUN_DIR/checker-dress/capture
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import trimesh

import stages.preprocess as preprocess
import igavatar.capture.shape_prior as shape_prior
from igavatar.avatar.canonical_report import canonical_truth
from igavatar.avatar.dataset import read_dataset
from igavatar.metrics.geometry import closest_points_on_mesh, contains_points


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--capture", type=Path, required=True, help="a synthetic capture (igavatar synth)")
    args = parser.parse_args()
    recorded = []
    original = shape_prior.hull_prior_mesh

    def recording(cells):
        recorded.append(cells)
        return original(cells)

    # The verdicts are those preprocess meshes into its prior, so listen in on that call.
    shape_prior.hull_prior_mesh = recording
    with tempfile.TemporaryDirectory() as tmp:
        preprocess.run_preprocess(preprocess.PreprocessOptions(capture=args.capture, out=Path(tmp) / "dataset",
                                                               shape_prior="visual-hull"))
        subject = read_dataset(Path(tmp) / "dataset").subject
    truth = canonical_truth(args.capture, subject)
    if truth is None:
        raise SystemExit(f"{args.capture}: no ground_truth/clothed_rest.npz on this skeleton (a synthetic capture is needed)")
    cells = recorded[0]
    cell = shape_prior.HULL_CELL_M
    x = cells.points.numpy().astype("float64")
    mesh = trimesh.Trimesh(*truth, process=False)
    inside = contains_points(mesh, x, watertight=True)
    far = ~inside & (closest_points_on_mesh(x, *truth)[1] > cell)
    print(f"{args.capture}: {len(x)} cells of {cell * 100:.0f} cm, {int(inside.sum())} inside the truth")
    print(f"{'rule':22s} {'inside truth':>13s} {'> 1 cell outside':>17s}")
    free, crushed, ghost, seen = cells.free, cells.crushed, cells.ghost, cells.seen
    for name, dropped in (("free (masks)", free), ("crushed", crushed & ~free), ("ghost limb", ghost & ~free & ~crushed),
                          ("unseen", ~seen & ~free)):
        d = dropped.numpy()
        print(f"drops: {name:15s} {int((d & inside).sum()):13d} {int((d & far).sum()):17d}")
    walled = cells.walled_in.numpy()
    print(f"re-admits: walled in    {int((walled & inside).sum()):10d} {int((walled & far).sum()):17d}")
    final = cells.kept.numpy()
    print(f"kept in the end         {int((final & inside).sum()):10d} {int((final & far).sum()):17d}")


if __name__ == "__main__":
    main()
