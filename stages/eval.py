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
    geometry/<frame>.png      scan | posed prediction coloured by its distance to the scan | legend
    geometry/worst_<frame>.ply  the worst frame's posed prediction with those vertex colours

What is compared (EVAL.md): the test frames of the dataset the model was trained on (their cameras,
bone transforms, pose conditioning, images and masks). The prediction is the canonical mesh
(marching cubes once, largest component) posed per frame by skinning with the non-rigid offsets,
in world coordinates; each frame is matched by name to `<gt>/<frame>.ply|.obj`. A missing scan or
an extra one is listed in the report, never skipped silently. Images are rendered on white and
compared with the ground truth composited on white through its mask.

Error colours: the mesh panels colour every predicted vertex by its distance to the scan (exact
distance to the faces near it, found through a k-d tree of scan samples; see
`vertex_distance_to_scan`) and ray cast both meshes from the test camera (Embree). A PLY with the same
colours is written only for the worst frame (30 coloured meshes would dwarf the report).
"""

from __future__ import annotations

import importlib.util
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from igavatar.artifacts.atomic import atomic_directory, atomic_write_bytes
from igavatar.artifacts.targets import check_output_target
from igavatar.artifacts.manifest import InputRecord, build_manifest, read_artifact, validate_against
from igavatar.capture.capture_v1 import CAPTURE_FILE
from igavatar.capture.images import resize_image, resize_mask, scale_intrinsics
from igavatar.capture.importers import detect_layout, read_layout
from igavatar.capture.xhumans import read_xhumans_scan
from igavatar.errors import ArtifactError, InputError
from igavatar.mesh.cleanup import clean_mesh, is_watertight
from igavatar.mesh.posing import canonical_mesh, pose_canonical_vertices
from igavatar.metrics.geometry import (
    closest_point_on_triangles,
    evaluate_meshes,
    sample_surface_uniform,
    volumetric_iou,
)
from igavatar.metrics.image import evaluate_image, side_by_side
from igavatar.metrics.report import (
    METRIC_KEYS,
    METRICS,
    error_colors,
    error_mesh_panel,
    markdown_report,
    mean_over_frames,
    metric_curves_image,
)
from igavatar.model.render_avatar import render_avatar_view
from stages.canonical_eval import canonical_section
from stages.kernels import build_kernels
from stages.model_io import LoadedModel, load_model
from stages.progress import NULL_PROGRESS, ProgressSink
from stages.resources import peak_cuda_bytes, peak_ram_bytes, require_marching_memory
from stages.train import resolve_device

#: Scan formats of a --gt folder; an imported capture (X-Humans) names its own scans (.pkl).
SCAN_SUFFIXES = (".ply", ".obj")
#: Distance (mm) shown fully red in the error-coloured mesh panels.
ERROR_VMAX_MM = 20.0
#: Scan samples whose faces the error colours are measured against.
ERROR_COLOUR_SAMPLES = 100_000
#: Longest side (pixels) of the error-coloured mesh panels.
ERROR_PANEL_MAX_SIDE = 512
#: Mean absolute RGB error shown fully red in the image panels.
IMAGE_ERROR_VMAX = 0.25
#: torchvision's AlexNet checkpoint that the `lpips` package loads (never downloaded here).
LPIPS_BACKBONE_FILE = "alexnet-owt-7be5be79.pth"
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

    def config(self) -> dict:
        """The options that change the numbers (recorded in the manifest)."""
        return {
            "geometry": self.geometry, "images": self.images, "mesh_resolution": self.mesh_resolution,
            "surface_samples": self.surface_samples, "iou_points": self.iou_points,
            "iou_open_meshes": self.iou_open_meshes, "image_scale": self.image_scale,
            "samples_per_ray": self.samples_per_ray, "image_frames": self.image_frames, "seed": self.seed,
            "device": self.device,
            "test_time_pose_refinement": False,
        }


# ----------------------------------------------------------------------------- inputs


@dataclass(frozen=True)
class ScanMatching:
    """Ground-truth scans matched to test frames by file stem.

    Attributes:
        matched: test frame -> scan path. missing: test frames with no scan.
        extra: scan stems that name no frame of the dataset. other_split: scan stems of dataset
        frames outside the test split (not evaluated). ignored_files: files that are not scans.
    """

    matched: dict[str, Path]
    missing: list[str]
    extra: list[str]
    other_split: list[str]
    ignored_files: list[str]

    def to_json(self) -> dict:
        return {"matched": sorted(self.matched), "missing": self.missing, "extra": self.extra,
                "other_split": self.other_split, "ignored_files": self.ignored_files}


def match_scans(gt_dir: Path, test_frames: list[str], all_frames: list[str]) -> ScanMatching:
    """Match `<gt_dir>/<frame>.ply|.obj` to the test frames; InputError if none matches.

    Args:
        gt_dir: directory of scans. test_frames: frames to evaluate, in order.
        all_frames: every frame of the dataset (to tell another split's scan from a stray one).
    """
    gt_dir = Path(gt_dir)
    if not gt_dir.is_dir():
        raise InputError(f"--gt {gt_dir}: no such directory of ground-truth scans (<frame>.ply or .obj)")
    scans: dict[str, Path] = {}
    ignored = []
    layout_scans = _layout_scans(gt_dir)
    if layout_scans is not None:
        scans = dict(layout_scans)
    for path in sorted(p for p in gt_dir.iterdir() if layout_scans is None and p.is_file() and not p.name.startswith(".")):
        if path.suffix.lower() not in SCAN_SUFFIXES:
            ignored.append(path.name)
            continue
        if path.stem in scans:
            raise InputError(
                f"--gt {gt_dir}: two scans for frame '{path.stem}' ({scans[path.stem].name} and {path.name}); keep one"
            )
        scans[path.stem] = path
    tests, known = set(test_frames), set(all_frames)
    matched = {f: scans[f] for f in test_frames if f in scans}
    if not matched:
        raise InputError(
            f"--gt {gt_dir}: no scan is named after a test frame (test frames: {', '.join(test_frames[:5])}"
            f"{', ...' if len(test_frames) > 5 else ''}; found {len(scans)} "
            f"{'scans in the capture' if layout_scans is not None else '.ply/.obj files'}); "
            "pass the scans folder of this capture, or --no-geometry"
        )
    return ScanMatching(
        matched=matched,
        missing=[f for f in test_frames if f not in scans],
        extra=sorted(s for s in scans if s not in known),
        other_split=sorted(s for s in scans if s in known and s not in tests),
        ignored_files=ignored,
    )


def _layout_scans(gt_dir: Path) -> dict[str, Path] | None:
    """frame -> scan of a capture in an imported layout that keeps its scans itself (X-Humans: one
    meshes_pkl/ folder per take), or None for a plain folder of <frame>.ply|.obj files."""
    if (gt_dir / CAPTURE_FILE).is_file():
        return None
    try:
        layout = detect_layout(gt_dir)
    except InputError:
        return None
    return read_layout(gt_dir, layout).scans


def load_scan(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64 metres and faces (F, 3) int64 of a PLY/OBJ scan or an X-Humans mesh
    pickle; InputError if unusable."""
    if Path(path).suffix.lower() == ".pkl":
        return read_xhumans_scan(Path(path))
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for a corrupt file; all mean "unreadable"
        raise InputError(f"{path}: cannot read the scan as a triangle mesh ({type(exc).__name__}: {exc})") from exc
    vertices = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), np.float64)
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), np.int64)
    if vertices.ndim != 2 or vertices.shape[0] == 0 or faces.ndim != 2 or faces.shape[0] == 0:
        raise InputError(f"{path}: the scan has {len(vertices)} vertices and {len(faces)} faces; expected a triangle mesh")
    if not np.all(np.isfinite(vertices)):
        raise InputError(f"{path}: the scan has NaN or infinite vertex coordinates")
    return vertices, faces


