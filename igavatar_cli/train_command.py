"""`igavatar train`: the command (registered on the app by igavatar_cli.main)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from igavatar_cli.cli_common import JsonOut, Quiet, RunDir, run_stage, user_errors
from igavatar_cli.help_panels import ADVANCED, CONSOLE, INPUTS, QUALITY, help_panels
from stages.layout import DEFAULT_RUN_DIR, RunLayout


def _view_settings(view: bool, host: str, port: int, mesh_every: int, mesh_resolution: int):
    if not view:
        return None
    from stages.train_view import ViewSettings

    return ViewSettings(host=host, port=port, mesh_every=mesh_every, mesh_resolution=mesh_resolution)


@user_errors
@help_panels({INPUTS: ("dataset", "out", "run_dir", "resume", "force"), QUALITY: ("preset", "steps", "rays", "samples", "seed", "device", "decoupled_color"),
              "Poses from a video": ("refine_poses", "pose_lr", "pose_prior_weight", "pose_silhouette_steps",
                                     "pose_silhouette_smoothness", "pose_prior_vote", "pose_align_steps"),
              "Watch it in a browser": ("view", "view_host", "view_port", "view_mesh_every", "view_mesh_resolution"),
              ADVANCED: ("regularizer", "smooth_weight", "smooth_pairs", "smooth_form", "smooth_band", "beta_init",
                         "beta_final", "beta_anneal_fraction", "lr_decay_power", "free_space_weight", "body_inside_weight", "body_inside_max_spill", "sdf_encoding",
                         "table_adam", "table_lr_factor", "color_normal_gradient", "color_feature_gradient", "color_shapes_geometry",
                         "color_weights_gradient", "color_weights_outline_px", "color_weights_edge_contrast", "color_grid", "shading",
                         "error_sampling", "outline_sampling"),
              CONSOLE: ("quiet", "json_out")})
def train(
    dataset: Annotated[Optional[Path], typer.Option(help="Dataset directory \\[default: RUN_DIR/dataset].")] = None,
    out: Annotated[Optional[Path], typer.Option(help="Model directory to write \\[default: RUN_DIR/model].")] = None,
    run_dir: RunDir = DEFAULT_RUN_DIR,
    preset: Annotated[str, typer.Option(help="paper (GPU, the paper's settings), cpu (~10 min on 2 cores) or tiny (tests).")] = "cpu",
    steps: Annotated[Optional[int], typer.Option(help="Optimization steps \\[default: the preset's].")] = None,
    rays: Annotated[Optional[int], typer.Option("--rays", help="Rays per step \\[default: the preset's].")] = None,
    samples: Annotated[Optional[int], typer.Option("--samples", help="Samples per ray before empty-space skipping \\[default: the preset's: cpu 96, paper 256].")] = None,
    seed: Annotated[int, typer.Option(help="Random seed (runs are deterministic on CPU).")] = 0,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda.")] = "auto",
    resume: Annotated[bool, typer.Option(help="Continue from the last checkpoint of an interrupted run.")] = False,
    force: Annotated[bool, typer.Option(help="Train even if --out holds a model of this dataset with these options.")] = False,
    refine_poses: Annotated[Optional[bool], typer.Option(
        "--refine-poses/--no-refine-poses",
        help="Correct the training poses: fitted to the masks before training, then optimised with the avatar, "
             "kept near the estimate; saved in the model (refined_poses.npz) and used by export, animate and eval for "
             "those frames \\[default: off: with 5 degrees of pose noise a joint it cut the shape's error from 21-22 to "
             "6-6.5 mm on two subjects (exact poses 4), but on the video path's own fitted poses it cost the held-out frames "
             "0.5-0.8 dB on three clips (0.1-0.9 dB of it back with eval --carry-poses), and on poses that are right it "
             "has not been shown to help].")] = None,
    pose_lr: Annotated[Optional[float], typer.Option(
        help="Learning rate of the pose corrections when they start at half-way, falling linearly to 0 at the end \\[default: 0.002].")] = None,
    pose_prior_weight: Annotated[Optional[float], typer.Option(
        help="Weight that keeps the refined poses near the estimate \\[default: 0.01].")] = None,
    pose_silhouette_steps: Annotated[Optional[int], typer.Option(
        help="With --refine-poses: steps fitting every training frame's pose to its mask before training, the "
             "shape prior posed into each frame (about a minute on 2 cores for 50 frames); 0: none "
             "\\[default: 200].", min=0)] = None,
    pose_silhouette_smoothness: Annotated[Optional[float], typer.Option(
        help="With --refine-poses: weight, in that fit, of the joints' acceleration between frames whose names "
             "number them as neighbours in one clip (the masks say little of depth; an estimate's errors change "
             "from frame to frame); 0: none \\[default: 0.3].", min=0.0)] = None,
    pose_prior_vote: Annotated[Optional[bool], typer.Option(
        "--pose-prior-vote/--no-pose-prior-vote",
        help="With --refine-poses: where preprocess kept the naked template as the shape prior (its loose-clothing "
             "test reads poses that are off as a body posed wrong, not as loose clothes), ask that test again on the "
             "poses fitted to the masks, and train on the masks' visual hull where it now wins (a dress on noisy "
             "poses) \\[default: on].")] = None,
    pose_align_steps: Annotated[Optional[int], typer.Option(
        help="With --refine-poses: steps of each training frame's pose fit to its whole image, the avatar frozen, "
             "at 30 % and 60 % of training (each step costs about a training step, per frame; 16 is a useful "
             "value); 0: none \\[default: 0: after the fit to the masks they gained nothing in a run 5.8x as long].",
        min=0)] = None,
    view: Annotated[bool, typer.Option(
        help="Serve a page (viser) that follows the run: loss and PSNR curves, the latest validation render and a "
             "coarse canonical mesh; its address is printed. The model written is the same as without it.")] = False,
    view_host: Annotated[str, typer.Option(help="--view: address to listen on (0.0.0.0 opens it to the network).")] = "127.0.0.1",
    view_port: Annotated[int, typer.Option(help="--view: port (0: any free one); a busy port is an error.")] = 8080,
    view_mesh_every: Annotated[int, typer.Option(
        help="--view: steps between two canonical meshes (0: none); each costs a marching cubes at 64, about "
             "0.03 s on 2 CPU cores (8 meshes in 750 steps cost 0.3 % of the time).", min=0)] = 100,
    view_mesh_resolution: Annotated[int, typer.Option(help="--view: marching-cubes resolution of that mesh.", min=16)] = 64,
    regularizer: Annotated[
        Optional[str], typer.Option(help="smooth (the paper), none, fd-eikonal, curvature, fd-eikonal+curvature or hybrid-pe \\[default: smooth].")
    ] = None,
    smooth_weight: Annotated[Optional[float], typer.Option(help="Weight of L_smooth (paper: 1.0; 0.5-1.5 works) \\[default: 1].")] = None,
    smooth_pairs: Annotated[
        Optional[str], typer.Option(help="L_smooth pairs: monotone (consecutive samples on a ray across which the SDF runs one way: no flip at a ridge of the distance field inside a thin part or in a gap, such as between the legs), valid (every consecutive pair, also across gaps; Eq. 9 read literally), adjacent (touching intervals only) or screen (same slot on neighbouring pixels, as the released code) \\[default: monotone].")
    ] = None,
    smooth_form: Annotated[
        Optional[str], typer.Option(help="L_smooth along rays: eq9 (unsquared, per valid sample, Eq. 9) or released (squared, averaged over every slot, as the authors' code: far weaker at the same weight) \\[default: the preset's: released].")
    ] = None,
    smooth_band: Annotated[Optional[float], typer.Option(help="L_smooth along rays compares only samples whose SDF lies within this many meters of the zero level (the surface's normals, not those of the empty space under a crotch or an armpit) \\[default: the preset's].")] = None,
    beta_init: Annotated[Optional[float], typer.Option(help="VolSDF beta (meters) when photometric training starts \\[default: the preset's].")] = None,
    beta_final: Annotated[Optional[float], typer.Option(help="Cap that beta is annealed down to (meters): the rendered silhouette sits ~3 beta outside the zero level (meshes are made there, see export --surface-level), so a smaller cap means a sharper surface \\[default: the preset's].")] = None,
    beta_anneal_fraction: Annotated[Optional[float], typer.Option(help="Share of training over which the cap on beta falls geometrically from --beta-init to --beta-final \\[default: 0.8].")] = None,
    lr_decay_power: Annotated[Optional[float], typer.Option(help="The learning rate is lr * (1 - step / steps) ** power, times a linear warm-up over the preset's first steps (the official code: 1.75; 0: no decay) \\[default: 1.75].")] = None,
    free_space_weight: Annotated[Optional[float], typer.Option(help="Weight of the visual-hull free-space term: canonical points the training masks rule out keep an SDF at least their distance to the hull (0: off) \\[default: the preset's].")] = None,
    body_inside_weight: Annotated[Optional[float], typer.Option(help="Weight of the body-inside term: at points inside the body model's naked template that the masks confirm, the SDF may not exceed the template's by more than 5 mm (keeps fingers and toes the images cannot resolve; a template that spills past masks of 1.5 cm pixels or finer, a fit too heavy, is not used; 0: off; no effect without a template) \\[default: the preset's: cpu 10, paper 0].")] = None,
    body_inside_max_spill: Annotated[Optional[float], typer.Option(help="The body-inside term's fit check: the largest share of views (mean over its points) in which the template may fall outside the masks; fitted templates with exact masks give under 0.02, a fit 1 cm too heavy or masks 1 px too tight about 0.06 (1: never refuse) \\[default: 0.035].")] = None,
    sdf_encoding: Annotated[
        Optional[str], typer.Option(help="hashgrid (the paper) or mlp (no hash grid: the slow-but-smooth baseline) \\[default: hashgrid].")
    ] = None,
    table_adam: Annotated[
        Optional[str], typer.Option(help="Adam on the hash table: sparse (entries no sample reached stay put, as tiny-cuda-nn) or dense (torch's Adam: they drift on their momentum; the ablation) \\[default: sparse].")
    ] = None,
    table_lr_factor: Annotated[Optional[float], typer.Option(help="Learning rate of the hash table relative to the preset's lr \\[default: the preset's: cpu 2, paper 1].")] = None,
    decoupled_color: Annotated[bool, typer.Option(
        help="Keep colour off the geometry, for clothes with bold stripes or checks that otherwise get carved into "
             "the surface: the colour network gets a hash grid of its own and neither its inputs nor the rendering "
             "weights pass the colour loss on to the shape (the four --color-* options below override it one by "
             "one). Bold stripes: CD-L1 5.4 -> 3.6 mm, NC 0.90 -> 0.96, sharper renders; plain or loose clothes lose "
             "the images' help with the shape (CD-L1 5.0 -> 5.8 mm on the demo); +7 % time a step.")] = False,
    color_normal_gradient: Annotated[Optional[bool], typer.Option(
        "--color-normal-gradient/--no-color-normal-gradient",
        help="Let the colour loss move the surface through the colour network's normal input (the paper's code); "
             "--no-color-normal-gradient detaches it, so that bold patterns are not carved into the geometry "
             "\\[default: the preset's: on].")] = None,
    color_feature_gradient: Annotated[Optional[bool], typer.Option(
        "--color-feature-gradient/--no-color-feature-gradient",
        help="Let the colour loss reshape the geometry through the SDF features the colour network reads (the "
             "paper's code); --no-color-feature-gradient detaches them \\[default: the preset's: on].")] = None,
    color_shapes_geometry: Annotated[Optional[bool], typer.Option(
        "--color-shapes-geometry/--no-color-shapes-geometry",
        help="Let the colour loss move the surface through the volume-rendering weights (the paper); "
             "--no-color-shapes-geometry leaves the shape to the masks, priors and regularizers "
             "\\[default: the preset's: on].")] = None,
    color_weights_gradient: Annotated[Optional[float], typer.Option(
        help="Scale in [0, 1] of what the colour loss passes to the surface through the volume-rendering weights "
             "(1: the paper; 0: as --no-color-shapes-geometry); the colours still get their whole gradient "
             "\\[default: the preset's: cpu 0.3 (inside the outline band, --color-weights-outline-px), paper and tiny 1].")] = None,
    color_weights_outline_px: Annotated[Optional[int], typer.Option(
        help="Pixels from the mask's outline within which the colour loss passes its whole gradient through the "
             "weights; elsewhere --color-weights-gradient applies. The images then shape the silhouette without "
             "carving a pattern inside it \\[default: the preset's: cpu the images' longer side / 128 (4 at 512 px), paper and tiny 0 (off)].")] = None,
    color_weights_edge_contrast: Annotated[Optional[float], typer.Option(
        help="Luma contrast in [0, 1]: a ray off the outline band whose window (the band's width) spans more than "
             "this on the person lies on a pattern's edge (a stripe, a checker, a logo) and passes none of the "
             "colour loss's gradient through the weights, since a pattern carves only where its colour changes; 0: off "
             "\\[default: the preset's: 0 (off)].")] = None,
    color_grid: Annotated[Optional[bool], typer.Option(
        "--color-grid/--no-color-grid",
        help="Give the colour network a hash grid of its own (the SDF grid's table, at most 8 levels up to 512 cells) beside the SDF's features. "
             "Without it bold stripes get carved into the surface and a real capture's clothes blur into one colour; "
             "--no-color-grid is the paper's network, a little better on plain clothes "
             "\\[default: the preset's: cpu on, paper off].")] = None,
    shading: Annotated[Optional[str], typer.Option(
        help="How the posed colour is lit: none (the paper: one colour per canonical point, whichever way it faces) "
             "or sh9 (that colour is the albedo, times the clip's light as nine spherical harmonics of the posed "
             "surface's normal: a person turning in a fixed light keeps its shading out of the texture, and exported "
             "meshes carry the albedo) \\[default: the preset's: cpu sh9, paper and tiny none].")] = None,
    error_sampling: Annotated[Optional[float], typer.Option(
        help="Share of the subject's ray patches, and of the frame draws, sent where a running map of the colour "
             "error is highest (Instant-NGP's error map) instead of uniformly; 0 is uniform "
             "\\[default: the preset's: 0].")] = None,
    outline_sampling: Annotated[Optional[float], typer.Option(
        help="Share of the subject's ray patches centred on the edge of the person's mask instead of anywhere on "
             "the person: most of a held-out frame's error lies on the outline; 0 is uniform "
             "\\[default: the preset's: cpu 0.5, paper and tiny 0].")] = None,
    quiet: Quiet = False,
    json_out: JsonOut = False,
) -> None:
    """Train the hash-grid SDF avatar on a dataset artifact and write a model artifact."""
    from stages.train import TrainOptions, run_train

    layout = RunLayout(run_dir)
    options = TrainOptions(
        dataset=dataset or layout.dataset, out=out or layout.model, preset=preset, steps=steps, rays_per_step=rays,
        samples_per_ray=samples, regularizer=regularizer, smooth_weight=smooth_weight, smooth_pairs=smooth_pairs, smooth_form=smooth_form, smooth_band=smooth_band,
        beta_init=beta_init, beta_final=beta_final, beta_anneal_fraction=beta_anneal_fraction,
        lr_decay_power=lr_decay_power, free_space_weight=free_space_weight,
        body_inside_weight=body_inside_weight, body_inside_max_spill=body_inside_max_spill, sdf_encoding=sdf_encoding, table_adam=table_adam, table_lr_factor=table_lr_factor,
        seed=seed, device=device, resume=resume, force=force, refine_poses=refine_poses, pose_lr=pose_lr,
        pose_prior_weight=pose_prior_weight, pose_silhouette_steps=pose_silhouette_steps,
        pose_silhouette_smoothness=pose_silhouette_smoothness, pose_prior_vote=pose_prior_vote,
        pose_align_steps=pose_align_steps,
        color_normal_gradient=color_normal_gradient, color_grid=color_grid,
        color_feature_gradient=color_feature_gradient, color_shapes_geometry=color_shapes_geometry,
        color_weights_gradient=color_weights_gradient, color_weights_outline_px=color_weights_outline_px,
        color_weights_edge_contrast=color_weights_edge_contrast,
        decoupled_color=decoupled_color, shading=shading,
        error_sampling=error_sampling, outline_sampling=outline_sampling,
        view=_view_settings(view, view_host, view_port, view_mesh_every, view_mesh_resolution),
    )
    run_stage(run_train, options, quiet, json_out)
