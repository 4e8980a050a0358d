"""The canonical shape prior of a dataset and the skinning grid sized from it: the body model's
template, the masks' visual hull (a bare skeleton, loose clothing) or capsules around the bones.

    prior = body_prior(subject, canonical, (64, 16, 64), WeightBlur())          # template or capsules
    views = hull_views(capture, canonical, "auto")                             # frames whose masks vote
    body = PriorBody.of(subject, canonical)                                    # or with other poses
    prior = hull_prior(body, views, masks, K, w2c, (64, 16, 64), WeightBlur()) or prior

The constants are the measured policy (`preprocess` records the versions in its manifest so that
a change redoes the dataset); docs/DESIGN.md "Geometry" and docs/RESEARCH.md give the measurements.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from igavatar.body.capsules import capsule_prior
from igavatar.body.skeleton import Skeleton, linear_blend_skinning
from igavatar.capture.capture_v1 import CaptureV1
from igavatar.capture.ghost_limbs import GhostTest, PosedBones
from igavatar.capture.loose_clothing import TemplateFit, template_fit
from igavatar.capture.posed_subject import CanonicalSubject, PosedSubject
from igavatar.capture.segment import PosedBody
from igavatar.capture.visual_hull import MaskViews, grid_skin, hull_cells, hull_prior_mesh, search_box, spread_views
from igavatar.errors import InputError
from igavatar.skinning.bone_weights import BoneWeightConfig, build_bone_skinning_grid
from igavatar.skinning.grid import build_skinning_grid, canonical_grid_box, sample_skinning_weights

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
#: Bump when auto's choice between the template and the hull changes (2: not when the template
#: spills past the masks nearly as far as they reach past it, igavatar.capture.loose_clothing.LOOSE_OVER_SPILL).
LOOSE_RULE_VERSION = 2
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
@dataclass(frozen=True)
class WeightBlur:
    """How the skinning-weight grid is made smooth: blur passes (None: the source's default) and,
    for a template, the growth of the distance-adaptive kernel used near the body (None: none)."""

    passes: int | None = None
    spread: float | None = None


def squeeze_axis(vertices: torch.Tensor) -> int:
    """The body's thinnest axis (its depth in canonical space: Y for Anny, Z for SMPL)."""
    return int((vertices.amax(0) - vertices.amin(0)).argmin())


def segmentation_body(subject: PosedSubject, canonical: CanonicalSubject, index: int) -> PosedBody:
    """Frame `index`'s posed body for GrabCut seeding: the skinned template, else the skeleton."""
    if canonical.template_vertices is not None:
        return PosedBody(vertices=PriorBody.of(subject, canonical).posed_template(index),
                         faces=subject.template_faces.numpy())
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


def padded_boxes(boxes: torch.Tensor) -> torch.Tensor:
    """(N, 2, 3) boxes grown by BOX_MARGIN_M on every side (a new tensor)."""
    return torch.stack((boxes[:, 0] - BOX_MARGIN_M, boxes[:, 1] + BOX_MARGIN_M), dim=1)


@dataclass(frozen=True)
class PriorBody:
    """What a shape prior is made from: the skeleton in canonical space, each frame's pose, and the
    body model's template when there is one (float32 CPU tensors; lengths in meters).

    Attributes:
        skeleton: J joints; canonical_joints: (J, 3) in the canonical pose.
        bone_transforms: (N, J, 4, 4) canonical -> posed world, per frame.
        template_vertices: (V, 3) canonical template, template_weights: (V, J) its skinning
            weights, template_faces: (F, 3) int64; all three None for a bare skeleton.
    """

    skeleton: Skeleton
    canonical_joints: torch.Tensor
    bone_transforms: torch.Tensor
    template_vertices: torch.Tensor | None = None
    template_weights: torch.Tensor | None = None
    template_faces: torch.Tensor | None = None

    @classmethod
    def of(cls, subject: PosedSubject, canonical: CanonicalSubject) -> PriorBody:
        """The body model's subject as preprocess poses it."""
        has_template = canonical.template_vertices is not None
        return cls(subject.skeleton, canonical.canonical_joints, canonical.bone_transforms, canonical.template_vertices,
                   subject.template_weights if has_template else None, subject.template_faces if has_template else None)

    def posed_template(self, index: int) -> np.ndarray:
        """(V, 3) float64 world vertices of the template in frame `index` (the body has a template)."""
        return linear_blend_skinning(self.template_vertices, self.template_weights,
                                     self.bone_transforms[index]).double().numpy()


def weights_grid(body: PriorBody, box_min: torch.Tensor, box_max: torch.Tensor,
                  resolution: tuple[int, int, int], blur: WeightBlur = WeightBlur()) -> torch.Tensor:
    """(J, D, H, W) skinning weights over a box: the template's, or for a bare skeleton the bones'.

    `blur.passes` None keeps each source's default (TEMPLATE_WEIGHT_SMOOTHING for a template,
    BoneWeightConfig's for bones); the spread applies to a template only (bones have no vertices).
    """
    if body.template_vertices is not None:
        passes = TEMPLATE_WEIGHT_SMOOTHING if blur.passes is None else blur.passes
        return build_skinning_grid(body.template_vertices, body.template_weights, box_min, box_max, resolution,
                                   smoothing_iterations=passes, spread=blur.spread)
    config = BoneWeightConfig() if blur.passes is None else BoneWeightConfig(smoothing_iterations=blur.passes)
    return build_bone_skinning_grid(body.canonical_joints, body.skeleton, box_min, box_max, resolution, config)


def body_prior(subject: PosedSubject, canonical: CanonicalSubject, resolution: tuple[int, int, int],
                blur: WeightBlur) -> ShapePrior:
    """The body model's template, or for a bare skeleton capsules around its bones."""
    if canonical.template_vertices is not None:
        vertices, faces, kind = canonical.template_vertices, subject.template_faces, "template"
        posed_boxes = canonical.posed_template_boxes
    else:
        capsules = capsule_prior(subject.skeleton, canonical.canonical_joints, canonical.bone_transforms)
        vertices, faces, kind = capsules.vertices, capsules.faces, "capsules"
        posed_boxes = capsules.posed_boxes  # joints alone miss the crown, hands and feet
    box_min, box_max = canonical_grid_box(vertices, squeeze_axis=squeeze_axis(vertices), margin=GRID_MARGIN_M)
    grid = weights_grid(PriorBody.of(subject, canonical), box_min, box_max, resolution, blur)
    return ShapePrior(vertices, faces, kind, box_min, box_max, grid, padded_boxes(posed_boxes))


def hull_prior(
    body: PriorBody,
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
    lo, hi = search_box(body.canonical_joints)
    search_weights = weights_grid(body, lo, hi, resolution, blur)
    skin = grid_skin(search_weights, lo, hi, body.bone_transforms)
    mask_views = MaskViews(masks=[masks[i] for i in views], K=K[views], w2c=w2c[views], frames=views)
    # Cells that ride rigidly into another limb (ghost legs beside spread canonical legs) are dropped.
    ghost_test = GhostTest(
        bones=PosedBones.from_skeleton(body.skeleton, body.canonical_joints, body.bone_transforms),
        weights=lambda x: sample_skinning_weights(search_weights, lo, hi, x),
    )
    hull = hull_prior_mesh(hull_cells(torch.stack((lo, hi)), skin, mask_views, cell_size=HULL_CELL_M, ghost_test=ghost_test))
    if hull is None:
        return None
    vertices = hull.vertices
    # Squeezed less than a template's box: a hull is deeper than the body it bounds.
    box_min, box_max = canonical_grid_box(vertices, squeeze_axis=squeeze_axis(vertices), squeeze=HULL_BOX_SQUEEZE,
                                          margin=GRID_MARGIN_M)
    grid = weights_grid(body, box_min, box_max, resolution, blur)
    skin = grid_skin(grid, box_min, box_max, body.bone_transforms)
    posed = [skin(i, vertices) for i in range(body.bone_transforms.shape[0])]
    posed_boxes = torch.stack([torch.stack((p.amin(0), p.amax(0))) for p in posed])
    return ShapePrior(vertices, hull.faces, "visual_hull", box_min, box_max, grid, padded_boxes(posed_boxes))


def hull_views(capture: CaptureV1, canonical: CanonicalSubject, shape_prior: str) -> list[int]:
    """Training frames whose masks vote for the visual hull; [] when the prior is the body model's.

    A bare skeleton's capsules are a sliver around a lone root and a naked stick figure elsewhere:
    its prior is the masks' visual hull, made once the masks are read. With a template and
    `auto`, the same views' masks decide whether the hull replaces it (`posed_template_fit`).
    `shape_prior` is --shape-prior (SHAPE_PRIORS).
    """
    train_names = set(capture.splits["train"])
    train_frames = [i for i, name in enumerate(capture.frames) if name in train_names]
    use_hull = canonical.template_vertices is None or shape_prior != "template"
    views = spread_views(train_frames, MAX_HULL_VIEWS) if use_hull else []
    if len(views) >= MIN_HULL_VIEWS:
        return views
    if shape_prior == "visual-hull":
        raise InputError(
            f"--shape-prior visual-hull: the capture has {len(train_frames)} training frames, and the hull needs at "
            f"least {MIN_HULL_VIEWS} views to vote; leave --shape-prior at auto (the body model's template)"
        )
    return []


def posed_template_fit(body: PriorBody, views: list[int], masks: dict[int, np.ndarray], K: np.ndarray,
                       w2c: np.ndarray) -> TemplateFit:
    """The views' masks against the posed template (igavatar.capture.loose_clothing.template_fit);
    the body has a template. The root joint's posed position gives each view's depth."""
    faces = body.template_faces.numpy()
    root = body.canonical_joints[0].double()
    bodies = []
    for i in views:
        transform = body.bone_transforms[i][0].double()
        bodies.append((body.posed_template(i), faces, (transform[:3, :3] @ root + transform[:3, 3]).numpy()))
    return template_fit([masks[i] for i in views], bodies, K[views], w2c[views])
