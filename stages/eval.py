"""`igavatar eval`: a model artifact + ground-truth scans -> a report artifact (metrics, tables, plots).

    summary = run_eval(EvalOptions(model=Path("igavatar-run/model"), out=Path("igavatar-run/report")))
    document = json.loads((Path(summary["report"]) / "metrics.json").read_text())

Report layout (schema `report`, version 1):
    metrics.json              every metric per test frame and its mean, each with protocol, units,
                              coordinate frame and background (EVAL.md); the manifest's `data` is the
                              same document without the per-frame list
    report.md                 means, scan matching, a per-frame table, notes, the paper's numbers
    plots/metric_curves.png   per-frame curve of every metric (OpenCV; matplotlib is not a dependency)
    images/<frame>.png        ground truth | render | mean absolute RGB error (JET, red >= 0.25)
    geometry/<frame>.png      scan | posed prediction colored by its distance to the scan | legend
    geometry/worst_<frame>.ply  the worst frame's posed prediction with those vertex colors

What is compared (EVAL.md): the test frames of the dataset the model was trained on (their cameras,
bone transforms, pose conditioning, images and masks). The prediction is the canonical mesh
(marching cubes once, largest component) posed per frame by skinning with the non-rigid offsets,
in world coordinates; each frame is matched by name to `<gt>/<frame>.ply|.obj`. A missing scan or
an extra one is listed in the report, never skipped silently. Images are rendered on white and
compared with the ground truth composited on white through its mask.

Error colors: the mesh panels color every predicted vertex by its distance to the scan (exact
distance to the faces near it, found through a k-d tree of scan samples; see
`igavatar.metrics.frame_geometry.vertex_distance_to_scan`) and ray cast both meshes from the test camera (Embree). A PLY with the same
colors is written only for the worst frame (30 colored meshes would dwarf the report).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import trimesh

from igavatar.artifacts.atomic import atomic_directory
from igavatar.artifacts.manifest import InputRecord, build_manifest, validate_against
from igavatar.artifacts.targets import check_output_target
from igavatar.artifacts.png import write_png
from igavatar.avatar.dataset import DatasetArtifact, DatasetFrames, read_dataset
from igavatar.avatar.model import ModelArtifact, ModelManifest, load_model, read_model_manifest
from igavatar.avatar.surfaces import canonical_surface
from igavatar.capture.images import scale_intrinsics
from igavatar.capture.scans import ScanMatching, default_gt_dir, load_scan, match_scans
from igavatar.errors import InputError
from igavatar.mesh.cleanup import clean_mesh, is_watertight
from igavatar.metrics.frame_geometry import frame_geometry
from igavatar.metrics.image import evaluate_image, side_by_side
from igavatar.metrics.lpips_scorer import lpips_scorer
from igavatar.metrics.report import (
    METRIC_KEYS,
    METRICS,
    error_colors,
    error_mesh_panel,
    markdown_report,
    mean_over_frames,
    metric_curves_image,
)
from igavatar.model.avatar import SURFACE_LEVELS
from igavatar.model.render_avatar import render_posed_view
from igavatar.avatar.canonical_report import canonical_section
from stages.common import StageClock, skipped, unchanged
from stages.eval_poses import refined_posed, refinement_notes
from stages.kernels import build_kernels, resolve_device
from stages.progress import NULL_PROGRESS, ProgressSink
from stages.resources import peak_cuda_bytes, peak_ram_bytes, require_marching_memory

#: Distance (mm) shown fully red in the error-colored mesh panels.
ERROR_VMAX_MM = 20.0
#: Longest side (pixels) of the error-colored mesh panels.
ERROR_PANEL_MAX_SIDE = 512
#: Mean absolute RGB error shown fully red in the image panels.
IMAGE_ERROR_VMAX = 0.25
#: Smallest rendered side: SSIM needs an 11 x 11 window.
MIN_IMAGE_SIDE = 16


@dataclass(frozen=True)
class EvalOptions:
    """Options of `igavatar eval` (see the CLI for each one's help)."""

    model: Path
    out: Path
    gt: Path | None = None
    dataset: Path | None = None
    geometry: bool = True
    images: bool = True
    mesh_resolution: int = 256
    surface_samples: int = 10_000
    iou_points: int = 1_000_000
    iou_open_meshes: bool = False
    image_scale: float | None = None
    samples_per_ray: int | None = None
    image_frames: int | None = None
    seed: int = 0
    device: str = "auto"
    surface_level: str = SURFACE_LEVELS[0]
    """Where meshes are made: "silhouette" or "zero" (igavatar.model.avatar.SURFACE_LEVELS)."""
    refine_test_poses: bool = False
    """Refine each rendered test frame's pose against its image first (image metrics only)."""
    refine_test_pose_steps: int = 80
    force: bool = False
    """Redo even if the report is up to date (same model, dataset, scans and options)."""

    def config(self) -> dict:
        """The options that change the numbers (recorded in the manifest)."""
        return {
            "geometry": self.geometry, "images": self.images, "mesh_resolution": self.mesh_resolution,
            "surface_samples": self.surface_samples, "iou_points": self.iou_points,
            "iou_open_meshes": self.iou_open_meshes, "image_scale": self.image_scale,
            "samples_per_ray": self.samples_per_ray, "image_frames": self.image_frames, "seed": self.seed,
            "device": self.device,
            "test_time_pose_refinement": self.refine_test_poses,
            **({"test_pose_steps": self.refine_test_pose_steps} if self.refine_test_poses else {}),
            "surface_level": self.surface_level,
        }


# ----------------------------------------------------------------------------- inputs


def resolve_dataset(model: ModelManifest, override: Path | None) -> Path:
    """The dataset the model was trained on (manifest data.dataset), or --dataset."""
    if override is not None:
        if not Path(override).exists():
            raise InputError(f"--dataset {override}: no such dataset directory")
        return Path(override)
    found = model.trained_dataset()
    if found is None:
        recorded = model.recorded_dataset
        raise InputError(
            f"{model.path}/manifest.json: data.dataset = {recorded} does not exist (nor {model.path.parent / recorded.name}); "
            "pass the dataset the model was trained on with --dataset"
        )
    return found


def _check_compatible(model: ModelArtifact, dataset: DatasetArtifact) -> None:
    for key, ours, theirs in (("joint_names", model.joint_names, dataset.recorded_joint_names), ("pose_dim", model.pose_dim, dataset.pose_dim)):
        if ours != theirs:
            raise InputError(
                f"--dataset {dataset.path}: its {key} differs from the model's ({model.path}); "
                "evaluate with the dataset the model was trained on"
            )


def render_size(dataset_hw: tuple[int, int], scale: float) -> tuple[int, int]:
    h, w = (max(MIN_IMAGE_SIDE, round(side * scale)) for side in dataset_hw)
    return int(h), int(w)


def _without_missing_scans(options: EvalOptions) -> tuple[EvalOptions, str | None]:
    """Geometry off, and why, when no --gt was given and the dataset has no scans (a video, a
    real capture): its images are still scored."""
    if not options.geometry or options.gt is not None:
        return options, None
    dataset = read_dataset(resolve_dataset(read_model_manifest(Path(options.model)), options.dataset))
    if dataset.data.get("has_scans", True):
        return options, None
    return (dataclasses.replace(options, geometry=False),
            f"{dataset.path}: the capture had no ground-truth scans, so geometry is not evaluated (pass --gt DIR "
            "to score it against scans of your own); images are")


def _check_options(options: EvalOptions) -> None:
    if not (options.geometry or options.images):
        raise InputError("--no-geometry and --no-images together leave nothing to evaluate")
    if options.mesh_resolution < 16:
        raise InputError(f"--mesh-resolution {options.mesh_resolution}: expected >= 16")
    if options.surface_samples < 1:
        raise InputError(f"--surface-samples {options.surface_samples}: expected >= 1")
    if options.iou_points < 0:
        raise InputError(f"--iou-points {options.iou_points}: expected >= 0 (0 skips the IoU)")
    if options.image_scale is not None and not 0 < options.image_scale <= 1:
        raise InputError(f"--image-scale {options.image_scale}: expected a fraction in (0, 1]")
    if options.samples_per_ray is not None and options.samples_per_ray < 1:
        raise InputError(f"--samples {options.samples_per_ray}: expected >= 1")
    if options.refine_test_poses and not options.images:
        raise InputError("--refine-test-poses refines poses for the image metrics; it needs --images")
    if options.refine_test_pose_steps < 1:
        raise InputError(f"--refine-test-pose-steps {options.refine_test_pose_steps}: expected >= 1")
    if options.image_frames is not None and options.image_frames < 0:
        raise InputError(f"--image-frames {options.image_frames}: expected >= 0 (0 = every test frame)")
    if options.surface_level not in SURFACE_LEVELS:
        raise InputError(f"--surface-level {options.surface_level!r}: choose one of {', '.join(SURFACE_LEVELS)}")


@dataclass(frozen=True)
class ImageSettings:
    """How test frames are rendered: resolved from the options and the device."""

    scale: float
    """Fraction of the dataset's image size."""
    samples_per_ray: int
    max_frames: int
    """Frames rendered, evenly spaced over the test frames (0 = all)."""


#: Defaults when an option is not given. Volume rendering with root finding costs ~20 s per
#: 128 x 128 frame at 32 samples on two CPU cores, so on a CPU the demo's 30 test frames are
#: rendered at a quarter of 512 px, and only 10 of them; a GPU renders every frame at full size.
IMAGE_DEFAULTS = {"cpu": ImageSettings(0.25, 32, 10), "cuda": ImageSettings(1.0, 128, 0)}


def resolve_image_settings(options: EvalOptions, device: torch.device) -> ImageSettings:
    """The options' image settings, each missing one taken from IMAGE_DEFAULTS for the device."""
    default = IMAGE_DEFAULTS["cuda" if device.type == "cuda" else "cpu"]
    return ImageSettings(
        scale=options.image_scale if options.image_scale is not None else default.scale,
        samples_per_ray=options.samples_per_ray if options.samples_per_ray is not None else default.samples_per_ray,
        max_frames=options.image_frames if options.image_frames is not None else default.max_frames,
    )


def image_frame_indices(n_frames: int, max_frames: int) -> set[int]:
    """Indices of the frames to render: all, or `max_frames` evenly spaced (first and last included)."""
    if max_frames <= 0 or max_frames >= n_frames:
        return set(range(n_frames))
    return {int(i) for i in np.linspace(0, n_frames - 1, max_frames).round()}


@dataclass(frozen=True)
class _Inputs:
    """What `eval` reads before it loads the model: the dataset, its test frames and the scans."""

    model_dir: Path
    dataset: DatasetArtifact
    test: DatasetFrames
    gt_dir: Path | None
    matching: ScanMatching | None


def _read_inputs(options: EvalOptions, progress: ProgressSink) -> _Inputs:
    model_dir, out = Path(options.model), Path(options.out)
    model_manifest = read_model_manifest(model_dir)
    dataset = read_dataset(resolve_dataset(model_manifest, options.dataset))
    check_output_target(out, "report", [model_dir, dataset.path, options.gt])
    if options.geometry:
        require_marching_memory(model_manifest.canonical_box, options.mesh_resolution,
                                f"--mesh-resolution {options.mesh_resolution} (the marching-cubes grid)")
    frames = dataset.frames()
    if not frames.test_indices:
        raise InputError(f"{dataset.path}: the dataset has no test frames (splits.test is empty); nothing to evaluate")
    test = frames.select(frames.test_indices)
    if not options.geometry:
        return _Inputs(model_dir, dataset, test, None, None)
    gt_dir = Path(options.gt) if options.gt is not None else default_gt_dir(dataset.path, dataset.manifest)
    matching = match_scans(gt_dir, list(test.names), list(frames.names))
    if matching.missing:
        progress.status(f"{len(matching.missing)} test frame(s) have no scan in {gt_dir}: {', '.join(matching.missing[:5])}")
    if matching.extra:
        progress.status(f"{len(matching.extra)} scan(s) in {gt_dir} name no frame of the dataset: {', '.join(matching.extra[:5])}")
    return _Inputs(model_dir, dataset, test, gt_dir, matching)


# ----------------------------------------------------------------------------- canonical shape


@dataclass(frozen=True)
class _CanonicalGeometry:
    """The canonical mesh (largest component) and the report's canonical section and picture."""

    vertices: np.ndarray
    faces: np.ndarray
    record: dict
    section: dict | None
    picture: np.ndarray | None


def _canonical_geometry(model: ModelArtifact, inputs: _Inputs, options: EvalOptions, clock: StageClock,
                        notes: list[str], progress: ProgressSink) -> _CanonicalGeometry:
    progress.status(f"canonical mesh: marching cubes at {options.mesh_resolution}")
    with clock("canonical_mesh_s"):
        # Closed by the canonical box, as `export` makes it: a surface that reaches the box (a sole,
        # a finger tip) is capped there, so that the posed meshes have an inside for the IoU.
        raw_v, raw_f = canonical_surface(model.avatar, resolution=options.mesh_resolution,
                                         surface_level=options.surface_level)
        if raw_f.shape[0] == 0:
            raise InputError(f"{inputs.model_dir}: the model's SDF has no surface in its canonical box (empty mesh); "
                             "the model is not trained enough to evaluate its geometry (use --no-geometry)")
        vertices, faces, cleanup = clean_mesh(raw_v, raw_f, keep_largest=True)
    record = {
        "canonical_vertices": int(vertices.shape[0]), "canonical_faces": int(faces.shape[0]),
        "components_dropped": cleanup["components_dropped"], "faces_dropped": cleanup["faces_dropped_in_components"],
        "watertight": is_watertight(vertices, faces),
        "surface_level": options.surface_level, "surface_level_m": model.avatar.surface_level(options.surface_level),
    }
    notes.append(
        f"pre-filter: the canonical mesh's largest component was kept; {cleanup['components_dropped']} other "
        f"component(s) with {cleanup['faces_dropped_in_components']} faces were dropped"
    )
    if not record["watertight"]:
        notes.append("the predicted mesh is not watertight (the surface reaches the canonical box or has holes)")
    with clock("canonical_checks_s"):
        capture_dir = inputs.gt_dir.parent if inputs.gt_dir is not None and inputs.gt_dir.name == "scans" else None
        section, picture = canonical_section(inputs.dataset, capture_dir, (vertices, faces),
                                             n_iou=min(options.iou_points, 200_000), seed=options.seed)
    return _CanonicalGeometry(vertices, faces, record, section, picture)


# ----------------------------------------------------------------------------- test frames


@dataclass(frozen=True)
class _ImagePlan:
    """Which test frames are rendered, at what size, and the mesh panels' size."""

    settings: ImageSettings
    frames: set[int]
    size_hw: tuple[int, int]
    dataset_hw: tuple[int, int]
    panel_hw: tuple[int, int]

    def scale_xy(self, size_hw: tuple[int, int]) -> tuple[float, float]:
        return size_hw[1] / self.dataset_hw[1], size_hw[0] / self.dataset_hw[0]


def _image_plan(options: EvalOptions, device: torch.device, dataset: DatasetArtifact, n_frames: int) -> _ImagePlan:
    settings = resolve_image_settings(options, device)
    dataset_hw = dataset.image_size
    frames = image_frame_indices(n_frames, settings.max_frames) if options.images else set()
    # Mesh panels are ray cast (cheap), so they keep the dataset's resolution up to 512 px.
    panel_hw = render_size(dataset_hw, min(1.0, ERROR_PANEL_MAX_SIDE / max(dataset_hw)))
    return _ImagePlan(settings, frames, render_size(dataset_hw, settings.scale), dataset_hw, panel_hw)


def _evaluate_frame(tmp: Path, i: int, model: ModelArtifact, inputs: _Inputs, canonical: _CanonicalGeometry | None,
                    plan: _ImagePlan, lpips_fn, options: EvalOptions) -> tuple[dict, np.ndarray | None, np.ndarray | None]:
    """One test frame's record; with geometry, its posed vertices and their error (mm)."""
    test, device = inputs.test, model.device
    name = test.names[i]
    record: dict[str, Any] = {"frame": name, "scan": None, "values": {k: None for k in METRIC_KEYS},
                              "notes": [], "geometry": None, "image": None, "files": {}, "seconds": {}}
    posed = model.posed(torch.from_numpy(test.bone_transforms[i]), torch.from_numpy(test.pose_condition[i]))
    posed_v = error_mm = None
    if canonical is not None and name not in inputs.matching.matched:
        record["notes"].append(f"no scan named {name}.ply/.obj in {inputs.gt_dir}: geometry not evaluated")
    elif canonical is not None:
        tick = time.perf_counter()
        posed_v = posed.pose_vertices(canonical.vertices)
        record["seconds"]["posing"] = time.perf_counter() - tick
        error_mm = _frame_geometry_record(
            record, posed_v.astype(np.float64), canonical.faces, inputs.matching.matched[name], options,
            scale_intrinsics(test.K[i].astype(np.float64), plan.scale_xy(plan.panel_hw)),
            test.w2c[i].astype(np.float64), plan.panel_hw, tmp,
        )
    if i in plan.frames:
        tick = time.perf_counter()
        if options.refine_test_poses:
            posed = refined_posed(record, model, inputs.dataset, test, i, options.refine_test_pose_steps,
                                  options.seed + i)
        size_hw = plan.size_hw
        render = render_posed_view(
            posed, model.canonical_grid,
            torch.from_numpy(scale_intrinsics(test.K[i].astype(np.float64), plan.scale_xy(size_hw))).float().to(device),
            torch.from_numpy(test.w2c[i]).float().to(device), size_hw[0], size_hw[1],
            torch.from_numpy(test.posed_boxes[i]).float().to(device),
            num_samples=plan.settings.samples_per_ray, occupancy_resolution=model.config.occupancy_resolution,
        )
        _frame_image_record(record, render, inputs.dataset.image_on_white(name, size_hw), lpips_fn, tmp)
        record["seconds"]["render"] = time.perf_counter() - tick
    for key, value in record["values"].items():
        if value is not None and not math.isfinite(value):
            record["values"][key] = None
            record["notes"].append(f"{key} is not finite ({value}); left out of the mean")
    return record, posed_v, error_mm


def _write_figures(tmp: Path, document: dict, records: list[dict], names: list[str],
                   worst: tuple[float, str, np.ndarray, np.ndarray] | None, canonical: _CanonicalGeometry | None) -> None:
    """Per-frame curves, the worst frame's colored mesh and the canonical views; listed in document["files"]."""
    series = {k: [r["values"][k] for r in records] for k in METRIC_KEYS if any(r["values"][k] is not None for r in records)}
    if series:
        curves = metric_curves_image(names, series, {k: document["metrics"][k]["mean"] for k in series})
        write_png(tmp / "plots" / "metric_curves.png", curves)
        document["files"]["per-frame curves"] = "plots/metric_curves.png"
    if worst is not None:
        _, name, posed_v, error_mm = worst
        colors = (error_colors(error_mm, ERROR_VMAX_MM) * 255).round().astype(np.uint8)
        trimesh.Trimesh(posed_v, canonical.faces, vertex_colors=colors, process=False).export(tmp / "geometry" / f"worst_{name}.ply")
        document["files"]["worst frame mesh (vertex colors = distance to scan)"] = f"geometry/worst_{name}.ply"
    if canonical is not None and canonical.section is not None:
        document["canonical"] = canonical.section
    if canonical is not None and canonical.picture is not None:
        write_png(tmp / "geometry" / "canonical_views.png", canonical.picture)
        document["files"]["canonical mesh, front and side, beside the truth and the template"] = "geometry/canonical_views.png"


def _input_records(inputs: _Inputs) -> list[InputRecord]:
    """The report's inputs: the model, the dataset and the scans (their hashes say which ground
    truth the numbers are against)."""
    records = [InputRecord(inputs.model_dir, "model"), InputRecord(inputs.dataset.path, "dataset")]
    return records + [InputRecord(path) for path in (inputs.matching.matched.values() if inputs.matching else ())]


def run_eval(options: EvalOptions, progress: ProgressSink = NULL_PROGRESS) -> dict:
    """Evaluate a model on its dataset's test frames and write the report artifact.

    Raises InputError/ArtifactError for bad inputs (nothing is written then).
    """
    clock = StageClock()
    options, skipped_geometry = _without_missing_scans(options)
    _check_options(options)
    if skipped_geometry:
        progress.status(skipped_geometry)
    inputs = _read_inputs(options, progress)
    out = Path(options.out)
    records_in = _input_records(inputs)  # hashes the model, dataset and scans: once, for the skip and the manifest
    if not options.force and unchanged(out, "report", options.config(), records_in):
        return {**skipped("report", out), "table": str(out / "report.md")}
    device = resolve_device(options.device)
    build_kernels(device, progress)
    with clock("load_s"):
        model = load_model(inputs.model_dir, device)
        _check_compatible(model, inputs.dataset)
    notes: list[str] = [skipped_geometry] if skipped_geometry else []
    canonical = _canonical_geometry(model, inputs, options, clock, notes, progress) if options.geometry else None
    names = list(inputs.test.names)
    plan = _image_plan(options, device, inputs.dataset, len(names))
    lpips_fn, lpips_status = lpips_scorer(device) if options.images else (None, "not computed: --no-images")
    records: list[dict] = []
    worst: tuple[float, str, np.ndarray, np.ndarray] | None = None  # (CD-L1, frame, posed vertices, error mm)
    with atomic_directory(out, kind="report", inputs=[inputs.model_dir, inputs.dataset.path, inputs.gt_dir]) as tmp:
        with progress.task("evaluating test frames", total=len(names)) as advance:
            for i, name in enumerate(names):
                record, posed_v, error_mm = _evaluate_frame(tmp, i, model, inputs, canonical, plan, lpips_fn, options)
                score = record["values"]["chamfer_l1_surface_mm"]
                if posed_v is not None and (worst is None or score > worst[0]):
                    worst = (score, name, posed_v, error_mm)
                records.append(record)
                advance(1, frame=name)
        for part in ("posing", "geometry", "render"):
            clock.add(f"{part}_s", sum(r["seconds"].get(part, 0.0) for r in records))
        if options.images and len(plan.frames) < len(names):
            notes.append(f"images: {len(plan.frames)} of {len(names)} test frames rendered, evenly spaced (--image-frames "
                         f"{plan.settings.max_frames}; 0 renders all)")
        document = _document(options, plan.settings, inputs.model_dir, inputs.dataset.path, inputs.gt_dir, names, records,
                             inputs.matching, canonical.record if canonical else None, notes, lpips_status, plan.size_hw,
                             plan.dataset_hw, str(device))
        _write_figures(tmp, document, records, names, worst, canonical)
        full = {**document, "frames": records}
        validate_against("report", full, f"{out}/metrics.json")
        (tmp / "metrics.json").write_text(json.dumps(full, indent=2) + "\n")
        (tmp / "report.md").write_text(markdown_report(full))
        build_manifest("report", tmp, stage="eval", config=options.config(), inputs=records_in, data=document,
                       seed=options.seed, device=str(device), timings=clock.finish(),
                       peak_memory={"ram_bytes": peak_ram_bytes(), "cuda_bytes": peak_cuda_bytes()})
    summary: dict[str, Any] = {"report": str(out), "table": str(out / "report.md"), "test_frames": len(records)}
    if inputs.matching is not None:
        summary.update(scans_matched=len(inputs.matching.matched), scans_missing=inputs.matching.missing,
                       scans_extra=inputs.matching.extra)
    summary.update(summary_of_metrics(document, len(records)))
    summary["seconds"] = round(clock.elapsed(), 1)
    return summary


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


def _frame_geometry_record(
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


def _frame_image_record(
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


def _document(
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
    notes = notes + [f"LPIPS {lpips_status}"] + refinement_notes(records)
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
