"""Where a held-out render's box error lies: the person's outline or the appearance inside it.

For each full-size render of an `eval` report (`images/<frame>.png`: ground truth | render | error,
made with `--image-scale 1`), the squared RGB error inside the ground-truth mask's bounding box
(the box of `psnr_mask_bbox_db`) is split by the dataset's ground-truth mask into three regions:

- outside: box pixels farther than `--band` px outside the mask (the render spilling over);
- outline: pixels within `--band` px of the mask's outline, on either side (a silhouette off by a
  pixel or two, and the colour at the edge);
- inside: mask pixels farther than `--band` px inside it (the appearance: texture, shading).

Per region: its share of the box's pixels and of its error, its own PSNR, and the box PSNR the
run would reach if that region were rendered perfectly. The frames' errors are pooled (sum of
squared error over all frames), so the box PSNR here is the pooled one, within a few tenths of a
dB of eval's mean over frames.

    python tests/benchmarks/image_error_regions.py --dataset D/dataset --report name=RUN/report-full \
        [--report ...] [--band 3] [--out tests/benchmarks/results/image-error-regions.json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import cv2
import numpy as np

from provenance import command, commit

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from igavatar.avatar.dataset import read_dataset  # noqa: E402
from igavatar.metrics.image import mask_bbox  # noqa: E402

REGIONS = ("outside", "outline", "inside")


def frame_regions(mask_gt: np.ndarray, band_px: int) -> dict[str, np.ndarray]:
    """(H, W) bool ground-truth mask -> (H, W) bool masks of the three regions inside its box."""
    kernel = np.ones((2 * band_px + 1,) * 2, np.uint8)
    m = mask_gt.astype(np.uint8)
    inside = cv2.erode(m, kernel) > 0
    near = cv2.dilate(m, kernel) > 0
    box = np.zeros_like(mask_gt, dtype=bool)
    y0, y1, x0, x1 = mask_bbox(mask_gt)
    box[y0:y1, x0:x1] = True
    return {"outside": box & ~near, "outline": box & near & ~inside, "inside": box & inside}


def split_report(report: Path, masks: dict[str, np.ndarray], band_px: int) -> dict:
    """Pool one report's frames: squared error and pixel count per region (RGB channels counted)."""
    error = dict.fromkeys(REGIONS, 0.0)
    count = dict.fromkeys(REGIONS, 0)
    frames = sorted((report / "images").glob("*.png"))
    if not frames:
        raise SystemExit(f"{report}/images holds no renders: run eval with --image-scale 1")
    for path in frames:
        panel = cv2.imread(str(path), cv2.IMREAD_COLOR)[:, :, ::-1].astype(np.float64) / 255.0
        mask = masks.get(path.stem)
        if mask is None:
            raise SystemExit(f"{path.name}: no mask of that frame in the dataset")
        height, width = mask.shape
        if panel.shape[0] != height or panel.shape[1] != 3 * width:
            raise SystemExit(f"{path}: panel {panel.shape[:2]} is not 3 x the dataset's {height}x{width} "
                             "(run eval with --image-scale 1)")
        gt, pred = panel[:, :width], panel[:, width:2 * width]
        squared = ((gt - pred) ** 2).sum(axis=2)
        for name, region in frame_regions(mask, band_px).items():
            error[name] += float(squared[region].sum())
            count[name] += int(region.sum()) * 3
    return summarise(error, count, len(frames))


def psnr_db(error: float, count: int) -> float:
    """PSNR of a pooled squared error over `count` values (data range 1)."""
    return -10.0 * math.log10(max(error, 1e-12) / max(count, 1))


def summarise(error: dict[str, float], count: dict[str, int], n_frames: int) -> dict:
    total_e, total_n = sum(error.values()), sum(count.values())
    out = {"frames": n_frames, "box_psnr_db": round(psnr_db(total_e, total_n), 2), "regions": {}}
    for name in REGIONS:
        out["regions"][name] = {
            "pixel_share": round(count[name] / total_n, 3),
            "error_share": round(error[name] / total_e, 3),
            "psnr_db": round(psnr_db(error[name], count[name]), 2),
            "box_psnr_if_perfect_db": round(psnr_db(total_e - error[name], total_n), 2),
        }
    return out


def dataset_masks(dataset_dir: Path) -> dict[str, np.ndarray]:
    """Frame name -> (H, W) bool ground-truth mask, for the dataset's test split."""
    dataset = read_dataset(dataset_dir)
    names = dataset.splits.get("test", [])
    return {name: dataset.image_and_mask(name)[1] for name in names}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", type=Path, required=True, help="the dataset the reports were made on")
    parser.add_argument("--report", action="append", required=True, help="name=eval report dir (full-size images)")
    parser.add_argument("--band", type=int, default=3, help="outline half-width in px (default 3)")
    parser.add_argument("--out", type=Path, help="JSON results file to write (default: print only)")
    args = parser.parse_args()
    masks = dataset_masks(args.dataset)
    runs = {}
    for spec in args.report:
        name, _, path = spec.partition("=")
        runs[name] = split_report(Path(path), masks, args.band)
        r = runs[name]["regions"]
        print(f"{name}: box {runs[name]['box_psnr_db']} dB; " + "; ".join(
            f"{k} {v['pixel_share']:.0%} px, {v['error_share']:.0%} err, {v['psnr_db']} dB, "
            f"perfect -> {v['box_psnr_if_perfect_db']} dB" for k, v in r.items()))
    if args.out:
        args.out.write_text(json.dumps({"commit": commit(), "command": command(), "band_px": args.band,
                                        "dataset": str(args.dataset), "runs": runs}, indent=2) + "\n")


if __name__ == "__main__":
    main()
