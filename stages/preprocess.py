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
    contact_sheet.png    frames with mask and projected skeleton, to check alignment by eye
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import trimesh

from igavatar.artifacts.atomic import atomic_directory
from igavatar.artifacts.targets import check_output_target
from igavatar.artifacts.manifest import MANIFEST_NAME, InputRecord, build_manifest, read_artifact
from igavatar.body.capsules import capsule_prior
from igavatar.body.skeleton import linear_blend_skinning
from igavatar.capture.body_fit import BODY_FIT_VERSION, BODY_FITS, fits_body, fitted_subject
from igavatar.capture.capture_v1 import CaptureV1, load_image, load_mask
from igavatar.capture.contact_sheet import contact_sheet
from igavatar.capture.importers import detect_layout, read_layout
from igavatar.capture.images import resize_image, resize_mask, resize_plan, scale_intrinsics, undistort
from igavatar.capture.segment import CLOTHING_BAND_M, GRABCUT_ITERATIONS, PosedBody, estimate_mask
from igavatar.capture.subject import CanonicalSubject, PosedSubject, canonicalize, subject_from_capture
from igavatar.capture.subject_skeleton import skeleton_subject
from igavatar.capture.subject_smpl import smpl_model_for
from igavatar.avatar.dataset import BODY_TEMPLATE_FILE, PRIOR_FILE
from igavatar.capture.ghost_limbs import GhostTest, PosedBones
from igavatar.capture.loose_clothing import LOOSE_DISTANCE_M, LOOSE_SHARE, loose_share
from igavatar.capture.visual_hull import MaskViews, grid_skin, hull_cells, hull_prior_mesh, search_box, spread_views
from igavatar.errors import InputError
from igavatar.geometry.projection import project_points
from igavatar.skinning.bone_weights import BoneWeightConfig, build_bone_skinning_grid
from igavatar.skinning.grid import build_skinning_grid, canonical_grid_box, sample_skinning_weights
from stages.common import StageClock, skipped, unchanged
from stages.progress import NULL_PROGRESS, ProgressSink
from stages.resources import peak_ram_bytes
from stages.video import VideoOptions, run_video_capture

#: Margin (meters) around the template for clothing, hair and loose garments.
BOX_MARGIN_M = 0.12
#: The skinning grid's box (and so the SDF's, which stays inside it) keeps at least this much room
#: beyond the prior on every side. Fast-SNARF's depth squeeze alone left 2.3 cm behind the back of
#: a heavy template whose feet stand ahead of its belly, and its clothed back, 3.4 cm out, was cut
#: flat; clothes the template prior keeps lie within LOOSE_DISTANCE_M (4 cm) of it.
GRID_MARGIN_M = 0.06
#: A bare skeleton's shape prior is the masks' visual hull when at least this many training frames
#: vote (fewer views leave a hull too coarse to trust; capsules around the bones are used then).
MIN_HULL_VIEWS = 8
#: At most this many training frames (evenly spaced) vote on the hull, which bounds time and memory.
MAX_HULL_VIEWS = 64
#: --shape-prior: auto = the body model's template, or the masks' visual hull when the masks show
#: clothing or hair the template cannot grow into (igavatar.capture.loose_clothing) or when there is
#: no template (else capsules); template = the template always; visual-hull = the hull even over a
#: tight template (it bounds clothes and hair), with the template's skinning weights.
SHAPE_PRIORS = ("auto", "template", "visual-hull")
#: Bump when auto's choice between the template and the hull changes.
LOOSE_RULE_VERSION = 1
#: Bump when the bare-skeleton prior changes (2: space that skinning crushes is not kept;
#: 3: space that skinning lands inside another limb is not kept; 4: body_template.ply beside it;
#: 5: crushed space that kept cells wall in, the inside of a skirt, is kept).
HULL_PRIOR_VERSION = 5
#: The hull's skinning-grid box: depth half-size = 1.2 x the largest half-extent / this.
HULL_BOX_SQUEEZE = 3.0
#: Grid spacing (meters) of the hull prior.
HULL_CELL_M = 0.02
#: Blur passes over a template's skinning-weight grid unless --weight-smoothing says otherwise.
#: InstantAvatar's 30 passes (sigma ~15 cm at the default grid's ~3.4 cm cells) blend the thighs
#: and the arms into the torso; 15 gave 2-3 mm lower out-of-distribution CD-L1 and +0.04 IoU on
#: three subjects x two seeds, in-distribution unchanged (tests/benchmarks/results/weight-smoothing.md).
#: Fewer passes (2, 8) were better still on two subjects but cut a foot off the third.
TEMPLATE_WEIGHT_SMOOTHING = 15
#: --weight-spread's default: near a template, weights by the distance-adaptive kernel with this
#: growth, handing over to the blurred grid further out (None: the blurred grid everywhere). Spread 1
#: lowered out-of-distribution CD-L1 on all nine (subject, seed) runs and removed most of the
#: leg-gap web; the foot one run lost with it was the hash table's dense-Adam drift, gone with
#: tiny-cuda-nn's sparse rule (tests/benchmarks/results/weight-spread.md, sparse-adam.md).
TEMPLATE_WEIGHT_SPREAD: float | None = 1.0
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


