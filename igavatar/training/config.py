"""Training configuration and its named presets.

    config = preset("cpu")                                   # a TrainConfig
    config = dataclasses.replace(config, steps=500, seed=3)   # CLI overrides

`paper` follows the paper and its released code (GPU); `cpu` is sized to give a good avatar of the
default synthetic subject in about ten minutes on two CPU cores; `tiny` is for tests.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field, replace
from typing import Literal

from igavatar.errors import InputError
from igavatar.model.avatar import AvatarConfig
from igavatar.model.deformer import DeformerConfig
from igavatar.model.fields import ColorFieldConfig, LaplaceDensityConfig, SDFFieldConfig
from igavatar.model.hashgrid import HashGridConfig
from igavatar.model.losses import LossWeights
from igavatar.training.body_prior import MAX_SPILL

Regularizer = Literal["smooth", "none", "fd-eikonal", "curvature", "fd-eikonal+curvature", "hybrid-pe"]
REGULARIZERS: tuple[str, ...] = ("smooth", "none", "fd-eikonal", "curvature", "fd-eikonal+curvature", "hybrid-pe")
SmoothPairs = Literal["valid", "adjacent", "monotone", "screen"]
SMOOTH_PAIRS: tuple[str, ...] = ("valid", "adjacent", "monotone", "screen")
SmoothForm = Literal["eq9", "released"]
SMOOTH_FORMS: tuple[str, ...] = ("eq9", "released")
TableAdam = Literal["sparse", "dense"]
TABLE_ADAMS: tuple[str, ...] = ("sparse", "dense")
"""Adam on the hash table: tiny-cuda-nn's rule (zero-gradient entries skipped) or torch's dense Adam."""
PRESETS: tuple[str, ...] = ("paper", "cpu", "tiny")
SDF_ENCODINGS: tuple[str, ...] = ("hashgrid", "mlp")
#: The `mlp` SDF: no hash grid, a 6-frequency positional encoding into 4 x 128 Softplus layers --
#: the slow-but-smooth baseline (a CPU-sized stand-in for Vid2Avatar's 8 x 256 MLP).
MLP_SDF = {"use_hash_grid": False, "pe_frequencies": 6, "hidden_dim": 128, "n_hidden_layers": 4}


@dataclass(frozen=True)
class TrainConfig:
    """Everything that decides a training run (recorded, resolved, in the model's manifest)."""

    preset: str = "paper"
    """Name of the preset these values started from."""
    steps: int | None = None
    """Optimization steps; None = `epochs` x the number of training frames (one frame per step)."""
    epochs: int = 30
    """Epochs when `steps` is None (official: 30)."""
    rays_per_step: int = 4096
    """Rays per step, drawn as square patches of `patch_size` pixels from one frame."""
    patch_size: int = 32
    """Edge of each ray patch in pixels (paper: four 32x32 patches = 4096 rays)."""
    patch_centres_in_mask: float = 0.9
    """Fraction of patches centerd on a mask pixel; the rest anywhere in the subject's box."""
    error_sampling: float = 0.0
    """Share of the subject-centred patches, and of the frame draws, steered by a running map of
    the colour error (igavatar.training.error_map: Instant-NGP's error map), so rays go where the
    renders are wrong (textures, edges, a face); 0 draws uniformly (the paper)."""
    error_cell_px: int = 16
    """Edge in pixels of the error map's cells."""
    outline_sampling: float = 0.0
    """Share of the subject-centred patches centred on the mask's edge (igavatar.training.outline.
    outline_pixels) instead of anywhere on the person: the outline holds most of the held-out image
    error; 0 draws them uniformly over the mask (the paper)."""
    color_shapes_geometry: bool = True
    """Whether the colour loss reaches the compositing weights, and so the geometry (VolSDF, the
    paper). False composites the colour on weights held fixed for that loss: the surface is then
    shaped by the masks, the priors and the regularizers, and colour only paints it (issue 36)."""
    color_weights_gradient: float = 1.0
    """With color_shapes_geometry, the scale in [0, 1] of the colour loss's gradient through the
    compositing weights (1: VolSDF, the paper): below 1 the images still help shape the surface,
    with less pull to carve sharp colour features (a face's eyes and mouth) into it."""
    color_weights_outline_px: int = 0
    """With color_shapes_geometry, rays within this many pixels of the mask's outline pass the colour
    loss's whole gradient through the weights, and the others `color_weights_gradient`: the images
    shape the silhouette, and a pattern inside it is not carved (0: `color_weights_gradient` on
    every ray; OUTLINE_AUTO: `outline_px_for(image size)`, resolved by the train stage once the
    dataset is read, so a saved config always holds the pixels used)."""
    color_weights_edge_contrast: float = 0.0
    """With the outline band on, rays off it whose window of the band's width spans a luma contrast
    above this on the person (a bold stripe's or checker's edge: igavatar.training.outline.
    texture_edge_rays) pass none of the colour loss's gradient through the weights, the others
    `color_weights_gradient`: a pattern changes colour only at its edges, so that is where it carves
    (0: off, the paper)."""
    samples_per_ray: int = 256
    """Bins per ray before empty-space skipping (official: up to 256)."""
    lr: float = 1e-2
    """Adam learning rate of every part but beta (official 1e-2)."""
    beta_lr_factor: float = 0.1
    """beta's learning rate is lr times this (official: lr / 10)."""
    network_lr_factor: float = 1.0
    """Learning rate of the MLPs (SDF, color, non-rigid) relative to lr; the hash table uses lr."""
    lr_warmup_steps: int = 0
    """Linear learning-rate warm-up from lr/100 over this many steps (protects the shape prior)."""
    lr_decay_power: float = 1.75
    """Polynomial decay lr * (1 - step / steps) ** power (official 1.75)."""
    adam_eps: float = 1e-15
    """Adam epsilon (official 1e-15, as Instant-NGP)."""
    table_lr_factor: float = 1.0
    """Learning rate of the hash table relative to lr (the MLPs have `network_lr_factor`)."""
    table_adam: TableAdam = "sparse"
    """Adam on the hash table: `sparse` (tiny-cuda-nn's rule, as Instant-NGP: entries with a zero
    gradient are left alone) or `dense` (torch's Adam: they keep drifting on their momentum)."""
    loss_weights: LossWeights = field(default_factory=LossWeights)
    """Weights of the loss terms (paper: rgb 10, alpha 0.1, eikonal 0.1, smooth 1.0)."""
    regularizer: Regularizer = "smooth"
    """Surface regularizer: the paper's along-ray `smooth` or one of the Table-5 ablations."""
    smooth_pairs: SmoothPairs = "monotone"
    """`smooth`: which consecutive valid samples of a ray L_smooth compares: those across which the
    SDF runs one way ("monotone", the default: no ridge of the distance field between them, where
    normals flip by construction; it took most of the web out of the crotch at the same CD and NC,
    tests/benchmarks/results/smooth-pairs.md), every pair (Eq. 9 read literally, also across
    skipped empty space: "valid"), only samples of touching intervals ("adjacent"), or the same
    sample slot on horizontally neighbouring pixels of a patch ("screen", what the released code
    computes)."""
    smooth_form: SmoothForm = "released"
    """`smooth` along rays: "eq9" (unsquared norms, each ray divided by its valid samples, as Eq. 9
    reads) or "released" (squared differences averaged over every sample slot, as the authors'
    code: orders of magnitude weaker at the same weight)."""
    smooth_band: float | None = None
    """`smooth` along rays: compare only samples whose SDF is within this many meters of the zero
    level (None: every valid sample, as Eq. 9 and the released code)."""
    fd_eps: float = 1e-3
    """Step (meters) of finite differences for the fd-eikonal / curvature ablations."""
    curvature_warmup_steps: int = 200
    """Linear warm-up of the curvature ablation's weight."""
    hybrid_pe_frequencies: int = 6
    """hybrid-pe ablation: Fourier frequencies of the positional encoding added to the hash grid."""
    hybrid_pe_anneal_fraction: float = 0.5
    """hybrid-pe ablation: fraction of training over which the hash levels open coarse-to-fine."""
    beta_final: float | None = None
    """Cap on the learned VolSDF beta, annealed geometrically from beta_init to this value (meters)
    over `beta_anneal_fraction` of training; None = beta only learned (the paper). The rendered
    silhouette sits about 1-2 beta outside the SDF's zero level, so a beta that stalls near 1 cm
    in a short run shrinks the surface by that much (measured on the synthetic subject)."""
    beta_anneal_fraction: float = 0.8
    """Fraction of training over which the beta cap reaches `beta_final`."""
    sigma_noise_std: float = 0.0
    """Gaussian noise on the density early in training (released code: 1.0; not in the paper)."""
    sigma_noise_steps: int = 1000
    """Steps during which `sigma_noise_std` applies."""
    free_space_points: int = 4096
    """Canonical points drawn uniformly in the box each step for the visual-hull free-space term
    (used when `loss_weights.free_space` > 0)."""
    body_inside_points: int = 4096
    """Points inside the naked template drawn each step for the body-inside term (used when
    `loss_weights.body_inside` > 0 and the dataset has a body-model template)."""
    body_inside_slack: float = 0.005
    """Meters the SDF may exceed the template's inside the body before the body-inside term acts."""
    body_inside_max_spill: float = MAX_SPILL
    """Largest spill of the template past the masks (igavatar.training.body_prior) for which the
    body-inside term is used, in [0, 1]; 1 never refuses a template (masks known to be tight, a fit trusted)."""
    hull_cell_size: float = 0.015
    """Spacing in meters of the canonical grid on which the masks' visual hull is voted."""
    hull_in_occupancy: bool = False
    """Mark cells inside the visual hull occupied, so that ray samples reach surface beyond the
    shape prior (loose garments, hair, a capture without a template)."""
    occupancy_resolution: int = 64
    """Cells per axis of the canonical and per-frame posed occupancy grids (official 64)."""
    occupancy_update_every: int = 16
    """Steps between canonical occupancy refreshes (official 16)."""
    nonrigid_start_fraction: float = 1 / 30
    """Non-rigid offsets switch on after this fraction of training (official: after epoch 1 of 30)."""
    nonrigid_window_fraction: float = 5 / 30
    """Their frequency window then opens over this fraction (official: epochs 1..6)."""
    refine_poses: bool = False
    """Optimise per-frame corrections of the training frames' joint rotations and root translation:
    fitted to the masks before the first step (pose_silhouette_*), then with the avatar
    (igavatar.training.pose_refine), optionally in whole-frame pose passes (pose_align_*). Off in
    every preset: with 5 degrees of noise a joint it took CD-L1 from 22.2 to 5.7 mm and from 20.9 to
    6.4 mm on two subjects (exact poses 3.7 and 4.3) at the cost of a 10 s fit
    (tests/benchmarks/results/pose-noise-temporal.md), but on poses that are right it has not been shown to
    help (ZJU-MoCap 377, zju377-registration.md), and on the video path's fitted poses the held-out
    frames lost 0.5-0.8 dB box PSNR on three clips, and still lost on two of them when posed by
    their refined neighbours' corrections (video-carry-poses.md)."""
    pose_lr: float = 0.002
    """Learning rate of the pose corrections (radians, meters) when they start, falling linearly to 0
    at the end of training; each frame's are stepped only on the steps that draw it (SparseAdam),
    about steps / training frames times."""
    pose_prior_weight: float = 0.01
    """Weight of the squared corrections (radians^2, and (meters / pose_translation_scale_m)^2)
    that keeps the refined poses near the estimate."""
    pose_translation_scale_m: float = 0.02
    """A root translation correction of this many meters costs as much as one radian of rotation."""
    pose_gradient_samples: int = 4096
    """Ray samples per step whose pose gradient is computed (scaled to stand for all of them)."""
    pose_refine_start_fraction: float = 0.5
    """Pose corrections are stepped from this fraction of training on, once the shape has formed."""
    pose_align_fractions: tuple[float, ...] = (0.3, 0.6)
    """With refine_poses: at these fractions of training every training frame's pose is fitted to
    its whole image, the avatar frozen (igavatar.training.pose_align); () for none."""
    pose_align_steps: int = 0
    """Steps of one frame's pose fit in such a pass (each costs about a training step); 0, the
    default, for no passes: after the fit to the masks (pose_silhouette_*) two passes of 16 steps
    left the 5-degree noise run where it was (CD-L1 6.52 against 6.53 mm) in a run 5.8x as long
    (tests/benchmarks/results/pose-noise.md)."""
    pose_align_lr: float = 0.004
    """Adam's rate of that fit (radians, meters): 16 steps can move a joint by up to about 3.7 degrees."""
    pose_prior_vote: bool = True
    """With refine_poses and that fit: where preprocess kept the naked template by its loose-clothing
    rule, vote again on the fitted poses, and train on the masks' visual hull where it now wins
    (igavatar.training.prior_vote: a dress on noisy poses)."""
    pose_silhouette_steps: int = 200
    """With refine_poses: Adam steps fitting every training frame's pose corrections to its mask
    before the first training step, the shape prior posed by them (igavatar.training.pose_silhouette);
    0 for none."""
    pose_silhouette_lr: float = 0.005
    """Adam's rate of that fit (radians, meters)."""
    pose_silhouette_coverage: float = 1.0
    """Weight of its outline term (the mask's outline near the posed prior) against the inside term."""
    pose_silhouette_prior_weight: float = 1.0
    """Weight of the squared corrections in that fit (radians^2, and (meters /
    pose_silhouette_translation_scale_m)^2), against the silhouette term's mean px."""
    pose_silhouette_translation_scale_m: float = 0.1
    """A root correction of this many meters costs as much as a radian in that fit: training's
    2 cm (pose_translation_scale_m) held the root where it was, since a silhouette moved by a few
    centimetres gains less than a pixel of the term."""
    pose_silhouette_smoothness: float = 0.3
    """Weight in that fit of the refined joints' acceleration between frames named as neighbours in
    one clip, per source frame squared (igavatar.training.pose_time), against the silhouette term's
    mean px; 0 for none. A mask says little of depth, and the estimate's errors differ from frame
    to frame: with 5 degrees of noise a joint the fit left the major joints 22-28 mm off on three
    subjects, 12-16 mm with this term (tests/benchmarks/results/pose-noise-temporal.md)."""
    shape_init_steps: int = 1000
    """Steps fitting the SDF to the template's SDF before photometric training (0 = sphere)."""
    shape_init_points: int = 16384
    """Points per shape-initialization step."""
    avatar: AvatarConfig = field(default_factory=AvatarConfig)
    """Network architecture and root finding."""
    validate_every: int = 500
    """Steps between validation renders (PNG); 0 = only at the end."""
    validation_scale: float = 0.5
    """Validation renders at this fraction of the dataset's image size."""
    validation_samples: int = 128
    """Bins per ray of validation renders."""
    checkpoint_every: int = 500
    """Steps between checkpoints (for --resume)."""
    log_every: int = 10
    """Steps between rows of the training log."""
    seed: int = 0
    """Seed of every random choice (deterministic on CPU)."""

    def resolved_steps(self, num_train_frames: int) -> int:
        """The number of optimization steps for a dataset with that many training frames."""
        return self.steps if self.steps is not None else self.epochs * num_train_frames


def _cpu_avatar() -> AvatarConfig:
    # beta starts at 2 cm: the official 7.5 cm blurs every silhouette by several centimeters, and
    # in a short run the forearms and hands fade in the first 50 steps and never come back.
    # The colour field has a hash grid of its own (the official code reads the SDF's features
    # only): without it, bold stripes were carved into the surface (issue 36; bold CD-L1 5.1 ->
    # 4.2 mm, NC 0.88 -> 0.95) and a real capture rendered as one olive figure (ZJU-MoCap 377:
    # vest, skin and shoes recognisable with it, +0.4 dB). It costs the plain heavy body 0.04-0.6 mm
    # CD-L1 (tests/benchmarks/results/color-grid-default.md).
    # The colour is the albedo, lit by the clip's light (nine spherical harmonics of the posed
    # normal): a person turning in a fixed light no longer averages its shading into the colour or
    # the shape. CD-L1 -0.13 to -0.52 mm and box PSNR +0.3 to +0.6 dB on the 5 runs of 4 subjects
    # measured, everything else up or even (tests/benchmarks/results/shading.md).
    sdf = SDFFieldConfig(hash_grid=HashGridConfig(n_levels=12, log2_hashmap_size=17, base_resolution=16, finest_resolution=1024))
    return AvatarConfig(
        sdf=sdf,
        color=ColorFieldConfig(hash_grid=color_grid_config(sdf.hash_grid)),
        density=LaplaceDensityConfig(beta_init=0.02),
        deformer=DeformerConfig(init_top_k=2),
        shading="sh9",
    )


def _tiny_avatar() -> AvatarConfig:
    return AvatarConfig(
        sdf=SDFFieldConfig(
            hash_grid=HashGridConfig(n_levels=4, n_features_per_level=2, log2_hashmap_size=12, base_resolution=4, finest_resolution=32),
            hidden_dim=16, feature_dim=8,
        ),
        color=ColorFieldConfig(feature_dim=8, hidden_dim=16),
        density=LaplaceDensityConfig(beta_init=0.075),
        nonrigid_width=16, nonrigid_layers=2,
        deformer=DeformerConfig(init_top_k=2),
    )


def color_grid_config(sdf_grid: HashGridConfig) -> HashGridConfig:
    """The colour field's own hash grid for an SDF grid: its table size and coarsest level, at most 8
    levels up to 512 cells (a few mm on a body). Measured on the cpu preset: +7 % step time, against
    +12 % for a copy of the SDF's 12 levels up to 1024 (tests/benchmarks/results/color-step.md)."""
    levels = min(8, sdf_grid.n_levels)
    finest = max(sdf_grid.base_resolution, min(512, sdf_grid.finest_resolution))
    return dataclasses.replace(sdf_grid, n_levels=levels, finest_resolution=finest)


#: `color_weights_outline_px` of a preset that scales the band with the images (`outline_px_for`).
OUTLINE_AUTO = -1


def outline_px_for(image_size_hw: tuple[int, int]) -> int:
    """The outline band's half-width for images of this size: the longer side / 128, at least 1
    (2 px at 256, 4 at 512, 8 at 1024: the widths measured, tests/benchmarks/results/outline-band.md)."""
    return max(1, round(max(image_size_hw) / 128))


def preset(name: str) -> TrainConfig:
    """The TrainConfig of a named preset; InputError for an unknown name."""
    if name == "paper":
        return TrainConfig(preset="paper", lr_warmup_steps=100, avatar=AvatarConfig(
            sdf=SDFFieldConfig(hash_grid=HashGridConfig(log2_hashmap_size=17, finest_resolution=4096)),
        ))
    if name == "cpu":
        # Fewer rays per step than the paper make each step noisier: a lower learning rate for
        # the networks, a warm-up, more background in the patches and a later non-rigid start
        # keep the shape prior from being blown apart early (measured on the synthetic subject).
        # The rendered silhouette sits ~2 beta outside the SDF's zero level (docs/DESIGN.md, Geometry),
        # so the surface is pulled ~2 beta inside the masks: capping beta down to 1 mm (3 mm
        # before) cut in-distribution CD-L1 from 10.0 to 6.2 mm and raised IoU from 0.78 to 0.87
        # on the stripes-shirt subject (tests/benchmarks/results/geometry.md).
        # The table's sparse Adam moves an entry reached once by one step, not torch's ten: twice
        # the rate gave back the texture and loose-garment fit that x1 lost in these short runs;
        # x3 re-opened an ankle (tests/benchmarks/results/sparse-adam.md).
        return TrainConfig(
            preset="cpu", steps=1500, rays_per_step=1024, patch_size=16, samples_per_ray=96,
            lr=5e-3, network_lr_factor=0.2, table_lr_factor=2.0, beta_lr_factor=0.5, lr_warmup_steps=100, beta_final=1e-3,
            patch_centres_in_mask=0.5, nonrigid_start_fraction=0.5, nonrigid_window_fraction=0.25,
            shape_init_steps=300, shape_init_points=8192, validate_every=500, checkpoint_every=250,
            validation_scale=0.5, validation_samples=96, avatar=_cpu_avatar(),
            # The naked body inside the clothes keeps the fingers and toes that a pixel-wide
            # silhouette cannot hold (tests/benchmarks/results/body-prior.md).
            # L_smooth on the surface's normals only: over every sample it also smoothed the
            # distance field in the empty space under the crotch, which grew the crotch 3.5 cm
            # down into the gap between the legs (tests/benchmarks/results/smooth-band.md). On the
            # surface only, the paper's weight 1 beats 0.5 (which had been the best weight over
            # every sample, smooth-weight.md) on 7 of 9 runs (smooth-band-weight.md).
            loss_weights=LossWeights(body_inside=10.0, smooth=1.0),
            smooth_band=0.01,
            # With the colour grid, 0.3 of the colour loss's pull on the surface through the
            # weights (the paper: all of it) kept the grid's gains and took back what it cost the
            # plain heavy body (a dented face): CD-L1 -0.24 mm over 5 subjects x 2-3 seeds, better
            # on 9 of 11 runs, the loose dress's seed 0 +0.2 mm; the images even
            # (tests/benchmarks/results/color-weights-gradient.md).
            color_weights_gradient=0.3,
            # ... and the whole of it within a few pixels of the mask's outline, where the images
            # shape the silhouette: CD-L1 -0.14 to -0.71 mm on 5 runs over 4 subjects, the bold
            # stripes' side view smoother (tests/benchmarks/results/outline-band.md).
            color_weights_outline_px=OUTLINE_AUTO,
            # Half the subject's patches centred on the mask's edge, where 57-90 % of the held-out
            # image error lay: CD-L1 -0.15 to -1.25 mm and full-size box PSNR +0.2 to +1.9 dB on five
            # runs over four subjects, the inside's texture a little fainter, at the same rays a step
            # (tests/benchmarks/results/outline-sampling.md).
            outline_sampling=0.5,
        )
    if name == "tiny":
        return TrainConfig(
            preset="tiny", steps=6, rays_per_step=32, patch_size=4, samples_per_ray=16,
            occupancy_resolution=16, occupancy_update_every=2, shape_init_steps=5, shape_init_points=256,
            validate_every=0, checkpoint_every=3, validation_scale=0.25, validation_samples=16, log_every=1,
            nonrigid_start_fraction=0.34, nonrigid_window_fraction=0.34, avatar=_tiny_avatar(),
        )
    raise InputError(f"--preset {name!r}: unknown; expected one of {', '.join(PRESETS)}")


#: Fields `with_overrides` checks against a closed range: field -> (lowest, highest, what the
#: error says is expected).
_RANGES: dict[str, tuple[float, float, str]] = {
    "body_inside_max_spill": (0.0, 1.0, "a share of views in [0, 1] (1: no check)"),
    "error_sampling": (0.0, 1.0, "a share in [0, 1]"),
    "outline_sampling": (0.0, 1.0, "a share in [0, 1]"),
    "beta_anneal_fraction": (0.01, 1.0, "a share of training in [0.01, 1]"),
    "lr_decay_power": (0.0, 10.0, "a power in [0, 10] (0: no decay)"),
}


def with_overrides(config: TrainConfig, **overrides) -> TrainConfig:
    """`config` with the given (non-None) fields replaced; InputError for bad values."""
    overrides = {k: v for k, v in overrides.items() if v is not None}
    encoding = overrides.pop("sdf_encoding", "hashgrid")
    if encoding not in SDF_ENCODINGS:
        raise InputError(f"--sdf-encoding {encoding!r}: expected one of {', '.join(SDF_ENCODINGS)}")
    if "smooth_form" in overrides and overrides["smooth_form"] not in SMOOTH_FORMS:
        raise InputError(f"--smooth-form {overrides['smooth_form']!r}: expected one of {', '.join(SMOOTH_FORMS)}")
    if "smooth_pairs" in overrides and overrides["smooth_pairs"] not in SMOOTH_PAIRS:
        raise InputError(f"--smooth-pairs {overrides['smooth_pairs']!r}: expected one of {', '.join(SMOOTH_PAIRS)}")
    if "table_adam" in overrides and overrides["table_adam"] not in TABLE_ADAMS:
        raise InputError(f"--table-adam {overrides['table_adam']!r}: expected one of {', '.join(TABLE_ADAMS)}")
    if "regularizer" in overrides and overrides["regularizer"] not in REGULARIZERS:
        raise InputError(f"--regularizer {overrides['regularizer']!r}: expected one of {', '.join(REGULARIZERS)}")
    if "smooth_band" in overrides and not overrides["smooth_band"] > 0:
        raise InputError(f"--smooth-band {overrides['smooth_band']}: must be > 0 (meters)")
    if "table_lr_factor" in overrides and not overrides["table_lr_factor"] > 0:
        raise InputError(f"--table-lr-factor {overrides['table_lr_factor']}: must be > 0")
    if "pose_lr" in overrides and not overrides["pose_lr"] > 0:
        raise InputError(f"--pose-lr {overrides['pose_lr']}: must be > 0")
    if "pose_prior_weight" in overrides and overrides["pose_prior_weight"] < 0:
        raise InputError(f"--pose-prior-weight {overrides['pose_prior_weight']}: must be >= 0")
    for name, (lowest, highest, expected) in _RANGES.items():
        if name in overrides and not lowest <= overrides[name] <= highest:
            raise InputError(f"--{name.replace('_', '-')} {overrides[name]}: expected {expected}")
    for name in ("steps", "rays_per_step", "samples_per_ray"):
        if name in overrides and overrides[name] < 1:
            raise InputError(f"--{name.replace('_', '-')} {overrides[name]}: must be >= 1")
    config = replace(config, **overrides)
    if encoding == "mlp":
        config = replace(config, avatar=replace(config.avatar, sdf=replace(config.avatar.sdf, **MLP_SDF)))
    if config.regularizer == "hybrid-pe" and config.avatar.sdf.pe_frequencies == 0:
        # The hybrid encoding is an architecture change: a Fourier encoding beside the hash grid.
        sdf = replace(config.avatar.sdf, pe_frequencies=config.hybrid_pe_frequencies)
        config = replace(config, avatar=replace(config.avatar, sdf=sdf))
    return config


def _from_json(cls, value):
    """Rebuild dataclass `cls` from its JSON form (nested dataclasses; lists back to tuples)."""
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for item in dataclasses.fields(cls):
        if item.name not in value:
            continue  # written by an older version: keep the default
        raw = value[item.name]
        kind = hints[item.name]
        # An optional dataclass (`HashGridConfig | None`): its dataclass when the JSON holds one.
        options = [k for k in typing.get_args(kind) if dataclasses.is_dataclass(k)]
        if isinstance(raw, dict) and len(options) == 1:
            kind = options[0]
        if dataclasses.is_dataclass(kind):
            kwargs[item.name] = _from_json(kind, raw)
        elif isinstance(raw, list):
            kwargs[item.name] = tuple(raw)
        else:
            kwargs[item.name] = raw
    return cls(**kwargs)


def config_from_json(value: dict) -> TrainConfig:
    """The TrainConfig recorded (as `dataclasses.asdict` JSON) in a model's manifest."""
    return _from_json(TrainConfig, value)