def _existing(path: Path, beside: Path) -> Path | None:
    """`path` if it exists, else a sibling of `beside` with the same name (a moved run directory)."""
    if path.exists():
        return path
    sibling = beside.parent / path.name
    return sibling if sibling.exists() else None


def resolve_dataset(model_dir: Path, manifest: dict, override: Path | None) -> Path:
    """The dataset the model was trained on (manifest data.dataset), or --dataset."""
    if override is not None:
        if not Path(override).exists():
            raise InputError(f"--dataset {override}: no such dataset directory")
        return Path(override)
    recorded = Path(manifest["data"]["dataset"])
    found = _existing(recorded, model_dir)
    if found is None:
        raise InputError(
            f"{model_dir}/manifest.json: data.dataset = {recorded} does not exist (nor {model_dir.parent / recorded.name}); "
            "pass the dataset the model was trained on with --dataset"
        )
    return found


def default_gt_dir(dataset_dir: Path, dataset_manifest: dict) -> Path:
    """`scans/` of the capture the dataset was made from (its manifest's first input)."""
    records = dataset_manifest.get("inputs", [])
    if not records:
        raise InputError(f"{dataset_dir}/manifest.json: no inputs recorded, so the capture is unknown; pass --gt")
    recorded = Path(records[0]["path"])
    # A capture without a manifest is recorded file by file: its first input is capture.json, or
    # for an imported layout a file in its root (whose scans match_scans finds by reading it).
    capture = recorded if records[0].get("artifact") == "capture" else recorded.parent
    found = _existing(capture, dataset_dir)
    if found is None:
        raise InputError(
            f"{dataset_dir}/manifest.json: the capture {capture} it was made from does not exist; pass --gt SCANS_DIR"
        )
    if dataset_manifest.get("data", {}).get("source_format", "capture-v1") != "capture-v1":
        return found
    return found / "scans"