@dataclass(frozen=True)
class WeightBlur:
    """How the skinning-weight grid is made smooth: blur passes (None: the source's default) and,
    for a template, the growth of the distance-adaptive kernel used near the body (None: none)."""

    passes: int | None = None
    spread: float | None = None


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


def _squeeze_axis(vertices: torch.Tensor) -> int:
    """The body's thinnest axis (its depth in canonical space: Y for Anny, Z for SMPL)."""
    return int((vertices.amax(0) - vertices.amin(0)).argmin())


def _segmentation_body(subject: PosedSubject, canonical: CanonicalSubject, index: int) -> PosedBody:
    """Frame `index`'s posed body for GrabCut seeding: the skinned template, else the skeleton."""
    if canonical.template_vertices is not None:
        posed = linear_blend_skinning(
            canonical.template_vertices, subject.template_weights, canonical.bone_transforms[index]
        )
        return PosedBody(vertices=posed.double().numpy(), faces=subject.template_faces.numpy())
    return PosedBody(joints=canonical.posed_joints[index].double().numpy(), parents=subject.skeleton.parents)


@dataclass(frozen=True)
class ShapePrior:
    """The canonical shape prior and what is sized from it (float32 / int64 CPU tensors).

    Attributes:
        vertices, faces: (V, 3), (F, 3) the prior mesh written as template.ply.
        kind: "template" | "visual_hull" | "capsules" (manifest data "shape_prior").
        box_min, box_max: (3,) the skinning grid's box.
        skinning_grid: (J, D, H, W) weights over that box.
        posed_boxes: (N, 2, 3) world boxes of the prior in every frame, padded by BOX_MARGIN_M.
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    kind: str
    box_min: torch.Tensor
    box_max: torch.Tensor
    skinning_grid: torch.Tensor
    posed_boxes: torch.Tensor

    def canonical_box(self) -> torch.Tensor:
        """(2, 3) the SDF's box: the prior plus BOX_MARGIN_M, inside the skinning grid's box."""
        lo = torch.maximum(self.vertices.amin(0) - BOX_MARGIN_M, self.box_min)
        hi = torch.minimum(self.vertices.amax(0) + BOX_MARGIN_M, self.box_max)
        return torch.stack((lo, hi))


def _padded(boxes: torch.Tensor) -> torch.Tensor:
    """(N, 2, 3) boxes grown by BOX_MARGIN_M on every side (a new tensor)."""
    return torch.stack((boxes[:, 0] - BOX_MARGIN_M, boxes[:, 1] + BOX_MARGIN_M), dim=1)


def _weights_grid(subject: PosedSubject, canonical: CanonicalSubject, box_min: torch.Tensor, box_max: torch.Tensor,
                  resolution: tuple[int, int, int], blur: WeightBlur = WeightBlur()) -> torch.Tensor:
    """(J, D, H, W) skinning weights over a box: the template's, or for a bare skeleton the bones'.

    `blur.passes` None keeps each source's default (TEMPLATE_WEIGHT_SMOOTHING for a template,
    BoneWeightConfig's for bones); the spread applies to a template only (bones have no vertices).
    """
    if canonical.template_vertices is not None:
        passes = TEMPLATE_WEIGHT_SMOOTHING if blur.passes is None else blur.passes
        return build_skinning_grid(canonical.template_vertices, subject.template_weights, box_min, box_max, resolution,
                                   smoothing_iterations=passes, spread=blur.spread)
    config = BoneWeightConfig() if blur.passes is None else BoneWeightConfig(smoothing_iterations=blur.passes)
    return build_bone_skinning_grid(canonical.canonical_joints, subject.skeleton, box_min, box_max, resolution, config)


def _body_prior(subject: PosedSubject, canonical: CanonicalSubject, resolution: tuple[int, int, int],
                blur: WeightBlur) -> ShapePrior:
    """The body model's template, or for a bare skeleton capsules around its bones."""
    if canonical.template_vertices is not None:
        vertices, faces, kind = canonical.template_vertices, subject.template_faces, "template"
        posed_boxes = canonical.posed_template_boxes
    else:
        capsules = capsule_prior(subject.skeleton, canonical.canonical_joints, canonical.bone_transforms)
        vertices, faces, kind = capsules.vertices, capsules.faces, "capsules"
        posed_boxes = capsules.posed_boxes  # joints alone miss the crown, hands and feet
    box_min, box_max = canonical_grid_box(vertices, squeeze_axis=_squeeze_axis(vertices), margin=GRID_MARGIN_M)
    return ShapePrior(vertices, faces, kind, box_min, box_max, _weights_grid(subject, canonical, box_min, box_max, resolution, blur), _padded(posed_boxes))


