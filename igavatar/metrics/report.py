"""What an evaluation report says and how it looks: metric vocabulary, means, markdown, plots.

    markdown = markdown_report(document)                           # document = metrics.json's content
    png_rgb = metric_curves_image(frame_names, {"chamfer_l2_cm2": [0.6, None, 0.7], ...})

Pure functions: arrays and dicts in, strings and RGB uint8 images out; the caller writes files.
Every metric is declared once in ``METRICS`` with its protocol, units, coordinate frame and
background (EVAL.md: a number that does not say these cannot be compared with another report).
Plots are drawn with OpenCV (matplotlib is not a dependency). The error-colored mesh panel ray
casts the posed prediction and the scan from the test camera with Embree
(``igavatar.geometry.raycast``) and colors the prediction by its distance to the scan.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np

from igavatar.errors import InputError
from igavatar.geometry.raycast import CameraRays, MeshRayCaster, RayHits, interpolate_vertex_values, render_mesh

__all__ = [
    "MetricSpec",
    "METRICS",
    "METRIC_KEYS",
    "PAPER_XHUMANS",
    "mean_over_frames",
    "format_value",
    "markdown_report",
    "metric_curves_image",
    "error_colors",
    "error_mesh_panel",
]

PANEL_HEADER_PX = 18
WORLD = "world (posed meshes, meters, the capture's world frame)"
IMAGE = "image plane of the test frame's camera"


@dataclass(frozen=True)
class MetricSpec:
    """One reported metric: what it is, where it is measured and which way is better."""

    key: str
    """Key in metrics.json (per-frame `values` and top-level `metrics`)."""
    label: str
    """Short column title for tables and plots."""
    kind: Literal["geometry", "image"]
    protocol: str
    """`paper`, `surface`, `volumetric` or `image` (see `description`)."""
    units: str
    frame: str
    """Coordinate frame the metric is computed in."""
    background: str | None
    """Background the images are composited on (None for geometry)."""
    better: Literal["lower", "higher"]
    description: str
    digits: int
    """Decimals shown in tables."""


METRICS: tuple[MetricSpec, ...] = (
    MetricSpec("chamfer_l2_cm2", "CD-L2", "geometry", "paper", "cm^2", WORLD, None, "lower",
               "mean squared nearest-VERTEX distance, (pred->gt + gt->pred) / 2 (averaged, not summed)", 3),
    MetricSpec("normal_consistency_vertices", "NC", "geometry", "paper", "unitless, [-1, 1]", WORLD, None, "higher",
               "1 - mean over gt vertices of |n_pred(nearest pred vertex) - n_gt|_2, unit vertex normals", 3),
    MetricSpec("chamfer_l1_surface_mm", "CD-L1 surf", "geometry", "surface", "mm", WORLD, None, "lower",
               "area-uniform surface samples, unsquared point-to-FACE distance, mean of both directions", 2),
    MetricSpec("normal_consistency_surface", "NC surf", "geometry", "surface", "unitless |cos|, [0, 1]", WORLD, None,
               "higher", "mean |cos| between a sample's face normal and the nearest face's normal, both directions", 3),
    MetricSpec("volumetric_iou", "IoU", "geometry", "volumetric", "unitless, [0, 1]", WORLD, None, "higher",
               "uniform points in the union bounding box, inside test by ray parity on watertight meshes "
               "(not X-Avatar's bounding-box IoU)", 3),
    MetricSpec("psnr_full_db", "PSNR", "image", "image", "dB", IMAGE, "white", "higher",
               "PSNR on [0, 1] RGB, data_range 1, the full image", 2),
    MetricSpec("ssim_full", "SSIM", "image", "image", "unitless, [-1, 1]", IMAGE, "white", "higher",
               "SSIM (Wang et al., 11x11 Gaussian, sigma 1.5), data_range 1, the full image", 4),
    MetricSpec("psnr_mask_bbox_db", "PSNR box", "image", "image", "dB", IMAGE, "white", "higher",
               "PSNR inside the ground-truth mask's bounding box", 2),
    MetricSpec("ssim_mask_bbox", "SSIM box", "image", "image", "unitless, [-1, 1]", IMAGE, "white", "higher",
               "SSIM inside the ground-truth mask's bounding box", 4),
    MetricSpec("lpips_full", "LPIPS", "image", "image", "unitless, >= 0", IMAGE, "white", "lower",
               "LPIPS (AlexNet, v0.1) on the full image; only with locally present weights", 4),
)
METRIC_KEYS: tuple[str, ...] = tuple(spec.key for spec in METRICS)
_SPEC_BY_KEY = {spec.key: spec for spec in METRICS}

#: The paper's Table (X-Humans, ~10 min of GPU training), to set beside ours (EVAL.md).
PAPER_XHUMANS: tuple[tuple[str, float, float, float, float, float], ...] = (
    ("25", 0.579, 0.910, 0.974, 29.87, 0.983),
    ("28", 0.600, 0.914, 0.947, 27.74, 0.976),
    ("35", 0.557, 0.891, 0.923, 28.68, 0.979),
    ("36", 0.691, 0.838, 0.936, 30.97, 0.974),
    ("58", 0.597, 0.875, 0.950, 30.54, 0.985),
)


def _finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def mean_over_frames(values: Sequence[float | None]) -> tuple[float | None, int]:
    """Mean of the finite values (None and non-finite are left out) and how many there were.

    Args:
        values: one entry per frame, None where the metric was not computed.
    Returns:
        (mean, n); mean is None when n == 0.
    """
    kept = [float(v) for v in values if _finite(v)]
    return (float(np.mean(kept)) if kept else None), len(kept)


def format_value(value: Any, digits: int) -> str:
    """A table cell: the number with `digits` decimals, or an em dash when absent."""
    return f"{value:.{digits}f}" if _finite(value) else "—"


# ----------------------------------------------------------------------------- markdown


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    # A literal '|' (as in "|cos|") would split a cell: escape it.
    cells = lambda row: " | ".join(str(c).replace("|", "\\|") for c in row)  # noqa: E731
    lines = ["| " + cells(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + cells(row) + " |" for row in rows]
    return lines


def _name_list(names: Sequence[str], limit: int = 12) -> str:
    if not names:
        return "none"
    shown = ", ".join(f"`{n}`" for n in names[:limit])
    return shown + (f" and {len(names) - limit} more" if len(names) > limit else "")


def markdown_report(document: dict[str, Any]) -> str:
    """The human-readable report of a metrics document (the content of metrics.json).

    Args:
        document: dict with `metrics` (key -> {mean, n_frames, status, ...}), `frames` (list of
            {frame, values, notes}), `settings`, `gt_matching`, `inputs`, `prediction_mesh`, `notes`.
    Returns:
        Markdown text: settings, means with protocol/units/frame/background, ground-truth matching,
        a per-frame table with a mean row, notes, and the paper's numbers for context.
    """
    settings = document["settings"]
    inputs = document["inputs"]
    metrics = document["metrics"]
    frames = document["frames"]
    keys = [k for k in METRIC_KEYS if k in metrics]
    lines = ["# igavatar evaluation report", ""]
    lines += [
        f"- model: `{inputs['model']}`",
        f"- dataset: `{inputs['dataset']}`",
        (f"- ground-truth scans: `{inputs['gt']}`" if inputs.get("gt")
         else "- ground-truth scans: none (geometry not evaluated)"),
        f"- test frames: {len(frames)}; geometry: "
        + (f"{metrics['chamfer_l2_cm2']['n_frames']} frames with a scan" if settings["geometry"] else "off (--no-geometry)")
        + "; images: " + (f"{settings['image_frames']} frames rendered" if settings["images"] else "off (--no-images)"),
        f"- posed prediction: canonical marching cubes at {settings['mesh_resolution']} (largest component), "
        "posed per frame by skinning with non-rigid offsets, world coordinates",
        f"- images: {settings['image_size'][1]}x{settings['image_size'][0]} px (scale {settings['image_scale']} of the "
        f"dataset's {settings['dataset_image_size'][1]}x{settings['dataset_image_size'][0]}), {settings['samples_per_ray']} "
        f"samples per ray, {settings['background']} background; test-time pose refinement: "
        f"{'on' if settings['test_time_pose_refinement'] else 'off'}",
        f"- surface samples: {settings['surface_samples']}; IoU points: {settings['iou_points']}; seed {settings['seed']}",
        "",
        "## Mean over test frames",
        "",
    ]
    rows = []
    for key in keys:
        spec, entry = _SPEC_BY_KEY[key], metrics[key]
        mean = format_value(entry["mean"], spec.digits) if entry["mean"] is not None else entry["status"]
        rows.append([f"{spec.label} (`{key}`)", spec.protocol, spec.units, "world" if spec.frame == WORLD else "image",
                     spec.background or "—", spec.better, mean, str(entry["n_frames"])])
    lines += _table(["metric", "protocol", "units", "frame", "background", "better", "mean", "frames"], rows)

    matching = document.get("gt_matching")
    if matching is not None:
        lines += [
            "", "## Ground-truth scans", "",
            f"- matched to a test frame: {len(matching['matched'])}",
            f"- **missing** (test frames without a scan, no geometry metrics): {_name_list(matching['missing'])}",
            f"- **extra** (scans named after no frame of the dataset): {_name_list(matching['extra'])}",
            f"- scans of frames in other splits (not evaluated): {len(matching['other_split'])}",
            f"- ignored files (not .ply/.obj): {_name_list(matching['ignored_files'])}",
        ]

    lines += ["", "## Per frame", ""]
    rows = [
        [f"`{record['frame']}`"] + [format_value(record["values"].get(k), _SPEC_BY_KEY[k].digits) for k in keys]
        for record in frames
    ]
    rows.append(["**mean**"] + [format_value(metrics[k]["mean"], _SPEC_BY_KEY[k].digits) for k in keys])
    lines += _table(["frame"] + [f"{_SPEC_BY_KEY[k].label} ({_SPEC_BY_KEY[k].units.split(',')[0]})" for k in keys], rows)

    frame_notes = [(record["frame"], note) for record in frames for note in record.get("notes", [])]
    notes = list(document.get("notes", [])) + [f"`{frame}`: {note}" for frame, note in frame_notes]
    if notes:
        lines += ["", "## Notes", ""] + [f"- {note}" for note in notes]

    lines += [
        "", "## The paper's numbers (X-Humans, ~10 min GPU training; other data, for scale only)", "",
    ]
    paper_rows = [[seq, f"{cd:.3f}", f"{nc:.3f}", f"{iou:.3f}", f"{psnr:.2f}", f"{ssim:.3f}"]
                  for seq, cd, nc, iou, psnr, ssim in PAPER_XHUMANS]
    lines += _table(["sequence", "CD-L2 (cm^2)", "NC", "IoU", "PSNR (dB)", "SSIM"], paper_rows)
    files = document.get("files", {})
    if files:
        lines += ["", "## Files", ""] + [f"- {what}: `{path}`" for what, path in files.items()]
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- plots

_INK = (40, 40, 40)
_GRID = (215, 215, 215)
_LINE = (31, 119, 180)
_MEAN = (214, 39, 40)


def _text(image: np.ndarray, text: str, origin: tuple[int, int], scale: float = 0.4, color=_INK) -> None:
    cv2.putText(image, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, color, 1, cv2.LINE_AA)


def _curve_panel(title: str, values: Sequence[float | None], mean: float | None, size: tuple[int, int]) -> np.ndarray:
    """One small-multiple panel (RGB uint8 (h, w, 3)): per-frame values, gaps where absent, mean dashed."""
    h, w = size
    panel = np.full((h, w, 3), 255, np.uint8)
    left, right, top, bottom = 52, 10, 24, 22
    _text(panel, title, (6, 15), 0.42)
    cv2.rectangle(panel, (left, top), (w - right, h - bottom), _GRID, 1)
    finite = [float(v) for v in values if _finite(v)]
    if not finite:
        _text(panel, "not computed", (left + 10, (top + h - bottom) // 2))
        return panel
    lo, hi = min(finite), max(finite)
    if hi - lo < 1e-12:
        lo, hi = lo - 0.5 * max(abs(lo), 1e-3), hi + 0.5 * max(abs(hi), 1e-3)
    n = len(values)

    def to_px(i: int, v: float) -> tuple[int, int]:
        x = left + (0.5 if n == 1 else i / (n - 1)) * (w - right - left)
        y = (h - bottom) - (v - lo) / (hi - lo) * (h - bottom - top)
        return int(round(x)), int(round(y))

    for label, v in ((f"{hi:.4g}", hi), (f"{lo:.4g}", lo)):
        _text(panel, label, (2, to_px(0, v)[1] + 4), 0.33)
    _text(panel, "0", (left - 3, h - 6), 0.33)
    _text(panel, str(n - 1), (w - right - 12, h - 6), 0.33)
    _text(panel, "test frame", ((left + w - right) // 2 - 28, h - 6), 0.33)
    if mean is not None and _finite(mean):
        y = to_px(0, mean)[1]
        for x in range(left, w - right, 8):
            cv2.line(panel, (x, y), (min(x + 4, w - right), y), _MEAN, 1, cv2.LINE_AA)
    run: list[tuple[int, int]] = []
    for i, v in enumerate(list(values) + [None]):
        if _finite(v):
            run.append(to_px(i, float(v)))
            continue
        # A missing value breaks the line, so a gap is never drawn as a straight interpolation.
        if len(run) > 1:
            cv2.polylines(panel, [np.array(run, np.int32)], False, _LINE, 1, cv2.LINE_AA)
        for point in run:
            cv2.circle(panel, point, 2, _LINE, -1, cv2.LINE_AA)
        run = []
    return panel


def metric_curves_image(
    frame_names: Sequence[str],
    series: dict[str, Sequence[float | None]],
    means: dict[str, float | None] | None = None,
    columns: int = 3,
    panel_size: tuple[int, int] = (180, 320),
) -> np.ndarray:
    """Per-frame metric curves as one RGB uint8 image, one panel per metric (small multiples).

    Args:
        frame_names: N test frames (the x axis is their index).
        series: metric key (of METRICS) -> N values, None where not computed (drawn as a gap).
        means: metric key -> mean, drawn as a dashed red line.
        columns: panels per row. panel_size: (h, w) of each panel in pixels.
    Returns:
        (rows * h, columns * w, 3) uint8 RGB.
    """
    if columns < 1:
        raise InputError(f"metric_curves_image: columns={columns}, expected >= 1")
    n = len(frame_names)
    for key, values in series.items():
        if key not in _SPEC_BY_KEY:
            raise InputError(f"metric_curves_image: unknown metric {key!r}; expected one of {', '.join(METRIC_KEYS)}")
        if len(values) != n:
            raise InputError(f"metric_curves_image: {key} has {len(values)} values for {n} frames")
    keys = [k for k in METRIC_KEYS if k in series]
    if not keys:
        raise InputError("metric_curves_image: no metric to plot")
    panels = []
    for key in keys:
        spec = _SPEC_BY_KEY[key]
        title = f"{spec.label} [{spec.units.split(',')[0]}] ({spec.better} is better)"
        panels.append(_curve_panel(title, series[key], (means or {}).get(key), panel_size))
    blank = np.full_like(panels[0], 255)
    panels += [blank] * ((-len(panels)) % columns)
    rows = [np.concatenate(panels[i : i + columns], axis=1) for i in range(0, len(panels), columns)]
    return np.concatenate(rows, axis=0)


# ----------------------------------------------------------------------------- error-colored meshes


def error_colors(error_mm: np.ndarray, vmax_mm: float) -> np.ndarray:
    """Color per value on the OpenCV JET map: blue at 0, red at >= vmax_mm.

    Args:
        error_mm: (V,) non-negative distances in mm. vmax_mm: distance shown fully red.
    Returns:
        (V, 3) float64 RGB in [0, 1].
    """
    if not vmax_mm > 0:
        raise InputError(f"error_colors: vmax_mm={vmax_mm}, expected > 0")
    error = np.asarray(error_mm, np.float64).reshape(-1)
    level = np.round(np.clip(np.nan_to_num(error, nan=vmax_mm) / vmax_mm, 0.0, 1.0) * 255).astype(np.uint8)
    bgr = cv2.applyColorMap(level[:, None], cv2.COLORMAP_JET)[:, 0]
    return bgr[:, ::-1].astype(np.float64) / 255.0


def _render_colored(
    vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray, rays: CameraRays
) -> np.ndarray:
    """Headlight-shaded ray cast (H, W, 3) float RGB of a mesh with per-vertex colors, white background."""
    caster = MeshRayCaster(vertices, faces)
    tri = np.asarray(vertices, np.float64)[np.asarray(faces)]
    face_normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    face_normals /= np.maximum(np.linalg.norm(face_normals, axis=1, keepdims=True), 1e-20)

    def shade(hits: RayHits, x_world: np.ndarray, view_dirs: np.ndarray) -> np.ndarray:
        albedo = interpolate_vertex_values(colors, faces, hits)
        # |cos| so that inverted or inside-out patches stay visible instead of turning black.
        lambert = np.abs(np.einsum("ij,ij->i", face_normals[hits.face_index], view_dirs))
        return albedo * (0.35 + 0.65 * lambert)[:, None]

    return render_mesh(caster, rays, shade, background=(1.0, 1.0, 1.0)).rgb.astype(np.float64) / 255.0


def _color_bar(height: int, vmax_mm: float, width: int = 70) -> np.ndarray:
    """A vertical JET legend (height, width, 3) uint8 RGB from 0 (bottom) to vmax_mm (top)."""
    bar = np.full((height, width, 3), 255, np.uint8)
    top, bottom = 16, height - 16
    if bottom - top < 2:
        return bar
    levels = np.linspace(vmax_mm, 0.0, bottom - top)
    colors = (error_colors(levels, vmax_mm) * 255).round().astype(np.uint8)
    bar[top:bottom, 6:22] = colors[:, None, :]
    _text(bar, f">={vmax_mm:g}", (24, top + 8), 0.33)
    _text(bar, "mm", (24, (top + bottom) // 2), 0.33)
    _text(bar, "0", (24, bottom), 0.33)
    return bar


def error_mesh_panel(
    gt_vertices: np.ndarray,
    gt_faces: np.ndarray,
    pred_vertices: np.ndarray,
    pred_faces: np.ndarray,
    pred_error_mm: np.ndarray,
    K: np.ndarray,
    w2c: np.ndarray,
    height: int,
    width: int,
    vmax_mm: float = 20.0,
) -> np.ndarray:
    """Scan | prediction colored by its distance to the scan | legend, seen from the test camera.

    Args:
        gt_vertices (Vg, 3), gt_faces (Fg, 3): the ground-truth scan, world coordinates (meters).
        pred_vertices (Vp, 3), pred_faces (Fp, 3): the posed prediction, world coordinates.
        pred_error_mm: (Vp,) distance of each predicted vertex to the scan in mm.
        K (3, 3), w2c (4, 4), height, width: the camera (pixels, OpenCV convention).
        vmax_mm: distance shown fully red (fixed, so that panels compare across frames).
    Returns:
        (PANEL_HEADER_PX + height, 2 * width + 70, 3) uint8 RGB: a title strip above the scan shaded
        gray, the prediction in JET colors and the legend.
    """
    pred_error_mm = np.asarray(pred_error_mm, np.float64).reshape(-1)
    if pred_error_mm.shape[0] != np.asarray(pred_vertices).shape[0]:
        raise InputError(
            f"error_mesh_panel: {pred_error_mm.shape[0]} errors for {np.asarray(pred_vertices).shape[0]} predicted vertices"
        )
    rays = CameraRays(np.asarray(K, np.float64), np.asarray(w2c, np.float64), height, width, supersample=1)
    gray = np.full((np.asarray(gt_vertices).shape[0], 3), 0.78)
    gt_image = _render_colored(gt_vertices, gt_faces, gray, rays)
    pred_image = _render_colored(pred_vertices, pred_faces, error_colors(pred_error_mm, vmax_mm), rays)
    to_u8 = lambda x: np.round(np.clip(x, 0, 1) * 255).astype(np.uint8)  # noqa: E731
    panel = np.concatenate([to_u8(gt_image), to_u8(pred_image), _color_bar(height, vmax_mm)], axis=1)
    # Titles go in a strip above the renders so that they never cover the meshes.
    header = np.full((PANEL_HEADER_PX, panel.shape[1], 3), 255, np.uint8)
    _text(header, "scan", (4, 13), 0.4)
    _text(header, "prediction: distance to scan", (width + 4, 13), 0.4)
    return np.concatenate([header, panel], axis=0)


def _look_from(center: np.ndarray, direction: np.ndarray, distance: float) -> np.ndarray:
    """(4, 4) OpenCV w2c of a camera `distance` from `center` along `direction`, looking back, +Z up."""
    eye = center + distance * direction
    forward = -direction / np.linalg.norm(direction)
    right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = rotation, -rotation @ eye
    return w2c


def canonical_views_image(meshes: Sequence[tuple[str, np.ndarray, np.ndarray]], size: int = 320) -> np.ndarray:
    """Front and side views of canonical meshes (+Z up, facing -Y) as one uint8 RGB image.

    Args:
        meshes: (title, vertices (V, 3), faces (F, 3)) per row, e.g. prediction, truth, template.
        size: pixels per view.
    Returns:
        (rows * size, 2 * size, 3) uint8: one row per mesh, front | side, titled.
    """
    everything = np.concatenate([np.asarray(v, np.float64) for _, v, _ in meshes])
    center = 0.5 * (everything.min(0) + everything.max(0))
    extent = float((everything.max(0) - everything.min(0)).max())
    distance = 4.0 * extent
    focal = size * distance / (1.15 * extent)
    K = np.array([[focal, 0.0, (size - 1) / 2], [0.0, focal, (size - 1) / 2], [0.0, 0.0, 1.0]])
    views = [_look_from(center, np.array([0.0, -1.0, 0.0]), distance), _look_from(center, np.array([1.0, 0.0, 0.0]), distance)]
    rows = []
    for title, vertices, faces in meshes:
        gray = np.full((len(vertices), 3), 0.75)
        row = [(_render_colored(vertices, faces, gray, CameraRays(K, w2c, size, size, supersample=1)) * 255).round().astype(np.uint8)
               for w2c in views]
        image = np.ascontiguousarray(np.concatenate(row, axis=1))
        _text(image, f"{title}: front | side", (6, 16))
        rows.append(image)
    return np.concatenate(rows, axis=0)