def _check_compatible(model: LoadedModel, dataset_dir: Path, dataset_manifest: dict) -> None:
    model_data, data = model.manifest["data"], dataset_manifest["data"]
    for key in ("joint_names", "pose_dim"):
        if model_data[key] != data[key]:
            raise InputError(
                f"--dataset {dataset_dir}: its {key} differs from the model's ({model.path}); "
                "evaluate with the dataset the model was trained on"
            )


@dataclass(frozen=True)
class TestFrames:
    """The dataset's test frames (numpy, CPU)."""

    names: list[str]
    all_names: list[str]
    K: np.ndarray  # (N, 3, 3) at the dataset's resolution
    w2c: np.ndarray  # (N, 4, 4)
    bone_transforms: np.ndarray  # (N, J, 4, 4) canonical -> posed world
    pose_condition: np.ndarray  # (N, P)
    posed_boxes: np.ndarray  # (N, 2, 3)


def load_test_frames(dataset_dir: Path) -> TestFrames:
    frames = np.load(dataset_dir / "frames.npz")
    names = [str(n) for n in frames["frame_names"]]
    index = np.flatnonzero(frames["is_test"])
    if index.size == 0:
        raise InputError(f"{dataset_dir}: the dataset has no test frames (splits.test is empty); nothing to evaluate")
    return TestFrames(
        names=[names[i] for i in index], all_names=names, K=frames["K"][index].astype(np.float64),
        w2c=frames["w2c"][index].astype(np.float64), bone_transforms=frames["bone_transforms"][index],
        pose_condition=frames["pose_condition"][index], posed_boxes=frames["posed_boxes"][index],
    )


