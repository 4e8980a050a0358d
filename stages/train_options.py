"""The options of `igavatar train` and the TrainConfig they resolve to (the preset, then the overrides).

    config = resolve_config(TrainOptions(dataset=Path("run/dataset"), out=Path("run/model"), preset="cpu"))
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from igavatar.errors import InputError
from igavatar.model.shading import SHADINGS
from igavatar.training.config import OUTLINE_AUTO, TrainConfig, color_grid_config, outline_px_for, preset, with_overrides

if TYPE_CHECKING:  # viser is imported only for --view
    from stages.train_view import ViewSettings


@dataclass(frozen=True)
class TrainOptions:
    """Options of `igavatar train` (see the CLI for each one's help)."""

    dataset: Path
    out: Path
    preset: str = "cpu"
    steps: int | None = None
    rays_per_step: int | None = None
    samples_per_ray: int | None = None
    regularizer: str | None = None
    sdf_encoding: str | None = None
    smooth_weight: float | None = None
    smooth_pairs: str | None = None
    smooth_form: str | None = None
    beta_init: float | None = None
    beta_final: float | None = None
    #: Share of training over which the beta cap reaches beta_final; None: the preset's.
    beta_anneal_fraction: float | None = None
    #: Power of the learning rate's polynomial decay; None: the preset's.
    lr_decay_power: float | None = None
    free_space_weight: float | None = None
    body_inside_weight: float | None = None
    smooth_band: float | None = None
    body_inside_max_spill: float | None = None
    table_adam: str | None = None
    table_lr_factor: float | None = None
    seed: int = 0
    device: str = "auto"
    resume: bool = False
    #: Train even when `out` holds a model of this dataset and these options (else: skipped).
    force: bool = False
    #: None: the preset's (off: measured, it does not yet pay for its time; docs/DESIGN.md "Video in").
    refine_poses: bool | None = None
    pose_lr: float | None = None
    pose_prior_weight: float | None = None
    #: Steps of the training poses' fit to the masks (0: none); None: the preset's.
    pose_silhouette_steps: int | None = None
    #: False: the shape prior is not voted again on the fitted poses; None: the preset's (on).
    pose_prior_vote: bool | None = None
    #: Weight of that fit's temporal term (0: none); None: the preset's.
    pose_silhouette_smoothness: float | None = None
    #: Steps of each frame's whole-image pose fit in the pose passes (0: no passes); None: the preset's.
    pose_align_steps: int | None = None
    #: None: the preset's (the colour loss reaches the geometry through the normal, as the paper's code).
    color_normal_gradient: bool | None = None
    #: False: the SDF's features reach the colour network detached; None: the preset's.
    color_feature_gradient: bool | None = None
    #: True: colour kept off the geometry (a colour grid, the SDF features and normal detached, colour
    #: on fixed weights); the four finer options below override it one by one.
    decoupled_color: bool = False
    #: False: the colour loss does not reach the compositing weights (the geometry); None: the preset's.
    color_shapes_geometry: bool | None = None
    #: Scale in [0, 1] of the colour loss's gradient through the weights; None: the preset's (cpu 0.3, paper 1).
    color_weights_gradient: float | None = None
    #: Pixels from the mask's outline within which the weights get the colour's whole gradient; None: the preset's (0: off).
    color_weights_outline_px: int | None = None
    #: Luma contrast in (0, 1] above which a ray off the outline band is on a pattern's edge and passes
    #: none of the colour's gradient through the weights; 0: off; None: the preset's (0).
    color_weights_edge_contrast: float | None = None
    #: True: the colour field gets a hash grid of its own, shaped as the SDF's; None: the preset's (cpu: on, paper: off).
    color_grid: bool | None = None
    #: The posed colour's light: "none" or "sh9" (igavatar.model.shading); None: the preset's (cpu sh9, paper none).
    shading: str | None = None
    #: Share of patch centres and frames drawn by the running error map; None: the preset's (0).
    error_sampling: float | None = None
    #: Share of the subject's patches centred on the mask's edge; None: the preset's (cpu 0.5, paper 0).
    outline_sampling: float | None = None
    #: A browser page that follows the run (stages.train_view); None: no page.
    view: ViewSettings | None = None


def resolve_config(options: TrainOptions) -> TrainConfig:
    """The preset with the CLI's overrides applied."""
    config = with_overrides(
        preset(options.preset), steps=options.steps, rays_per_step=options.rays_per_step,
        samples_per_ray=options.samples_per_ray, regularizer=options.regularizer, seed=options.seed,
        sdf_encoding=options.sdf_encoding, smooth_pairs=options.smooth_pairs, smooth_form=options.smooth_form, smooth_band=options.smooth_band,
        table_adam=options.table_adam, table_lr_factor=options.table_lr_factor,
        refine_poses=options.refine_poses, pose_lr=options.pose_lr, pose_prior_weight=options.pose_prior_weight,
        pose_silhouette_steps=options.pose_silhouette_steps, pose_silhouette_smoothness=options.pose_silhouette_smoothness,
        pose_prior_vote=options.pose_prior_vote,
        pose_align_steps=options.pose_align_steps,
        body_inside_max_spill=options.body_inside_max_spill, error_sampling=options.error_sampling,
        outline_sampling=options.outline_sampling, beta_anneal_fraction=options.beta_anneal_fraction,
        lr_decay_power=options.lr_decay_power,
    )
    weights = {name: value for name, value in (("smooth", options.smooth_weight), ("free_space", options.free_space_weight),
                                               ("body_inside", options.body_inside_weight))
               if value is not None}
    for name, value in weights.items():
        if value < 0:
            raise InputError(f"--{name.replace('_', '-')}-weight {value}: must be >= 0")
    if weights:
        config = dataclasses.replace(config, loss_weights=dataclasses.replace(config.loss_weights, **weights))
    if config.outline_sampling + config.error_sampling > 1.0:
        raise InputError(f"--outline-sampling {config.outline_sampling} and --error-sampling {config.error_sampling}: "
                         "together they share the subject's patches, so their sum must be <= 1")
    if options.beta_init is not None:
        if not 1e-4 <= options.beta_init <= 1.0:
            raise InputError(f"--beta-init {options.beta_init}: expected meters in [1e-4, 1]")
        density = dataclasses.replace(config.avatar.density, beta_init=options.beta_init)
        config = dataclasses.replace(config, avatar=dataclasses.replace(config.avatar, density=density))
    if options.beta_final is not None:
        if not 1e-4 <= options.beta_final <= config.avatar.density.beta_init:
            raise InputError(f"--beta-final {options.beta_final}: expected meters in [1e-4, beta_init = {config.avatar.density.beta_init}]")
        config = dataclasses.replace(config, beta_final=options.beta_final)
    return _color_options(config, options)


def with_outline_px(config: TrainConfig, image_size_hw: tuple[int, int]) -> TrainConfig:
    """`config` with a preset's OUTLINE_AUTO outline band resolved for images of this size (pixels)."""
    if config.color_weights_outline_px != OUTLINE_AUTO:
        return config
    return dataclasses.replace(config, color_weights_outline_px=outline_px_for(image_size_hw))


def _color_options(config: TrainConfig, options: TrainOptions) -> TrainConfig:
    """--decoupled-color, then the finer colour options, over the preset's."""
    def given(value: bool | None, decoupled: bool) -> bool | None:
        return value if value is not None else (decoupled if options.decoupled_color else None)

    shapes = given(options.color_shapes_geometry, False)
    if shapes is not None:
        config = dataclasses.replace(config, color_shapes_geometry=shapes)
    if options.color_weights_gradient is not None:
        if not 0.0 <= options.color_weights_gradient <= 1.0:
            raise InputError(f"--color-weights-gradient {options.color_weights_gradient}: expected a scale in [0, 1]")
        config = dataclasses.replace(config, color_weights_gradient=options.color_weights_gradient)
    if options.color_weights_outline_px is not None:
        if not 0 <= options.color_weights_outline_px <= 64:
            raise InputError(f"--color-weights-outline-px {options.color_weights_outline_px}: expected pixels in [0, 64] (0: off)")
        config = dataclasses.replace(config, color_weights_outline_px=options.color_weights_outline_px)
    if options.color_weights_edge_contrast is not None:
        if not 0.0 <= options.color_weights_edge_contrast <= 1.0:
            raise InputError(f"--color-weights-edge-contrast {options.color_weights_edge_contrast}: expected a luma "
                             "contrast in [0, 1] (0: off)")
        config = dataclasses.replace(config, color_weights_edge_contrast=options.color_weights_edge_contrast)
    if config.color_weights_edge_contrast > 0 and config.color_weights_outline_px == 0:
        raise InputError("--color-weights-edge-contrast needs the outline band (its window's width): give "
                         "--color-weights-outline-px N (N >= 1), or --color-weights-edge-contrast 0")
    color = config.avatar.color
    grid, features, normal = (given(options.color_grid, True), given(options.color_feature_gradient, False),
                              given(options.color_normal_gradient, False))
    if grid is not None:
        color = dataclasses.replace(color, hash_grid=color_grid_config(config.avatar.sdf.hash_grid) if grid else None)
    if features is not None:
        color = dataclasses.replace(color, feature_gradient=features)
    if normal is not None:
        color = dataclasses.replace(color, normal_gradient=normal)
    avatar = dataclasses.replace(config.avatar, color=color)
    if options.shading is not None:
        if options.shading not in SHADINGS:
            raise InputError(f"--shading {options.shading!r}: expected one of {', '.join(SHADINGS)}")
        avatar = dataclasses.replace(avatar, shading=options.shading)
    return dataclasses.replace(config, avatar=avatar)
