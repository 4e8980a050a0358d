"""`igavatar eval`: a model artifact + ground-truth scans -> a report artifact (metrics, tables, plots).

    summary = run_eval(EvalOptions(model=Path("igavatar-run/model"), out=Path("igavatar-run/report")))
    document = json.loads((Path(summary["report"]) / "metrics.json").read_text())

The options and what they resolve to are stages.eval_options; one frame's record, the report
document and the console summary are stages.eval_records.

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
from igavatar.avatar.model import MODEL_PRIOR_FILE, ModelArtifact, load_model, read_model_manifest
from igavatar.avatar.surfaces import canonical_surface
from igavatar.capture.images import scale_intrinsics
from igavatar.capture.scans import ScanMatching, default_gt_dir, match_scans
from igavatar.errors import InputError
from igavatar.mesh.cleanup import clean_mesh, is_watertight
from igavatar.metrics.lpips_scorer import lpips_scorer
from igavatar.metrics.report import METRIC_KEYS, error_colors, markdown_report, metric_curves_image
from igavatar.model.render_avatar import render_posed_view
from igavatar.avatar.canonical_report import canonical_section
from stages.common import StageClock, skipped, unchanged
from stages.eval_options import (
    EvalOptions,
    ImageSettings,
    check_options,
    image_frame_indices,
    render_size,
    resolve_dataset,
    resolve_image_settings,
)
from stages.eval_poses import CarriedTestPoses, carried_poses, refined_posed
from stages.eval_records import (
    ERROR_PANEL_MAX_SIDE,
    ERROR_VMAX_MM,
    frame_geometry_record,
    frame_image_record,
    report_document,
    summary_of_metrics,
)
from stages.kernels import build_kernels, resolve_device
from stages.progress import NULL_PROGRESS, ProgressSink
from stages.resources import peak_cuda_bytes, peak_ram_bytes, require_marching_memory

def _check_compatible(model: ModelArtifact, dataset: DatasetArtifact) -> None:
    for key, ours, theirs in (("joint_names", model.joint_names, dataset.recorded_joint_names), ("pose_dim", model.pose_dim, dataset.pose_dim)):
        if ours != theirs:
            raise InputError(
                f"--dataset {dataset.path}: its {key} differs from the model's ({model.path}); "
                "evaluate with the dataset the model was trained on"
            )


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
                                             n_iou=min(options.iou_points, 200_000), seed=options.seed,
                                             trained_prior=inputs.model_dir / MODEL_PRIOR_FILE)
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


def _image_plan(options: EvalOptions, device: torch.device, dataset: DatasetArtifact, n_frames: int,
                model_samples: int) -> _ImagePlan:
    settings = resolve_image_settings(options, device, model_samples)
    dataset_hw = dataset.image_size
    frames = image_frame_indices(n_frames, settings.max_frames) if options.images else set()
    # Mesh panels are ray cast (cheap), so they keep the dataset's resolution up to 512 px.
    panel_hw = render_size(dataset_hw, min(1.0, ERROR_PANEL_MAX_SIDE / max(dataset_hw)))
    return _ImagePlan(settings, frames, render_size(dataset_hw, settings.scale), dataset_hw, panel_hw)


def _evaluate_frame(tmp: Path, i: int, model: ModelArtifact, inputs: _Inputs, poses: CarriedTestPoses,
                    canonical: _CanonicalGeometry | None, plan: _ImagePlan, lpips_fn,
                    options: EvalOptions) -> tuple[dict, np.ndarray | None, np.ndarray | None]:
    """One test frame's record; with geometry, its posed vertices and their error (mm)."""
    test, device = inputs.test, model.device
    name = test.names[i]
    record: dict[str, Any] = {"frame": name, "scan": None, "values": {k: None for k in METRIC_KEYS},
                              "notes": [], "geometry": None, "image": None, "files": {}, "seconds": {}}
    if poses.record(i) is not None:
        record["carried_pose"] = poses.record(i)
    posed = model.posed(torch.from_numpy(poses[i]), torch.from_numpy(test.pose_condition[i]))
    posed_v = error_mm = None
    if canonical is not None and name not in inputs.matching.matched:
        record["notes"].append(f"no scan named {name}.ply/.obj in {inputs.gt_dir}: geometry not evaluated")
    elif canonical is not None:
        tick = time.perf_counter()
        posed_v = posed.pose_vertices(canonical.vertices)
        record["seconds"]["posing"] = time.perf_counter() - tick
        error_mm = frame_geometry_record(
            record, posed_v.astype(np.float64), canonical.faces, inputs.matching.matched[name], options,
            scale_intrinsics(test.K[i].astype(np.float64), plan.scale_xy(plan.panel_hw)),
            test.w2c[i].astype(np.float64), plan.panel_hw, tmp,
        )
    if i in plan.frames:
        tick = time.perf_counter()
        if options.refine_test_poses:
            posed = refined_posed(record, model, inputs.dataset, test, i, poses[i], options.refine_test_pose_steps,
                                  options.seed + i)
        size_hw = plan.size_hw
        render = render_posed_view(
            posed, model.canonical_grid,
            torch.from_numpy(scale_intrinsics(test.K[i].astype(np.float64), plan.scale_xy(size_hw))).float().to(device),
            torch.from_numpy(test.w2c[i]).float().to(device), size_hw[0], size_hw[1],
            torch.from_numpy(test.posed_boxes[i]).float().to(device),
            num_samples=plan.settings.samples_per_ray, occupancy_resolution=model.config.occupancy_resolution,
        )
        frame_image_record(record, render, inputs.dataset.image_on_white(name, size_hw), lpips_fn, tmp)
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
    check_options(options)
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
    poses = carried_poses(model, inputs.dataset, inputs.test, options.carry_poses)
    plan = _image_plan(options, device, inputs.dataset, len(names), model.config.validation_samples)
    lpips_fn, lpips_status = lpips_scorer(device) if options.images else (None, "not computed: --no-images")
    records: list[dict] = []
    worst: tuple[float, str, np.ndarray, np.ndarray] | None = None  # (CD-L1, frame, posed vertices, error mm)
    with atomic_directory(out, kind="report", inputs=[inputs.model_dir, inputs.dataset.path, inputs.gt_dir]) as tmp:
        with progress.task("evaluating test frames", total=len(names)) as advance:
            for i, name in enumerate(names):
                record, posed_v, error_mm = _evaluate_frame(tmp, i, model, inputs, poses, canonical, plan, lpips_fn, options)
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
        document = report_document(options, plan.settings, inputs.model_dir, inputs.dataset.path, inputs.gt_dir, names, records,
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