def _hull_prior(
    subject: PosedSubject,
    canonical: CanonicalSubject,
    views: list[int],
    masks: dict[int, np.ndarray],
    K: np.ndarray,
    w2c: np.ndarray,
    resolution: tuple[int, int, int],
    blur: WeightBlur,
) -> ShapePrior | None:
    """The masks' visual hull as the shape prior, or None when the masks keep nothing.

    The skinning weights (the template's, or the bones') skin a generous search box
    (igavatar.capture.visual_hull.search_box) into the voting frames; the kept cells' mesh then
    sizes the final boxes and weight grid, and its vertices skinned into every frame give the
    posed boxes.
    """
    lo, hi = search_box(canonical.canonical_joints)
    search_weights = _weights_grid(subject, canonical, lo, hi, resolution, blur)
    skin = grid_skin(search_weights, lo, hi, canonical.bone_transforms)
    mask_views = MaskViews(masks=[masks[i] for i in views], K=K[views], w2c=w2c[views], frames=views)
    # Cells that ride rigidly into another limb (ghost legs beside spread canonical legs) are dropped.
    ghost_test = GhostTest(
        bones=PosedBones.from_skeleton(subject.skeleton, canonical.canonical_joints, canonical.bone_transforms),
        weights=lambda x: sample_skinning_weights(search_weights, lo, hi, x),
    )
    hull = hull_prior_mesh(hull_cells(torch.stack((lo, hi)), skin, mask_views, cell_size=HULL_CELL_M, ghost_test=ghost_test))
    if hull is None:
        return None
    vertices = hull.vertices
    # Squeezed less than a template's box: a hull is deeper than the body it bounds.
    box_min, box_max = canonical_grid_box(vertices, squeeze_axis=_squeeze_axis(vertices), squeeze=HULL_BOX_SQUEEZE,
                                          margin=GRID_MARGIN_M)
    grid = _weights_grid(subject, canonical, box_min, box_max, resolution, blur)
    skin = grid_skin(grid, box_min, box_max, canonical.bone_transforms)
    posed = [skin(i, vertices) for i in range(canonical.bone_transforms.shape[0])]
    posed_boxes = torch.stack([torch.stack((p.amin(0), p.amax(0))) for p in posed])
    return ShapePrior(vertices, hull.faces, "visual_hull", box_min, box_max, grid, _padded(posed_boxes))


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
        config["loose_clothing"] = {"version": LOOSE_RULE_VERSION, "distance_m": LOOSE_DISTANCE_M, "share": LOOSE_SHARE}
    if not has_template or options.shape_prior != "template":
        # The prior is computed here, not read: a change to how it is made must redo the dataset.
        config["hull_prior"] = {"version": HULL_PRIOR_VERSION, "cell_m": HULL_CELL_M, "min_views": MIN_HULL_VIEWS}
    if not capture.has_masks:
        config["segmentation"] = {"method": "grabcut", "band_m": CLOTHING_BAND_M, "iterations": GRABCUT_ITERATIONS}
    return config