# ----------------------------------------------------------------------------- geometry


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Enclosed volume (m^3) by the divergence theorem: the integral of the winding number.

    For a watertight, consistently wound mesh this counts a region covered twice (a
    self-intersection) twice, whereas ray parity counts it zero times: comparing the two exposes
    self-intersections that make a parity inside test wrong.
    """
    tri = np.asarray(vertices, np.float64)[np.asarray(faces)]
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)


def volume_check(vertices: np.ndarray, faces: np.ndarray, n_inside: int, n_points: int, box_volume: float) -> dict:
    """Compare the parity (Monte Carlo) volume with the signed volume of one mesh.

    Args:
        vertices (V, 3), faces (F, 3): the mesh. n_inside, n_points: its parity count among the
        IoU's uniform points. box_volume: volume (m^3) of the box they were drawn in.
    Returns:
        {"signed_volume_m3", "parity_volume_m3", "consistent"}: consistent is False when the two
        differ by more than 4 Monte Carlo standard errors plus 1 %, i.e. when the inside test is
        unreliable (self-intersection, holes or inverted orientation).
    """
    fraction = n_inside / n_points
    parity = fraction * box_volume
    signed = signed_volume(vertices, faces)
    standard_error = box_volume * math.sqrt(max(fraction * (1 - fraction), 1.0 / n_points) / n_points)
    consistent = abs(parity - signed) <= 4 * standard_error + 0.01 * abs(signed)
    return {"signed_volume_m3": signed, "parity_volume_m3": parity, "consistent": bool(consistent)}


def vertex_distance_to_scan(
    vertices: np.ndarray, scan_vertices: np.ndarray, scan_faces: np.ndarray, seed: int, k: int = 4
) -> np.ndarray:
    """Distance (V,) in metres from each vertex to the scan, for the error colours.

    Args:
        vertices: (V, 3) query points. scan_vertices (Vg, 3), scan_faces (Fg, 3): the scan.
        seed: fixes the scan samples. k: nearest samples whose faces are tested exactly.
    Returns:
        (V,) the exact distance to the nearest of the faces holding the k nearest of
        ERROR_COLOUR_SAMPLES area-uniform scan samples: an upper bound on the point-to-face distance
        that equals it unless the closest face holds none of those samples. It costs one k-d tree
        query and V * k triangle tests, where the exact search of the metrics would dominate a
        frame's time when run from every predicted vertex.
    """
    samples, sample_face = sample_surface_uniform(scan_vertices, scan_faces, ERROR_COLOUR_SAMPLES,
                                                  np.random.default_rng([seed, 3]))
    _, nearest = cKDTree(samples).query(vertices, k=k)
    candidate_faces = scan_faces[sample_face[nearest.reshape(-1)]]  # (V * k, 3)
    tri = scan_vertices[candidate_faces]
    points = np.repeat(vertices, k, axis=0)
    closest = closest_point_on_triangles(points, tri[:, 0], tri[:, 1], tri[:, 2])
    return np.linalg.norm(closest - points, axis=1).reshape(-1, k).min(axis=1)


def frame_geometry(
    pred_vertices: np.ndarray, pred_faces: np.ndarray, gt_vertices: np.ndarray, gt_faces: np.ndarray,
    options: EvalOptions,
) -> tuple[dict[str, float | None], dict, list[str], np.ndarray]:
    """Every geometry metric of one frame, its diagnostics, notes and per-vertex error (mm).

    Args:
        pred_vertices (Vp, 3), pred_faces (Fp, 3): posed prediction (already its largest component).
        gt_vertices (Vg, 3), gt_faces (Fg, 3): the scan; both world coordinates, metres.
    Returns:
        (values by metric key, details dict, notes, pred vertex distance to the scan (Vp,) in mm).
    """
    metrics = evaluate_meshes((pred_vertices, pred_faces), (gt_vertices, gt_faces),
                              n_surface=options.surface_samples, n_iou=0, seed=options.seed)
    notes: list[str] = []
    iou_value: float | None = None
    iou_details: dict[str, Any] = {"pred_watertight": metrics.pred_watertight, "gt_watertight": metrics.gt_watertight}
    watertight = metrics.pred_watertight and metrics.gt_watertight
    if options.iou_points <= 0:
        iou_details["status"] = "not computed: --iou-points 0"
    elif not watertight and not options.iou_open_meshes:
        flags = (("prediction", metrics.pred_watertight), ("scan", metrics.gt_watertight))
        which = " and ".join(name for name, ok in flags if not ok)
        iou_details["status"] = (
            f"not computed: the {which} is not watertight (pass --iou-open-meshes for a ray-parity estimate)"
        )
        notes.append(f"IoU {iou_details['status']}")
    else:
        iou = volumetric_iou((pred_vertices, pred_faces), (gt_vertices, gt_faces), options.iou_points, options.seed,
                             require_watertight=False)
        iou_value = float(iou["iou"])
        box_volume = float(np.prod(np.subtract(iou["box_max"], iou["box_min"])))
        checks = {
            "pred": volume_check(pred_vertices, pred_faces, iou["n_inside_pred"], iou["n_points"], box_volume),
            "gt": volume_check(gt_vertices, gt_faces, iou["n_inside_gt"], iou["n_points"], box_volume),
        }
        reliable = watertight and all(c["consistent"] for c in checks.values())
        iou_details.update(
            status="computed" if reliable else "approximate", n_points=iou["n_points"],
            n_intersection=iou["n_intersection"], n_union=iou["n_union"], volume_check=checks,
        )
        if not watertight:
            notes.append("IoU is a ray-parity estimate on a mesh that is not watertight (--iou-open-meshes)")
        for name, check in checks.items():
            if not check["consistent"]:
                notes.append(
                    f"IoU approximate: the {'prediction' if name == 'pred' else 'scan'}'s parity volume "
                    f"{check['parity_volume_m3'] * 1e3:.2f} L differs from its signed volume "
                    f"{check['signed_volume_m3'] * 1e3:.2f} L (self-intersection or holes)"
                )
    distance = vertex_distance_to_scan(pred_vertices, gt_vertices, gt_faces, options.seed)
    pred_centre = 0.5 * (pred_vertices.min(0) + pred_vertices.max(0))
    gt_centre = 0.5 * (gt_vertices.min(0) + gt_vertices.max(0))
    offset = float(np.linalg.norm(pred_centre - gt_centre))
    if offset > 0.25:
        notes.append(
            f"the prediction's box centre is {offset:.2f} m from the scan's: wrong frame, units (metres expected) or pose?"
        )
    values = {
        "chamfer_l2_cm2": metrics.chamfer_l2_vertices_cm2,
        "normal_consistency_vertices": metrics.normal_consistency_vertices,
        "chamfer_l1_surface_mm": metrics.chamfer_l1_surface_mm,
        "normal_consistency_surface": metrics.normal_consistency_surface,
        "volumetric_iou": iou_value,
    }
    details = {
        "pred_to_gt_cm2": metrics.chamfer_l2_vertices_pred_to_gt_cm2,
        "gt_to_pred_cm2": metrics.chamfer_l2_vertices_gt_to_pred_cm2,
        "surface_pred_to_gt_mm": metrics.surface_pred_to_gt_mm,
        "surface_gt_to_pred_mm": metrics.surface_gt_to_pred_mm,
        "n_dropped_components": metrics.n_dropped_components,
        "pred_vertices": int(len(pred_vertices)), "gt_vertices": int(len(gt_vertices)),
        "box_centre_offset_m": offset,
        "pred_vertex_error_mm": {"median": float(np.median(distance) * 1e3), "p95": float(np.percentile(distance, 95) * 1e3)},
        "volumetric_iou": iou_details,
    }
    return values, details, notes, distance * 1e3


# ----------------------------------------------------------------------------- images


def lpips_scorer(device: torch.device) -> tuple[Callable[[np.ndarray, np.ndarray], float] | None, str]:
    """An LPIPS (AlexNet, v0.1) scorer built only from weights already on this machine.

    Returns:
        (score(pred, gt) -> float on (H, W, 3) [0, 1] RGB, status) or (None, why not). LPIPS needs
        the `lpips` package and torchvision's AlexNet checkpoint in the torch hub cache; nothing is
        downloaded, and without them the report says "not computed" (never a made-up value).
    """
    if importlib.util.find_spec("lpips") is None or importlib.util.find_spec("torchvision") is None:
        return None, ("not computed: the `lpips` and `torchvision` packages are not installed "
                      "(weights cannot be downloaded here)")
    backbone = Path(torch.hub.get_dir()) / "checkpoints" / LPIPS_BACKBONE_FILE
    if not backbone.is_file():
        return None, f"not computed: the AlexNet weights are not present locally ({backbone})"
    import lpips  # noqa: PLC0415 - optional dependency, imported only when its weights exist

    try:
        net = lpips.LPIPS(net="alex", version="0.1", verbose=False).to(device).eval()
    except (OSError, RuntimeError) as exc:
        return None, f"not computed: LPIPS could not load its local weights ({exc})"

    @torch.no_grad()
    def score(pred: np.ndarray, gt: np.ndarray) -> float:
        def to_tensor(rgb: np.ndarray) -> torch.Tensor:  # (H, W, 3) [0, 1] -> (1, 3, H, W) [-1, 1]
            return torch.from_numpy(np.ascontiguousarray(rgb, np.float32)).permute(2, 0, 1)[None].to(device) * 2 - 1

        return float(net(to_tensor(pred), to_tensor(gt)).item())

    return score, "computed: LPIPS AlexNet v0.1 (lpips package, local weights), inputs scaled to [-1, 1]"


def _ground_truth_on_white(dataset_dir: Path, name: str, size_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The dataset frame composited on white and resized: RGB (h, w, 3) float in [0, 1], mask (h, w) bool."""
    image_path, mask_path = dataset_dir / "images" / f"{name}.png", dataset_dir / "masks" / f"{name}.png"
    image = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
    mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
    if image is None or mask is None:
        raise ArtifactError(f"{image_path if image is None else mask_path}: unreadable; re-run `igavatar preprocess`")
    inside = mask > 127
    rgb = np.where(inside[..., None], cv2.cvtColor(image, cv2.COLOR_BGR2RGB), 255).astype(np.uint8)
    # Composite first, then area-resample, so that edge pixels blend with white as the render does.
    return resize_image(rgb, size_hw).astype(np.float64) / 255.0, resize_mask(inside, size_hw)


