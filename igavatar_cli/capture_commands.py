"""`igavatar synth` and `igavatar preprocess`: the commands that make a capture and a dataset
(registered on the app by igavatar_cli.main)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from igavatar.errors import InputError
from igavatar_cli.cli_common import JsonOut, Quiet, RunDir, run_stage, user_errors
from igavatar_cli.help_panels import ADVANCED, CONSOLE, INPUTS, QUALITY, help_panels
from stages.layout import DEFAULT_RUN_DIR, RunLayout


@user_errors
@help_panels({INPUTS: ("out", "run_dir", "force"), QUALITY: ("resolution", "train_frames", "test_frames", "holdout_frames", "seed"),
              "Subject": ("phenotype", "garment", "texture", "skeleton"), ADVANCED: ("anny_cache",), CONSOLE: ("quiet", "json_out")})
def synth(
    out: Annotated[Optional[Path], typer.Option(help="Capture directory to write \\[default: RUN_DIR/capture].")] = None,
    run_dir: RunDir = DEFAULT_RUN_DIR,
    resolution: Annotated[int, typer.Option(help="Image height and width in pixels.", min=32, max=4096)] = 512,
    train_frames: Annotated[int, typer.Option(help="Frames of the 360-degree turn in A-pose (training split).", min=1)] = 100,
    test_frames: Annotated[int, typer.Option(help="Frames of novel poses (walk, arm raise, squat; test split).", min=0)] = 30,
    holdout_frames: Annotated[
        int, typer.Option(help="Frames of a second A-pose turn in the test split (in-distribution poses, new views).", min=0)
    ] = 0,
    phenotype: Annotated[
        Optional[list[str]], typer.Option(help="Anny phenotype value, repeatable: --phenotype gender=0.2 --phenotype weight=0.7 \\[default: the built-in subject's].")
    ] = None,
    garment: Annotated[str, typer.Option(help="Garment variant: shirt-trousers, dress, tight.")] = "shirt-trousers",
    texture: Annotated[str, typer.Option(help="Texture variant: stripes, checker, plain, or bold (3 cm dark-green stripes on white, a green checker: the pattern that carves surfaces).")] = "stripes",
    seed: Annotated[int, typer.Option(help="Random seed (motion jitter, colors).")] = 0,
    skeleton: Annotated[str, typer.Option(
        help="How the poses are written: anny (the body model), bare (its joints as a bare skeleton, no template) "
             "or root (a static subject: one root joint, held still while it turns; needs --test-frames 0).")] = "anny",
    anny_cache: Annotated[Optional[Path], typer.Option(help="Anny body-model cache directory \\[default: ~/.cache/anny].")] = None,
    force: Annotated[bool, typer.Option(help="Redo even if an identical capture exists.")] = False,
    quiet: Quiet = False,
    json_out: JsonOut = False,
) -> None:
    """Make a synthetic monocular capture (capture v1) of a clothed, textured Anny subject."""
    from stages.synth import SynthOptions, run_synth

    options = SynthOptions(
        out=out or RunLayout(run_dir).capture, resolution=resolution, train_frames=train_frames,
        test_frames=test_frames, holdout_frames=holdout_frames, phenotype=tuple(phenotype or ()), garment=garment, texture=texture,
        seed=seed, skeleton=skeleton, anny_cache=anny_cache, force=force,
    )
    run_stage(run_synth, options, quiet, json_out)


@user_errors
@help_panels({INPUTS: ("capture", "out", "run_dir", "input_format", "smpl_model", "force"),
              "Video": ("video", "every", "max_frames", "test_every", "height", "focal", "fov", "poses_from"),
              QUALITY: ("max_size",),
              ADVANCED: ("shape_prior", "body_fit", "grid_resolution", "weight_smoothing", "weight_spread", "anny_cache"),
              CONSOLE: ("quiet", "json_out")})
def preprocess(
    capture: Annotated[Optional[Path], typer.Option(
        help="Capture directory to read, or with --video to write \\[default: RUN_DIR/capture].")] = None,
    out: Annotated[Optional[Path], typer.Option(help="Dataset directory to write \\[default: RUN_DIR/dataset].")] = None,
    run_dir: RunDir = DEFAULT_RUN_DIR,
    input_format: Annotated[str, typer.Option("--format", help="Input layout: auto (detect), capture-v1, peoplesnapshot, xhumans or humannerf.")] = "auto",
    max_size: Annotated[int, typer.Option(help="Resize images so the longer side is at most this many pixels.", min=16)] = 512,
    grid_resolution: Annotated[
        str, typer.Option(help="Skinning-weight grid D,H,W (z,y,x) in canonical space.")
    ] = "64,16,64",
    weight_smoothing: Annotated[Optional[int], typer.Option(
        help="Blur passes over the skinning-weight grid \\[default: 15 for a body model's template, 2 for a bare "
             "skeleton's bone weights]; fewer keeps the weights sharp where limbs meet.", min=0)] = None,
    weight_spread: Annotated[Optional[float], typer.Option(
        help="Near a template (within 5 cm, handing over by 15 cm) take its own skinning weights, blended by a "
             "Gaussian of width 1 cm + SPREAD x the distance to the body, instead of the blurred grid, which "
             "leaks weight between the thighs and from the arms into the flanks; 0 turns it off (the blurred grid "
             "everywhere) \\[default: 1].", min=0.0)] = None,
    anny_cache: Annotated[Optional[Path], typer.Option(help="Anny body-model cache directory \\[default: ~/.cache/anny].")] = None,
    smpl_model: Annotated[
        Optional[Path],
        typer.Option(
            envvar="IGAVATAR_SMPL_MODEL",
            help="Your licensed SMPL model file (SMPL_NEUTRAL/MALE/FEMALE .pkl or .npz from smpl.is.tue.mpg.de), "
            "needed by captures with SMPL poses; igavatar never ships or downloads it \\[default: none].",
        ),
    ] = None,
    shape_prior: Annotated[str, typer.Option(
        help="auto: the body model's template, or the masks' visual hull in canonical space when there is no template "
             "or when 1 %+ of the subject's pixels lie 4 cm+ outside the posed template (a dress, a coat, long hair; "
             "needs 8+ training frames); template: the template always; visual-hull: the hull even over tight clothes.")] = "auto",
    body_fit: Annotated[str, typer.Option(
        help="A bare skeleton (joints only) of Anny's or SMPL's kind: anny fits the Anny body model to its joints "
             "(proportions from the bones, average girth) and uses it as the template, with its skinning weights; "
             "none keeps the masks' visual hull and bone-distance weights. Body-model captures ignore it.")] = "anny",
    force: Annotated[bool, typer.Option(help="Redo even if the inputs and options are unchanged.")] = False,
    video: Annotated[Optional[Path], typer.Option(
        help="A clip of one person filmed by a still camera (mp4, mov, webm, avi, mkv, gif, or a folder of frames): "
             "igavatar finds the person (MediaPipe, offline), fits the Anny body to the whole clip and writes the "
             "capture at --capture first, then the dataset \\[default: none: read --capture].", rich_help_panel="Video")] = None,
    every: Annotated[int, typer.Option(help="Video: keep every N-th frame.", min=1, rich_help_panel="Video")] = 1,
    max_frames: Annotated[int, typer.Option(
        help="Video: keep at most this many frames, evenly spaced (after dropping blurred and duplicate ones).",
        min=9, rich_help_panel="Video")] = 300,
    test_every: Annotated[int, typer.Option(
        help="Video: hold out every K-th kept frame for `eval` (0: none).", min=0, rich_help_panel="Video")] = 8,
    height: Annotated[float, typer.Option(
        help="Video: the person's height in meters. It sets the avatar's size in meters (one view cannot tell size "
             "from distance); the images and proportions do not depend on it.", rich_help_panel="Video")] = 1.70,
    focal: Annotated[Optional[float], typer.Option(
        help="Video: focal length in pixels of the frames as read (longer side at most 1024 px) "
             "\\[default: from --fov].", rich_help_panel="Video")] = None,
    fov: Annotated[Optional[float], typer.Option(
        help="Video: field of view in degrees across the longer side \\[default: 50]; a phone's main camera films "
             "about 65-70, zoomed in less.", rich_help_panel="Video")] = None,
    poses_from: Annotated[Optional[Path], typer.Option(
        help="Video: SMPL poses a GPU estimator made for this clip, in place of igavatar's own fit: WHAM's "
             "wham_output.pkl or TRAM's hps/hps_track_K.npy (their camera-frame estimate; needs --smpl-model). "
             "GVHMR's SMPL-X output is not supported \\[default: none: igavatar fits Anny].",
        rich_help_panel="Video")] = None,
    quiet: Quiet = False,
    json_out: JsonOut = False,
) -> None:
    """Turn a capture (images, masks, cameras, body poses), or a video of one person (--video), into a dataset
    artifact that `train` reads."""
    from stages.preprocess import PreprocessOptions, parse_grid_resolution, run_preprocess
    from stages.video import VideoOptions

    if poses_from is not None and video is None:
        raise InputError(f"--poses-from {poses_from}: needs --video, the clip the poses were estimated on")
    layout = RunLayout(run_dir)
    options = PreprocessOptions(
        capture=capture or layout.capture, out=out or layout.dataset, input_format=input_format,
        max_size=max_size, grid_resolution=parse_grid_resolution(grid_resolution),
        weight_smoothing=weight_smoothing, weight_spread=weight_spread, anny_cache=anny_cache,
        smpl_model=smpl_model, shape_prior=shape_prior, body_fit=body_fit, force=force,
        video=None if video is None else VideoOptions(
            video=video, out=capture or layout.capture, every=every, max_frames=max_frames, test_every=test_every,
            height_m=height, focal_px=focal, fov_deg=fov, anny_cache=anny_cache, poses_from=poses_from,
            smpl_model=smpl_model, force=force),
    )
    run_stage(run_preprocess, options, quiet, json_out)