def _hull_views(capture: CaptureV1, canonical: CanonicalSubject, options: PreprocessOptions) -> list[int]:
    """Training frames whose masks vote for the visual hull; [] when the prior is the body model's.

    A bare skeleton's capsules are a sliver around a lone root and a naked stick figure elsewhere:
    its prior is the masks' visual hull, made once the masks are read. With a template and
    `auto`, the same views' masks decide whether the hull replaces it (`_loose_clothing`).
    """
    train_names = set(capture.splits["train"])
    train_frames = [i for i, name in enumerate(capture.frames) if name in train_names]
    use_hull = canonical.template_vertices is None or options.shape_prior != "template"
    views = spread_views(train_frames, MAX_HULL_VIEWS) if use_hull else []
    if len(views) >= MIN_HULL_VIEWS:
        return views
    if options.shape_prior == "visual-hull":
        raise InputError(
            f"--shape-prior visual-hull: the capture has {len(train_frames)} training frames, and the hull needs at "
            f"least {MIN_HULL_VIEWS} views to vote; leave --shape-prior at auto (the body model's template)"
        )
    return []


def _loose_clothing(subject: PosedSubject, canonical: CanonicalSubject, views: list[int], masks: dict[int, np.ndarray],
                    K: np.ndarray, w2c: np.ndarray) -> float:
    """Mean share of the views' subject pixels LOOSE_DISTANCE_M outside the posed template's silhouette."""
    bodies = []
    for i in views:
        body = _segmentation_body(subject, canonical, i)
        bodies.append((body.vertices, body.faces, canonical.posed_joints[i][0].double().numpy()))
    return loose_share([masks[i] for i in views], bodies, K[views], w2c[views])


def _frame_mask(capture: CaptureV1, i: int, rgb: np.ndarray, mask: np.ndarray, K: np.ndarray, subject: PosedSubject,
                canonical: CanonicalSubject) -> np.ndarray:
    """The frame's mask at the dataset's size: given, or cut by GrabCut around the posed body; never empty."""
    frame = capture.frames[i]
    if not capture.has_masks:
        mask = estimate_mask(rgb, K[i], capture.w2c[i], _segmentation_body(subject, canonical, i))
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
            cv2.imwrite(str(tmp / "images" / f"{frame}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
            cv2.imwrite(str(tmp / "masks" / f"{frame}.png"), mask.astype(np.uint8) * 255)
            if i in sheet_frames:
                joints_uv, _ = project_points(K[i], capture.w2c[i], canonical.posed_joints[i].double().numpy())
                sheet_items.append((rgb, mask, joints_uv, frame if capture.has_masks else f"{frame} (est.)"))
            advance(1)
    sheet = contact_sheet(sheet_items, subject.skeleton.parents)
    cv2.imwrite(str(tmp / "contact_sheet.png"), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
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
        # A video's poses are igavatar's own estimate: `train` refines them by default.
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
    hull_views = _hull_views(capture, canonical, options)
    scale_xy, size_hw = resize_plan(capture.height, capture.width, options.max_size)
    K = scale_intrinsics(capture.K, scale_xy)
    with atomic_directory(out, kind="dataset", inputs=output_inputs) as tmp:
        with clock("frames_s"):
            hull_masks = _write_frames(tmp, capture, subject, canonical, K, size_hw, hull_views, progress)
        loose = None
        if hull_views and canonical.template_vertices is not None and options.shape_prior == "auto":
            loose = _loose_clothing(subject, canonical, hull_views, hull_masks, K, capture.w2c)
            if loose < LOOSE_SHARE:
                hull_views = []  # tight clothes: the naked template is the better prior
        with clock("skinning_grid_s"):
            prior = _hull_prior(subject, canonical, hull_views, hull_masks, K, capture.w2c, options.grid_resolution,
                                options.weight_blur) if hull_views else None
            if prior is None:
                prior = _body_prior(subject, canonical, options.grid_resolution, options.weight_blur)
        _write_arrays(tmp, capture, subject, canonical, prior, K)
        data = _dataset_data(capture, input_format, subject, canonical, prior, size_hw, scale_xy[0], options)
        if loose is not None:
            data["loose_clothing"] = {"share": round(loose, 5), "threshold": LOOSE_SHARE, "distance_m": LOOSE_DISTANCE_M}
        build_manifest("dataset", tmp, stage="preprocess", config=config, inputs=inputs, data=data, seed=None,
                       device="cpu", timings=clock.finish(), peak_memory={"ram_bytes": peak_ram_bytes()})
    return {
        "dataset": str(out), "frames": len(capture.frames), "train": len(capture.splits["train"]),
        "test": len(capture.splits.get("test", [])), "image_size": f"{size_hw[1]}x{size_hw[0]}",
        "joints": subject.skeleton.num_joints, "contact_sheet": str(out / "contact_sheet.png"),
        "seconds": round(clock.elapsed(), 2), **({"video": video_summary} if video_summary else {}),
    }
