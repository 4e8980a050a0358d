"""`igavatar preprocess`: a capture -> a dataset artifact that `train` reads without body models.

    summary = run_preprocess(PreprocessOptions(capture=Path("run/capture"), out=Path("run/dataset")))

Dataset layout (schema `dataset`, version 1):
    images/<frame>.png   RGB, resized so the longer side <= max_size, undistorted
    masks/<frame>.png    0/255: the capture's masks, or when it has none, GrabCut's around the posed
                         body (manifest data "masks": "given" | "estimated (grabcut)")
    frames.npz           frame_names (N,), K (N,3,3), w2c (N,4,4), bone_transforms (N,J,4,4)
                         canonical -> posed world, pose_condition (N,pose_dim), posed_boxes (N,2,3),
                         posed_joints (N,J,3), is_train (N,), is_test (N,)
    subject.npz          parents (J,), rest_joints (J,3), canonical_joints (J,3), joint_names (J,),
                         canonical_rotations (J,3,3) of the canonical pose relative to the rest pose,
                         init_bones (I,) major bones root finding starts from,
                         skinning_grid (J,D,H,W), grid_box_min (3,), grid_box_max (3,),
                         canonical_box (2,3)
    template.ply         canonical shape prior: the body model's template mesh (for a bare skeleton of
                         Anny's or SMPL's kind, Anny fitted to its joints: manifest data
                         subject.body_fit), or the masks' visual hull in canonical space for a bare
                         skeleton without a body (--body-fit none, unknown kind) or for clothing the template
                         cannot grow into (capsules around a bare skeleton's bones when fewer than
                         MIN_HULL_VIEWS training frames can vote) (manifest data "shape_prior":
                         "template" | "visual_hull" | "capsules"; "loose_clothing" says why)
    body_template.ply    the body model's naked template in the canonical pose, when the shape prior
                         is not that template: eval's limb check reads it
    body_weights.npz     weights (V, J): the naked template's skinning weights, when there is one
                         (`train --refine-poses` votes the prior again on its fitted poses)
    contact_sheet.png    frames with mask and projected skeleton, to check alignment by eye
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from igavatar.artifacts.atomic import atomic_directory
from igavatar.artifacts.targets import check_output_target
from igavatar.artifacts.png import write_png
from igavatar.artifacts.manifest import MANIFEST_NAME, InputRecord, build_manifest, read_artifact
from igavatar.capture.body_fit import BODY_FIT_VERSION, BODY_FITS, fits_body, fitted_subject
from igavatar.capture.capture_v1 import CaptureV1, load_image, load_mask
from igavatar.capture.contact_sheet import contact_sheet
from igavatar.capture.importers import detect_layout, read_layout
from igavatar.capture.images import resize_image, resize_mask, resize_plan, scale_intrinsics, undistort
from igavatar.capture.segment import CLOTHING_BAND_M, GRABCUT_ITERATIONS, estimate_mask
from igavatar.capture.subject import CanonicalSubject, PosedSubject, canonicalize, subject_from_capture
from igavatar.capture.subject_skeleton import skeleton_subject
from igavatar.capture.subject_smpl import smpl_model_for
from igavatar.avatar.dataset import BODY_TEMPLATE_FILE, BODY_WEIGHTS_FILE, PRIOR_FILE
from igavatar.capture.loose_clothing import LOOSE_DISTANCE_M, LOOSE_OVER_SPILL, LOOSE_SHARE
from igavatar.capture.shape_prior import (
    BOX_MARGIN_M, GRID_MARGIN_M, HULL_CELL_M, HULL_PRIOR_VERSION, LOOSE_RULE_VERSION, MIN_HULL_VIEWS, SHAPE_PRIORS,
    TEMPLATE_WEIGHT_SMOOTHING, TEMPLATE_WEIGHT_SPREAD, PriorBody, ShapePrior, WeightBlur, body_prior, hull_prior, hull_views,
    posed_template_fit, segmentation_body,
)
from igavatar.errors import InputError
from igavatar.geometry.projection import project_points
from igavatar.skinning.bone_weights import BoneWeightConfig
from stages.common import StageClock, skipped, unchanged
from stages.progress import NULL_PROGRESS, ProgressSink
from stages.resources import peak_ram_bytes
from stages.video import VideoOptions, run_video_capture

CONTACT_SHEET_FRAMES = 12


@dataclass(frozen=True)
class PreprocessOptions:
    """Options of `igavatar preprocess` (see the CLI for each one's help)."""

    capture: Path
    out: Path
    input_format: str = "auto"
    max_size: int = 512
    grid_resolution: tuple[int, int, int] = (64, 16, 64)
    weight_smoothing: int | None = None
    weight_spread: float | None = None
    anny_cache: Path | None = None
    smpl_model: Path | None = None
    shape_prior: str = "auto"
    body_fit: str = "anny"
    force: bool = False
    #: A clip to make the capture from first (written at `capture`), or None to read `capture`.
    video: VideoOptions | None = None

    def config(self) -> dict:
        """The options that change the dataset (recorded in the manifest, compared to skip)."""
        return {
            "input_format": self.input_format, "max_size": self.max_size,
            "grid_resolution": list(self.grid_resolution), "box_margin_m": BOX_MARGIN_M, "grid_margin_m": GRID_MARGIN_M,
            # Only when not the default, so that datasets made before the option keep their config.
            **({"shape_prior": self.shape_prior} if self.shape_prior != "auto" else {}),
            # The passes actually used, so that a change of the defaults makes a new dataset.
            "weight_smoothing": self.weight_smoothing if self.weight_smoothing is not None else
            f"default: template {TEMPLATE_WEIGHT_SMOOTHING}, bones {BoneWeightConfig().smoothing_iterations}",
            # Only when set, so that datasets made with inverse-distance weights keep their config.
            **({"weight_spread": spread} if (spread := self.weight_blur.spread) is not None else {}),
        }

    @property
    def weight_blur(self) -> WeightBlur:
        spread = TEMPLATE_WEIGHT_SPREAD if self.weight_spread is None else self.weight_spread
        # --weight-spread 0 turns the kernel off: the blurred grid everywhere.
        return WeightBlur(self.weight_smoothing, spread if spread else None)


def parse_grid_resolution(text: str) -> tuple[int, int, int]:
    """'64,16,64' -> (64, 16, 64); InputError for anything else."""
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or min(values) < 2:
        raise InputError(f"--grid-resolution {text!r}: expected three integers >= 2 as D,H,W (e.g. 64,16,64)")
    return values  # type: ignore[return-value]


def detect_format(capture: Path, requested: str) -> str:
    """The input layout: `requested` unless 'auto' (see igavatar.capture.importers)."""
    if capture.is_dir() and (capture / MANIFEST_NAME).is_file():
        # An artifact: it must be a capture, and intact (hashes), before anything reads it.
        read_artifact(capture, expected="capture")
    return detect_layout(capture, requested)


def _input_records(capture: CaptureV1, smpl_model: Path | None = None) -> list[InputRecord]:
    if (capture.root / MANIFEST_NAME).is_file():
        records = [InputRecord(capture.root, "capture")]
    else:
        records = [InputRecord(p) for p in capture.input_files()]
    if capture.body_model == "smpl":
        # The user's SMPL file shapes the template and the skeleton: a different file is a new dataset.
        records.append(InputRecord(smpl_model_for(capture, smpl_model)))
    return records


def _fits_body(capture: CaptureV1, options: PreprocessOptions) -> bool:
    """Whether preprocess fits Anny to the capture's skeleton (a bare skeleton of a known kind)."""
    if options.body_fit not in BODY_FITS:
        raise InputError(f"--body-fit {options.body_fit!r}: choose one of {', '.join(BODY_FITS)}")
    return capture.body_model == "skeleton" and options.body_fit == "anny" and fits_body(skeleton_subject(capture))


def _dataset_config(options: PreprocessOptions, capture: CaptureV1, input_format: str) -> dict:
    """Everything that shapes the dataset (the manifest's config; compared to skip an unchanged run)."""
    if options.shape_prior not in SHAPE_PRIORS:
        raise InputError(f"--shape-prior {options.shape_prior!r}: choose one of {', '.join(SHAPE_PRIORS)}")
    config = options.config() | {"input_format": input_format}
    fitted = _fits_body(capture, options)
    has_template = capture.body_model != "skeleton" or fitted
    if fitted:
        config["body_fit"] = {"model": "anny", "version": BODY_FIT_VERSION}
    if not has_template and options.shape_prior == "template":
        raise InputError(
            "--shape-prior template: the capture has a bare skeleton and no body is fitted to it (--body-fit none, "
            "or a skeleton whose joints are neither Anny's nor SMPL's); leave --shape-prior at auto (the masks' "
            "visual hull) or give SMPL/Anny poses"
        )
    if has_template and options.shape_prior == "auto":
        # The masks decide between the template and the hull: a change to the rule redoes the dataset.
        config["loose_clothing"] = {"version": LOOSE_RULE_VERSION, "distance_m": LOOSE_DISTANCE_M, "share": LOOSE_SHARE,
                                    "loose_over_spill": LOOSE_OVER_SPILL}
    if not has_template or options.shape_prior != "template":
        # The prior is computed here, not read: a change to how it is made must redo the dataset.
        config["hull_prior"] = {"version": HULL_PRIOR_VERSION, "cell_m": HULL_CELL_M, "min_views": MIN_HULL_VIEWS}
    if not capture.has_masks:
        config["segmentation"] = {"method": "grabcut", "band_m": CLOTHING_BAND_M, "iterations": GRABCUT_ITERATIONS}
    return config


def _frame_mask(capture: CaptureV1, i: int, rgb: np.ndarray, mask: np.ndarray, K: np.ndarray, subject: PosedSubject,
                canonical: CanonicalSubject) -> np.ndarray:
    """The frame's mask at the dataset's size: given, or cut by GrabCut around the posed body; never empty."""
    frame = capture.frames[i]
    if not capture.has_masks:
        mask = estimate_mask(rgb, K[i], capture.w2c[i], segmentation_body(subject, canonical, i))
        if not mask.any():
            raise InputError(
                f"{capture.image_path(frame)}: no subject found where the posed body projects; check "
                "that the poses and cameras put the body in view, or give masks"
            )
    if not mask.any():
        raise InputError(
            f"{capture.mask_path(frame)}: the mask of frame {frame} is empty (no subject pixels); "
            "give a mask with the subject in white (255), drop the frame from capture.json, "
            "or remove masks/ to have them estimated"
        )
    return mask


def _write_frames(tmp: Path, capture: CaptureV1, subject: PosedSubject, canonical: CanonicalSubject, K: np.ndarray,
                  size_hw: tuple[int, int], hull_views: list[int], progress: ProgressSink) -> dict[int, np.ndarray]:
    """images/ and masks/ at the dataset's size and the contact sheet; returns the hull views' masks."""
    (tmp / "images").mkdir()
    (tmp / "masks").mkdir()
    n_frames = len(capture.frames)
    sheet_frames = set(np.linspace(0, n_frames - 1, min(CONTACT_SHEET_FRAMES, n_frames)).round().astype(int))
    sheet_items, hull_masks = [], {}
    task = "resizing frames" if capture.has_masks else "resizing frames, segmenting the subject"
    with progress.task(task, total=n_frames) as advance:
        for i, frame in enumerate(capture.frames):
            rgb = load_image(capture.image_path(frame), (capture.height, capture.width))
            if capture.has_masks:
                mask = load_mask(capture.mask_path(frame), (capture.height, capture.width))
            else:
                mask = np.ones((capture.height, capture.width), bool)  # replaced after resizing
            dist = capture.frame_dist(i)
            if dist is not None:
                rgb, mask = undistort(rgb, mask, capture.K[i], dist)
            rgb, mask = resize_image(rgb, size_hw), resize_mask(mask, size_hw)
            mask = _frame_mask(capture, i, rgb, mask, K, subject, canonical)
            if i in hull_views:
                hull_masks[i] = mask
            write_png(tmp / "images" / f"{frame}.png", rgb)
            write_png(tmp / "masks" / f"{frame}.png", mask.astype(bool))
            if i in sheet_frames:
                joints_uv, _ = project_points(K[i], capture.w2c[i], canonical.posed_joints[i].double().numpy())
                sheet_items.append((rgb, mask, joints_uv, frame if capture.has_masks else f"{frame} (est.)"))
            advance(1)
    sheet = contact_sheet(sheet_items, subject.skeleton.parents)
    write_png(tmp / "contact_sheet.png", sheet)
    return hull_masks


def _write_arrays(tmp: Path, capture: CaptureV1, subject: PosedSubject, canonical: CanonicalSubject, prior: ShapePrior,
                  K: np.ndarray) -> None:
    """frames.npz, subject.npz and template.ply (the shape prior's mesh)."""
    splits = capture.splits
    np.savez_compressed(
        tmp / "frames.npz",
        frame_names=np.array(capture.frames, dtype=np.str_),
        K=K.astype(np.float32), w2c=capture.w2c.astype(np.float32),
        bone_transforms=canonical.bone_transforms.numpy().astype(np.float32),
        pose_condition=canonical.pose_condition.numpy().astype(np.float32),
        posed_boxes=prior.posed_boxes.numpy().astype(np.float32),
        posed_joints=canonical.posed_joints.numpy().astype(np.float32),
        is_train=np.isin(capture.frames, splits["train"]),
        is_test=np.isin(capture.frames, splits.get("test", [])),
    )
    np.savez_compressed(
        tmp / "subject.npz",
        parents=subject.skeleton.parents.astype(np.int64),
        rest_joints=np.asarray(subject.skeleton.rest_joints, np.float32),
        canonical_joints=canonical.canonical_joints.numpy().astype(np.float32),
        canonical_rotations=subject.canonical_rotations.numpy().astype(np.float32),
        joint_names=np.array(subject.skeleton.joint_names, dtype=np.str_),
        init_bones=np.array(subject.init_bones, dtype=np.int64),
        skinning_grid=prior.skinning_grid.numpy().astype(np.float32),
        grid_box_min=prior.box_min.numpy().astype(np.float32), grid_box_max=prior.box_max.numpy().astype(np.float32),
        canonical_box=prior.canonical_box().numpy().astype(np.float32),
    )
    trimesh.Trimesh(prior.vertices.numpy(), prior.faces.numpy(), process=False).export(tmp / PRIOR_FILE)
    if canonical.template_vertices is not None:
        np.savez_compressed(tmp / BODY_WEIGHTS_FILE, weights=subject.template_weights.numpy().astype(np.float32))
    if prior.kind != "template" and canonical.template_vertices is not None:
        trimesh.Trimesh(canonical.template_vertices.numpy(), subject.template_faces.numpy(),
                        process=False).export(tmp / BODY_TEMPLATE_FILE)


def _dataset_data(capture: CaptureV1, input_format: str, subject: PosedSubject, canonical: CanonicalSubject,
                  prior: ShapePrior, size_hw: tuple[int, int], scale: float, options: PreprocessOptions) -> dict:
    """The dataset manifest's data."""
    frame_index = set(capture.frames)
    return {
        "source_format": input_format,
        "body_model": subject.body_model,
        "frames": capture.frames,
        "splits": {k: [f for f in v if f in frame_index] for k, v in capture.splits.items()},
        "image_size": [size_hw[0], size_hw[1]],
        "scale": scale,
        "joint_names": list(subject.skeleton.joint_names),
        "pose_dim": int(canonical.pose_condition.shape[1]),
        "skinning_grid": {
            "resolution": list(options.grid_resolution),
            "box_min": prior.box_min.tolist(), "box_max": prior.box_max.tolist(),
        },
        "canonical_box": prior.canonical_box().tolist(),
        "has_template": True,
        "shape_prior": prior.kind,
        "has_scans": bool(capture.scans),
        # Without masks, each frame's mask is cut by GrabCut around the posed body (igavatar.capture.segment).
        "masks": "given" if capture.has_masks else "estimated (grabcut)",
        # A video's poses are igavatar's own estimate (`train --refine-poses` can correct them; off by default).
        "poses": "estimated" if capture.input_format == "video" else "given",
        "subject": json.loads(json.dumps(subject.description)),
    }


def run_preprocess(options: PreprocessOptions, progress: ProgressSink = NULL_PROGRESS) -> dict:
    """Read the capture, pose its body model, resize images, build the skinning grid, write the dataset.

    Returns a JSON-able summary (paths, counts, seconds). Raises InputError/ArtifactError/
    BodyModelError/NotAvailableError for problems a user can fix.
    """
    clock = StageClock()
    video_summary = run_video_capture(options.video, progress) if options.video is not None else None
    input_format = detect_format(Path(options.capture), options.input_format)
    capture = read_layout(Path(options.capture), input_format)
    config = _dataset_config(options, capture, input_format)
    inputs = _input_records(capture, options.smpl_model)
    out = Path(options.out)
    output_inputs = [capture.root, options.smpl_model]
    if not options.force and unchanged(out, "dataset", config, inputs):  # read-only, so before the target check
        return {**skipped("dataset", out), **({"video": video_summary} if video_summary else {})}
    check_output_target(out, "dataset", output_inputs)
    with clock("body_model_s"):
        subject = subject_from_capture(capture, options.anny_cache, progress.status, options.smpl_model)
        if "body_fit" in config:
            subject = fitted_subject(subject, options.anny_cache, progress.status)
            if subject.template_vertices_rest is None and options.shape_prior == "template":
                raise InputError(f"--shape-prior template: {subject.description['body_fit']['rejected']}")
        canonical = canonicalize(subject)
    voting = hull_views(capture, canonical, options.shape_prior)
    scale_xy, size_hw = resize_plan(capture.height, capture.width, options.max_size)
    K = scale_intrinsics(capture.K, scale_xy)
    with atomic_directory(out, kind="dataset", inputs=output_inputs) as tmp:
        with clock("frames_s"):
            hull_masks = _write_frames(tmp, capture, subject, canonical, K, size_hw, voting, progress)
        fit = None
        if voting and canonical.template_vertices is not None and options.shape_prior == "auto":
            fit = posed_template_fit(PriorBody.of(subject, canonical), voting, hull_masks, K, capture.w2c)
            if not fit.hull_is_better:
                voting = []  # tight clothes, or poses too far off for a hull: the naked template is the better prior
        with clock("skinning_grid_s"):
            prior = hull_prior(PriorBody.of(subject, canonical), voting, hull_masks, K, capture.w2c,
                               options.grid_resolution, options.weight_blur) if voting else None
            if prior is None:
                prior = body_prior(subject, canonical, options.grid_resolution, options.weight_blur)
        _write_arrays(tmp, capture, subject, canonical, prior, K)
        data = _dataset_data(capture, input_format, subject, canonical, prior, size_hw, scale_xy[0], options)
        if fit is not None:
            data["loose_clothing"] = {"share": round(fit.loose, 5), "threshold": LOOSE_SHARE, "distance_m": LOOSE_DISTANCE_M,
                                      "spill": round(fit.spill, 5), "loose_over_spill": LOOSE_OVER_SPILL}
        build_manifest("dataset", tmp, stage="preprocess", config=config, inputs=inputs, data=data, seed=None,
                       device="cpu", timings=clock.finish(), peak_memory={"ram_bytes": peak_ram_bytes()})
    return {
        "dataset": str(out), "frames": len(capture.frames), "train": len(capture.splits["train"]),
        "test": len(capture.splits.get("test", [])), "image_size": f"{size_hw[1]}x{size_hw[0]}",
        "joints": subject.skeleton.num_joints, "contact_sheet": str(out / "contact_sheet.png"),
        "seconds": round(clock.elapsed(), 2), **({"video": video_summary} if video_summary else {}),
    }
