"""One test frame's record of `igavatar eval` (geometry against its scan, image against its truth), the
report document over all of them, and the console summary of its means.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from igavatar.artifacts.png import write_png
from igavatar.capture.scans import ScanMatching, load_scan
from igavatar.metrics.frame_geometry import frame_geometry
from igavatar.metrics.image import evaluate_image, side_by_side
from igavatar.metrics.report import METRIC_KEYS, METRICS, error_mesh_panel, mean_over_frames
from stages.eval_options import EvalOptions, ImageSettings
from stages.eval_poses import carried_notes, refinement_notes

#: Distance (mm) shown fully red in the error-colored mesh panels.
ERROR_VMAX_MM = 20.0
#: Longest side (pixels) of the error-colored mesh panels.
ERROR_PANEL_MAX_SIDE = 512
#: Mean absolute RGB error shown fully red in the image panels.
IMAGE_ERROR_VMAX = 0.25


def summary_of_metrics(document: dict, n_frames: int, keys: tuple[str, ...] = METRIC_KEYS) -> dict[str, Any]:
    """Each metric's mean (or why there is none) for the console; a mean over only some of the
    `n_frames` test frames adds `<key>_covers` saying how many."""
    summary: dict[str, Any] = {}
    for key in keys:
        entry = document["metrics"][key]
        summary[key] = round(entry["mean"], 4) if entry["mean"] is not None else entry["status"]
        if 0 < entry["n_frames"] < n_frames:
            summary[f"{key}_covers"] = f"{entry['n_frames']} of {n_frames} test frames (see the report's notes)"
    return summary


def frame_geometry_record(
    record: dict, posed_v: np.ndarray, faces: np.ndarray, scan_path: Path, options: EvalOptions,
    K_panel: np.ndarray, w2c: np.ndarray, panel_hw: tuple[int, int], tmp: Path,
) -> np.ndarray:
    """Fill one frame's geometry values, details and notes, write its error panel; returns (V,) error in mm.

    Args:
        posed_v (V, 3): the posed prediction in world coordinates; faces (F, 3).
        K_panel (3, 3), w2c (4, 4), panel_hw: the test camera at the panel's size.
    """
    tick = time.perf_counter()
    name = record["frame"]
    gt_v, gt_f = load_scan(scan_path)
    values, details, notes, error_mm = frame_geometry(posed_v, faces, gt_v, gt_f, options)
    record["scan"] = str(scan_path)
    record["values"].update(values)
    record["geometry"] = details
    record["notes"] += notes
    panel = error_mesh_panel(gt_v, gt_f, posed_v, faces, error_mm, K_panel, w2c, panel_hw[0], panel_hw[1], ERROR_VMAX_MM)
    write_png(tmp / "geometry" / f"{name}.png", panel)
    record["files"]["error_render"] = f"geometry/{name}.png"
    record["seconds"]["geometry"] = time.perf_counter() - tick
    return error_mm


def frame_image_record(
    record: dict, render, ground_truth: tuple[np.ndarray, np.ndarray],
    lpips_fn: Callable[[np.ndarray, np.ndarray], float] | None, tmp: Path,
) -> None:
    """Fill one frame's image values from its render (ImageRender) and write ground truth | render | error.

    Args:
        ground_truth: (RGB (h, w, 3) float on white, mask (h, w) bool) at the render's size.
    """
    name = record["frame"]
    pred_rgb = render.rgb.clamp(0, 1).cpu().numpy().astype(np.float64)
    gt_rgb, gt_mask = ground_truth
    if gt_mask.any():
        metrics = evaluate_image(pred_rgb, gt_rgb, gt_mask)
        record["values"].update(
            psnr_full_db=metrics.psnr_full_db, ssim_full=metrics.ssim_full,
            psnr_mask_bbox_db=metrics.psnr_mask_bbox_db, ssim_mask_bbox=metrics.ssim_mask_bbox,
        )
    else:
        record["notes"].append("the ground-truth mask is empty at the render's size: image metrics not computed")
    if lpips_fn is not None:
        record["values"]["lpips_full"] = lpips_fn(pred_rgb, gt_rgb)
    record["image"] = {"height": int(pred_rgb.shape[0]), "width": int(pred_rgb.shape[1]),
                       "mean_opacity": float(render.opacity.mean())}
    write_png(tmp / "images" / f"{name}.png", side_by_side(gt_rgb, pred_rgb, IMAGE_ERROR_VMAX))
    record["files"]["side_by_side"] = f"images/{name}.png"


def report_document(
    options: EvalOptions, image_settings: ImageSettings, model_dir: Path, dataset_dir: Path, gt_dir: Path | None,
    frame_names: list[str],
    records: list[dict], matching: ScanMatching | None, prediction_mesh: dict | None, notes: list[str],
    lpips_status: str, size_hw: tuple[int, int], dataset_hw: tuple[int, ...], device: str,
) -> dict:
    """The report document without its per-frame list (the manifest's data)."""
    metrics = {}
    for spec in METRICS:
        mean, n = mean_over_frames([r["values"][spec.key] for r in records])
        if spec.key == "lpips_full":
            status = lpips_status
        elif spec.kind == "geometry" and not options.geometry:
            status = "not computed: --no-geometry"
        elif spec.kind == "image" and not options.images:
            status = "not computed: --no-images"
        elif n == 0:
            status = "not computed on any frame (see the per-frame notes)"
        else:
            status = f"mean over {n} of {len(records)} test frames"
        metrics[spec.key] = {
            "label": spec.label, "protocol": spec.protocol, "description": spec.description, "units": spec.units,
            "frame": spec.frame, "background": spec.background, "better": spec.better, "mean": mean, "n_frames": n,
            "status": status,
        }
    iou_states = [r["geometry"]["volumetric_iou"]["status"] for r in records if r["geometry"] is not None]
    n_approximate = sum(s == "approximate" for s in iou_states)
    if n_approximate:
        notes = notes + [f"IoU is approximate on {n_approximate} frame(s) (see their notes)"]
    notes = notes + [f"LPIPS {lpips_status}"] + carried_notes(records) + refinement_notes(records)
    return {
        "inputs": {"model": str(model_dir), "dataset": str(dataset_dir), "gt": str(gt_dir) if gt_dir else None},
        "frame_names": frame_names,
        "settings": {
            "geometry": options.geometry, "images": options.images, "mesh_resolution": options.mesh_resolution,
            "surface_samples": options.surface_samples, "iou_points": options.iou_points,
            "iou_open_meshes": options.iou_open_meshes, "seed": options.seed, "image_scale": image_settings.scale,
            "image_size": list(size_hw), "dataset_image_size": list(dataset_hw),
            "samples_per_ray": image_settings.samples_per_ray,
            "image_frames": sum(r["image"] is not None for r in records), "background": "white",
            "carry_poses": options.carry_poses,
            "test_time_pose_refinement": options.refine_test_poses,
            "error_vmax_mm": ERROR_VMAX_MM, "image_error_vmax": IMAGE_ERROR_VMAX, "bbox_pad": 0, "device": device,
        },
        "prediction_mesh": prediction_mesh,
        "gt_matching": matching.to_json() if matching is not None else None,
        "metrics": metrics,
        "lpips": {"computed": lpips_status.startswith("computed"), "status": lpips_status},
        "notes": notes,
        "files": {"metrics": "metrics.json", "tables": "report.md"},
    }