def render_size(dataset_hw: tuple[int, int], scale: float) -> tuple[int, int]:
    h, w = (max(MIN_IMAGE_SIDE, round(side * scale)) for side in dataset_hw)
    return int(h), int(w)


# ----------------------------------------------------------------------------- the stage


def _write_png(path: Path, rgb: np.ndarray) -> None:
    ok, data = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise InputError(f"{path}: PNG encoding failed")
    atomic_write_bytes(path, data.tobytes())


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
    if options.image_frames is not None and options.image_frames < 0:
        raise InputError(f"--image-frames {options.image_frames}: expected >= 0 (0 = every test frame)")


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


def run_eval(options: EvalOptions, progress: ProgressSink = NULL_PROGRESS) -> dict:
    """Evaluate a model on its dataset's test frames and write the report artifact.

    Raises InputError/ArtifactError for bad inputs (nothing is written then).
    """
    started = time.perf_counter()
    timings: dict[str, float] = {}
    _check_options(options)
    model_dir, out = Path(options.model), Path(options.out)
    model_manifest = read_artifact(model_dir, expected="model")
    dataset_dir = resolve_dataset(model_dir, model_manifest, options.dataset)
    dataset_manifest = read_artifact(dataset_dir, expected="dataset")
    check_output_target(out, "report", [model_dir, dataset_dir, options.gt])
    if options.geometry:
        require_marching_memory(model_manifest["data"]["canonical_box"], options.mesh_resolution,
                                f"--mesh-resolution {options.mesh_resolution} (the marching-cubes grid)")
    frames = load_test_frames(dataset_dir)
    matching: ScanMatching | None = None
    gt_dir: Path | None = None
    if options.geometry:
        gt_dir = Path(options.gt) if options.gt is not None else default_gt_dir(dataset_dir, dataset_manifest)
        matching = match_scans(gt_dir, frames.names, frames.all_names)
        if matching.missing:
            progress.status(
                f"{len(matching.missing)} test frame(s) have no scan in {gt_dir}: {', '.join(matching.missing[:5])}"
            )
        if matching.extra:
            progress.status(
                f"{len(matching.extra)} scan(s) in {gt_dir} name no frame of the dataset: {', '.join(matching.extra[:5])}"
            )
    device = resolve_device(options.device)
    build_kernels(device, progress)
    tick = time.perf_counter()
    model = load_model(model_dir, device)
    _check_compatible(model, dataset_dir, dataset_manifest)
    avatar = model.avatar
    timings["load_s"] = time.perf_counter() - tick

    notes: list[str] = []
    prediction_mesh = canonical = canonical_png = None
    canonical_v = canonical_f = None
    if options.geometry:
        tick = time.perf_counter()
        progress.status(f"canonical mesh: marching cubes at {options.mesh_resolution}")
        raw_v, raw_f = canonical_mesh(avatar, resolution=options.mesh_resolution)
        if raw_f.shape[0] == 0:
            raise InputError(f"{model_dir}: the model's SDF has no zero level set in its canonical box (empty mesh); "
                             "the model is not trained enough to evaluate its geometry (use --no-geometry)")
        canonical_v, canonical_f, cleanup = clean_mesh(raw_v, raw_f, keep_largest=True)
        prediction_mesh = {
            "canonical_vertices": int(canonical_v.shape[0]), "canonical_faces": int(canonical_f.shape[0]),
            "components_dropped": cleanup["components_dropped"],
            "faces_dropped": cleanup["faces_dropped_in_components"],
            "watertight": is_watertight(canonical_v, canonical_f),
        }
        notes.append(
            f"pre-filter: the canonical mesh's largest component was kept; {cleanup['components_dropped']} other "
            f"component(s) with {cleanup['faces_dropped_in_components']} faces were dropped"
        )
        if not prediction_mesh["watertight"]:
            notes.append("the predicted mesh is not watertight (the surface reaches the canonical box or has holes)")
        timings["canonical_mesh_s"] = time.perf_counter() - tick
        tick = time.perf_counter()
        capture_dir = gt_dir.parent if gt_dir is not None and gt_dir.name == "scans" else None
        canonical, canonical_png = canonical_section(dataset_dir, dataset_manifest, capture_dir, (canonical_v, canonical_f),
                                                     n_iou=min(options.iou_points, 200_000), seed=options.seed)
        timings["canonical_checks_s"] = time.perf_counter() - tick

    dataset_hw = tuple(int(s) for s in dataset_manifest["data"]["image_size"])
    image_settings = resolve_image_settings(options, device)
    rendered = image_frame_indices(len(frames.names), image_settings.max_frames) if options.images else set()
    size_hw = render_size(dataset_hw, image_settings.scale)
    scale_xy = (size_hw[1] / dataset_hw[1], size_hw[0] / dataset_hw[0])
    # Mesh panels are ray cast (cheap), so they keep the dataset's resolution up to 512 px.
    panel_hw = render_size(dataset_hw, min(1.0, ERROR_PANEL_MAX_SIDE / max(dataset_hw)))
    panel_scale_xy = (panel_hw[1] / dataset_hw[1], panel_hw[0] / dataset_hw[0])
    lpips_fn, lpips_status = (lpips_scorer(device) if options.images else (None, "not computed: --no-images"))

    records = []
    worst: tuple[float, str, np.ndarray, np.ndarray] | None = None  # (CD-L1, frame, posed vertices, error mm)
    with atomic_directory(out, kind="report", inputs=[model_dir, dataset_dir, gt_dir]) as tmp:
        with progress.task("evaluating test frames", total=len(frames.names)) as advance:
            for i, name in enumerate(frames.names):
                record: dict[str, Any] = {"frame": name, "scan": None, "values": {k: None for k in METRIC_KEYS},
                                          "notes": [], "geometry": None, "image": None, "files": {}, "seconds": {}}
                bone_transforms = torch.from_numpy(frames.bone_transforms[i]).float().to(device)
                pose = torch.from_numpy(frames.pose_condition[i]).float().to(device)
                if options.geometry and name not in matching.matched:
                    record["notes"].append(f"no scan named {name}.ply/.obj in {gt_dir}: geometry not evaluated")
                elif options.geometry:
                    tick = time.perf_counter()
                    posed_v = pose_canonical_vertices(avatar, canonical_v, avatar.deformer.prepare(bone_transforms), pose)
                    record["seconds"]["posing"] = time.perf_counter() - tick
                    error_mm = _frame_geometry_record(
                        record, posed_v.astype(np.float64), canonical_f, matching.matched[name], options,
                        scale_intrinsics(frames.K[i], panel_scale_xy), frames.w2c[i], panel_hw, tmp,
                    )
                    score = record["values"]["chamfer_l1_surface_mm"]
                    if worst is None or score > worst[0]:
                        worst = (score, name, posed_v, error_mm)
                if i in rendered:
                    tick = time.perf_counter()
                    render = render_avatar_view(
                        avatar, model.canonical_grid, bone_transforms, pose,
                        torch.from_numpy(scale_intrinsics(frames.K[i], scale_xy)).float().to(device),
                        torch.from_numpy(frames.w2c[i]).float().to(device), size_hw[0], size_hw[1],
                        torch.from_numpy(frames.posed_boxes[i]).float().to(device),
                        num_samples=image_settings.samples_per_ray, occupancy_resolution=model.config.occupancy_resolution,
                    )
                    _frame_image_record(record, render, _ground_truth_on_white(dataset_dir, name, size_hw), lpips_fn, tmp)
                    record["seconds"]["render"] = time.perf_counter() - tick
                for key, value in record["values"].items():
                    if value is not None and not math.isfinite(value):
                        record["values"][key] = None
                        record["notes"].append(f"{key} is not finite ({value}); left out of the mean")
                records.append(record)
                advance(1, frame=name)
        for stage_part in ("posing", "geometry", "render"):
            timings[f"{stage_part}_s"] = sum(r["seconds"].get(stage_part, 0.0) for r in records)

        if options.images and len(rendered) < len(frames.names):
            notes.append(
                f"images: {len(rendered)} of {len(frames.names)} test frames rendered, evenly spaced (--image-frames "
                f"{image_settings.max_frames}; 0 renders all)"
            )
        document = _document(options, image_settings, model_dir, dataset_dir, gt_dir, frames, records, matching,
                             prediction_mesh, notes, lpips_status, size_hw, dataset_hw, str(device))
        series = {k: [r["values"][k] for r in records] for k in METRIC_KEYS
                  if any(r["values"][k] is not None for r in records)}
        if series:
            curves = metric_curves_image(frames.names, series, {k: document["metrics"][k]["mean"] for k in series})
            _write_png(tmp / "plots" / "metric_curves.png", curves)
            document["files"]["per-frame curves"] = "plots/metric_curves.png"
        if worst is not None:
            _, name, posed_v, error_mm = worst
            colours = (error_colors(error_mm, ERROR_VMAX_MM) * 255).round().astype(np.uint8)
            trimesh.Trimesh(posed_v, canonical_f, vertex_colors=colours, process=False).export(
                tmp / "geometry" / f"worst_{name}.ply")
            document["files"]["worst frame mesh (vertex colours = distance to scan)"] = f"geometry/worst_{name}.ply"
        if canonical is not None:
            document["canonical"] = canonical
        if canonical_png is not None:
            _write_png(tmp / "geometry" / "canonical_views.png", canonical_png)
            document["files"]["canonical mesh, front and side, beside the truth and the template"] = "geometry/canonical_views.png"
        full = {**document, "frames": records}
        validate_against("report", full, f"{out}/metrics.json")
        (tmp / "metrics.json").write_text(json.dumps(full, indent=2) + "\n")
        (tmp / "report.md").write_text(markdown_report(full))
        timings["total_s"] = time.perf_counter() - started
        # The scans are inputs too: their hashes say which ground truth these numbers are against.
        inputs = [InputRecord(model_dir, "model"), InputRecord(dataset_dir, "dataset")]
        inputs += [InputRecord(path) for path in (matching.matched.values() if matching is not None else ())]
        build_manifest(
            "report", tmp, stage="eval", config=options.config(), inputs=inputs, data=document, seed=options.seed,
            device=str(device), timings=timings,
            peak_memory={"ram_bytes": peak_ram_bytes(), "cuda_bytes": peak_cuda_bytes()},
        )

    summary: dict[str, Any] = {"report": str(out), "table": str(out / "report.md"), "test_frames": len(records)}
    if matching is not None:
        summary.update(scans_matched=len(matching.matched), scans_missing=matching.missing, scans_extra=matching.extra)
    for key in METRIC_KEYS:
        entry = document["metrics"][key]
        summary[key] = round(entry["mean"], 4) if entry["mean"] is not None else entry["status"]
    summary["seconds"] = round(time.perf_counter() - started, 1)
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
    _write_png(tmp / "geometry" / f"{name}.png", panel)
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
    _write_png(tmp / "images" / f"{name}.png", side_by_side(gt_rgb, pred_rgb, IMAGE_ERROR_VMAX))
    record["files"]["side_by_side"] = f"images/{name}.png"


