"""How well a trained model's renders register with its frames, and what a one-pixel slip costs.

For each named frame (training or held-out) of a model's dataset, the frame is rendered at the
dataset's size (the model's refined pose when it refined that frame, else the dataset's), every
sample kept (no early stop), and scored in the ground-truth mask's box on white, as `eval` does:

- silhouette: IoU of the render's opacity with the mask, and the best whole-image shift of the
  render (quarter pixels, up to 4 px) with the IoU it reaches;
- where the box error lies: the share of the box's squared error on pixels the render misses
  (inside the mask, opacity < 1/2) or adds (outside, > 1/2);
- colour with the outline made perfect: the render clipped to the mask (white outside), and the
  colour of each ray's heaviest sample in place of the composite (no transparency);
- calibration: the ground truth against itself moved by one pixel (along x, along y), on white
  and on black: the box PSNR a perfect render a pixel off would get.

    python tests/benchmarks/frame_registration.py --model RUN/model --frames frame_000000 frame_000288 \
        [--dataset D] [--samples 128] [--dataset-poses] [--maps OUT_DIR] [--out results.json]

`--maps` writes each frame's maps (`.npz`: image, mask, rgb, heavy_rgb, opacity) for pictures;
they hold the dataset's images, so keep them out of the repository for a research-only capture.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import shift as shift_image

from provenance import command, commit

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from igavatar.avatar.dataset import read_dataset  # noqa: E402
from igavatar.avatar.model import load_model  # noqa: E402
from igavatar.avatar.poses import model_frame_poses  # noqa: E402
from igavatar.metrics.image import mask_bbox  # noqa: E402
from igavatar.render.rays import pixel_grid, pixel_rays, rays_in_box  # noqa: E402
from igavatar.render.sampler import sample_along_rays  # noqa: E402
from igavatar.render.volume import render_rays  # noqa: E402


def render_maps(model, frames, index: int, bones: torch.Tensor, size_hw: tuple[int, int],
                samples: int) -> dict[str, np.ndarray]:
    """(H, W[, 3]) composite rgb on white, opacity, and the heaviest sample's colour of dataset frame
    `index` posed by (J, 4, 4) `bones`."""
    posed = model.posed(bones, torch.from_numpy(frames.pose_condition[index]))
    box = torch.from_numpy(frames.posed_boxes[index]).float()
    grid = posed.occupancy(model.canonical_grid, box, model.config.occupancy_resolution)
    origins, directions = pixel_rays(torch.from_numpy(frames.K[index]).float(),
                                     torch.from_numpy(frames.w2c[index]).float(), pixel_grid(*size_hw))
    rays = rays_in_box(origins, directions, box[0], box[1])
    parts: dict[str, list[torch.Tensor]] = {"rgb": [], "opacity": [], "heavy_rgb": []}
    for start in range(0, rays.num_rays, 2048):
        batch = sample_along_rays(rays.slice(start, start + 2048), samples, grid.is_occupied, stratified=False)
        out = render_rays(batch, posed.field_fn, torch.ones(3))
        heaviest = out.weights.argmax(dim=1)
        parts["rgb"].append(out.rgb.detach())
        parts["opacity"].append(out.opacity.detach())
        parts["heavy_rgb"].append(out.sample_rgb.detach()[torch.arange(heaviest.shape[0]), heaviest])
    return {key: torch.cat(value).reshape(*size_hw, -1).squeeze(-1).numpy().astype(np.float64)
            for key, value in parts.items()}


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return -10.0 * math.log10(max(float(((a - b) ** 2).mean()), 1e-12))


def best_shift(opacity: np.ndarray, mask: np.ndarray) -> tuple[float, float, float]:
    """(dx, dy, IoU): the whole-image shift of the render that best matches the mask."""
    best = (0.0, 0.0, -1.0)
    for dy in np.arange(-4.0, 4.01, 0.25):
        for dx in np.arange(-4.0, 4.01, 0.25):
            moved = shift_image(opacity, (dy, dx), order=1)
            iou = float(np.minimum(moved, mask).sum() / np.maximum(moved, mask).sum())
            if iou > best[2]:
                best = (float(dx), float(dy), iou)
    return best


def frame_record(maps: dict[str, np.ndarray], image: np.ndarray, mask: np.ndarray) -> dict:
    """The frame's numbers (see the module docstring); image (H, W, 3) on white in [0, 1], mask (H, W) bool."""
    y0, y1, x0, x1 = mask_bbox(mask)
    box = (slice(y0, y1), slice(x0, x1))
    opacity, rgb = maps["opacity"], maps["rgb"]
    error = ((rgb - image) ** 2).sum(-1)
    missed, added = mask & (opacity < 0.5), ~mask & (opacity > 0.5)
    on_black = np.where(mask[..., None], image, 0.0)
    dx, dy, shifted_iou = best_shift(opacity, mask.astype(np.float64))
    return {
        "silhouette_iou": float(np.minimum(opacity, mask).sum() / np.maximum(opacity, mask).sum()),
        "best_shift_px": [dx, dy], "best_shift_iou": shifted_iou,
        "box_psnr_db": psnr(rgb[box], image[box]),
        "box_error_share_missed_or_added": float((error[missed].sum() + error[added].sum()) / error[box].sum()),
        "box_psnr_clipped_to_mask_db": psnr(np.where(mask[..., None], rgb, 1.0)[box], image[box]),
        "box_psnr_heaviest_sample_in_mask_db": psnr(np.where(mask[..., None], maps["heavy_rgb"], 1.0)[box], image[box]),
        "gt_moved_1px_box_psnr_db": {
            "white_x": psnr(np.roll(image, 1, axis=1)[box], image[box]),
            "white_y": psnr(np.roll(image, 1, axis=0)[box], image[box]),
            "black_x": psnr(np.roll(on_black, 1, axis=1)[box], on_black[box]),
            "black_y": psnr(np.roll(on_black, 1, axis=0)[box], on_black[box]),
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--dataset", type=Path, help="default: the dataset the model records")
    parser.add_argument("--frames", nargs="+", required=True, help="frame names (images/<name>.png)")
    parser.add_argument("--samples", type=int, default=128)
    parser.add_argument("--dataset-poses", action="store_true", help="the dataset's poses even where the model refined them")
    parser.add_argument("--maps", type=Path, help="folder for each frame's maps (.npz)")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    torch.manual_seed(0)
    model = load_model(args.model)
    dataset = read_dataset(args.dataset or model.recorded_dataset)
    frames = dataset.frames()
    # The model's refined training poses, by frame slot (none when it refined none or was trained on another dataset).
    refined = {} if args.dataset_poses else model_frame_poses(
        model, dataset.path, list(frames.names), torch.from_numpy(frames.bone_transforms), carry=False).refined
    records = {}
    for name in args.frames:
        if name not in frames.names:
            raise SystemExit(f"{name}: no such frame in {dataset.path}")
        index = frames.names.index(name)
        image, mask = dataset.image_on_white(name, dataset.image_size)
        bones = refined.get(index, torch.from_numpy(frames.bone_transforms[index]))
        maps = render_maps(model, frames, index, bones, dataset.image_size, args.samples)
        split = "train" if name in dataset.splits.get("train", []) else "test"
        records[name] = {"split": split, "refined_pose": index in refined, **frame_record(maps, image, mask)}
        print(name, json.dumps(records[name]))
        if args.maps is not None:
            args.maps.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(args.maps / f"{name}.npz", image=image, mask=mask, **maps)
    keys = [k for k, v in next(iter(records.values())).items() if isinstance(v, float)]
    means = {k: float(np.mean([r[k] for r in records.values()])) for k in keys}
    result = {"commit": commit(), "command": command(), "model": str(args.model), "samples": args.samples,
              "frames": records, "mean": means}
    print(json.dumps(means, indent=1))
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
