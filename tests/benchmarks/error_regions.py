"""Where a model's geometry is off: posed NC split by scan region, canonical error split by body part.

For each in-distribution test frame (`test_holdout_*`), the model's canonical mesh (as `eval` makes
it: silhouette level, closed by the box, largest component) is posed and compared with the scan as
`eval` does (10,000 area-uniform samples per surface, the same seeds). The scan's samples are then
split into the faces that look down (unit normal's up component < -0.8: the underside of a skirt's
hem, the soles) and the rest, and their NC (|cos| to the prediction's closest face) is reported
with each region's share of the area and of the NC loss (sum of 1 - |cos|).

Then, for a synthetic capture (its true clothed surface in the canonical pose), the distance from
30,000 area-uniform samples of that truth to the model's canonical mesh, grouped by the body part
each sample's true skinning weights follow most (the part of its dominant bone's name: upperleg
for a skirt, spine for a shirt's torso), with each part's share of the area and of the error.

    python tests/benchmarks/error_regions.py --run RUN/checker-dress-spread --model RUN/checker-dress-spread/model-smooth
    (RUN/<subject> holds capture/scans and dataset/ as bench_quality.py makes them)

The up axis is the capture's world axis with the scan's largest extent (z for the synthetic subjects).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from igavatar.avatar.canonical_report import canonical_truth
from igavatar.avatar.dataset import read_dataset
from igavatar.avatar.model import load_model
from igavatar.avatar.surfaces import canonical_surface
from igavatar.capture.scans import load_scan
from igavatar.mesh.cleanup import clean_mesh
from igavatar.metrics.canonical import REST_SURFACE_FILE
from igavatar.metrics.geometry import closest_points_on_mesh, sample_surface_uniform, surface_samples

#: A scan face looks down when its unit normal's up component is below this.
DOWN_COSINE = -0.8


def region_nc(pred: tuple[np.ndarray, np.ndarray], scan: tuple[np.ndarray, np.ndarray], seed: int = 0,
              n_points: int = 10_000) -> dict[str, float]:
    """NC both ways (as `surface_metrics`) and the scan-to-prediction NC of the down-facing scan faces.

    Args:
        pred, scan: (vertices (V, 3), faces (F, 3)) in the same world frame, meters.
    Returns:
        nc (the protocol's mean of both directions), down_share (of the scan's samples), down_nc,
        rest_nc and down_loss_share (the down-facing samples' share of the scan-to-prediction loss).
    """
    gv = np.asarray(scan[0])
    up = int(np.argmax(gv.max(axis=0) - gv.min(axis=0)))
    samples = surface_samples(pred[0], pred[1], scan[0], scan[1], n_points, seed)
    cos_p2g, cos_g2p = samples.pred_to_gt_cos, samples.gt_to_pred_cos
    down = samples.gt_normals[:, up] < DOWN_COSINE
    loss = 1.0 - cos_g2p
    return {
        "nc": 0.5 * float(cos_p2g.mean() + cos_g2p.mean()),
        "down_share": float(down.mean()),
        "down_nc": float(cos_g2p[down].mean()) if down.any() else float("nan"),
        "rest_nc": float(cos_g2p[~down].mean()),
        "down_loss_share": float(loss[down].sum() / max(loss.sum(), 1e-12)),
    }


def canonical_error_by_part(pred: tuple[np.ndarray, np.ndarray], truth: tuple[np.ndarray, np.ndarray],
                            part_of_vertex: np.ndarray, n_points: int = 30_000, seed: int = 0) -> list[tuple[str, float, float, float]]:
    """Truth-to-prediction distance of the canonical truth's samples, by part.

    Args:
        pred, truth: (vertices (V, 3), faces (F, 3)) canonical meshes, meters.
        part_of_vertex: (Vt,) part name of each truth vertex (a sample takes its face's first vertex's).
    Returns:
        [(part, share of the area, mean distance mm, share of the summed distance)], largest share first.
    """
    x, face = sample_surface_uniform(truth[0], truth[1], n_points, np.random.default_rng([seed, 4]))
    _, distance, _ = closest_points_on_mesh(x, pred[0], pred[1])
    part = part_of_vertex[truth[1][face, 0]]
    rows = [(name, float(np.mean(part == name)), float(distance[part == name].mean() * 1e3),
             float(distance[part == name].sum() / distance.sum())) for name in np.unique(part)]
    return sorted(rows, key=lambda row: -row[3])


def _part_name(bone: str) -> str:
    """'upperleg02.L' -> 'upperleg': the bone's name without side and index."""
    return bone.split(".")[0].rstrip("0123456789_")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, required=True, help="a subject's run dir (capture/scans and dataset/)")
    parser.add_argument("--model", type=Path, required=True, help="a trained model artifact")
    parser.add_argument("--mesh-resolution", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0, help="the surface samples' seed (eval's --seed)")
    args = parser.parse_args()
    model = load_model(args.model)
    dataset = read_dataset(args.run / "dataset")
    frames = dataset.frames()
    test = frames.select(frames.test_indices)
    raw_v, raw_f = canonical_surface(model.avatar, resolution=args.mesh_resolution)
    vertices, faces, _ = clean_mesh(raw_v, raw_f, keep_largest=True)
    rows = []
    print(f"{'frame':20s} {'NC':>6s} {'down share':>10s} {'down NC':>8s} {'rest NC':>8s} {'down loss share':>15s}")
    for i, name in enumerate(test.names):
        if not name.startswith("test_holdout"):
            continue
        posed = model.posed(torch.from_numpy(test.bone_transforms[i]), torch.from_numpy(test.pose_condition[i]))
        scan = load_scan(args.run / "capture" / "scans" / f"{name}.ply")
        row = region_nc((posed.pose_vertices(vertices), faces), scan, seed=args.seed)
        rows.append(row)
        print(f"{name:20s} {row['nc']:6.3f} {row['down_share']:10.3f} {row['down_nc']:8.3f} {row['rest_nc']:8.3f} "
              f"{row['down_loss_share']:15.2f}", flush=True)
    mean = {key: float(np.mean([row[key] for row in rows])) for key in rows[0]}
    print(f"{'mean':20s} {mean['nc']:6.3f} {mean['down_share']:10.3f} {mean['down_nc']:8.3f} {mean['rest_nc']:8.3f} "
          f"{mean['down_loss_share']:15.2f}")
    truth = canonical_truth(args.run / "capture", dataset.subject)
    if truth is None:
        print(f"\nno {REST_SURFACE_FILE} for this skeleton: canonical error by part not computed")
        return
    with np.load(args.run / "capture" / REST_SURFACE_FILE) as rest:
        dominant = rest["weights_index"][np.arange(len(rest["weights_index"])), rest["weights_value"].argmax(axis=1)]
    part_of_vertex = np.array([_part_name(str(dataset.subject.joint_names[j])) for j in dominant])
    print(f"\n{'canonical part':16s} {'area':>6s} {'mean mm':>8s} {'error share':>11s}")
    for name, area, mean_mm, share in canonical_error_by_part((vertices, faces), truth, part_of_vertex, seed=args.seed)[:8]:
        print(f"{name:16s} {area:6.3f} {mean_mm:8.2f} {share:11.2f}")


if __name__ == "__main__":
    main()