def _document(
    options: EvalOptions, image_settings: ImageSettings, model_dir: Path, dataset_dir: Path, gt_dir: Path | None,
    frames: TestFrames,
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
    notes = notes + [f"LPIPS {lpips_status}"]
    return {
        "inputs": {"model": str(model_dir), "dataset": str(dataset_dir), "gt": str(gt_dir) if gt_dir else None},
        "frame_names": frames.names,
        "settings": {
            "geometry": options.geometry, "images": options.images, "mesh_resolution": options.mesh_resolution,
            "surface_samples": options.surface_samples, "iou_points": options.iou_points,
            "iou_open_meshes": options.iou_open_meshes, "seed": options.seed, "image_scale": image_settings.scale,
            "image_size": list(size_hw), "dataset_image_size": list(dataset_hw),
            "samples_per_ray": image_settings.samples_per_ray,
            "image_frames": sum(r["image"] is not None for r in records), "background": "white",
            "test_time_pose_refinement": False,
            "error_vmax_mm": ERROR_VMAX_MM, "image_error_vmax": IMAGE_ERROR_VMAX, "bbox_pad": 0, "device": device,
        },
        "prediction_mesh": prediction_mesh,
        "gt_matching": matching.to_json() if matching is not None else None,
        "metrics": metrics,
        "lpips": {"computed": lpips_status.startswith("computed"), "status": lpips_status},
        "notes": notes,
        "files": {"metrics": "metrics.json", "tables": "report.md"},
    }
