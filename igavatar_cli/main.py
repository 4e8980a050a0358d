"""The `igavatar` command: thin Typer wrappers that call one stage each.

    igavatar synth && igavatar preprocess && igavatar validate igavatar-run/dataset

Commands only parse options, call a function in `stages/`, and print where the result is.
Library errors become one red line on stderr and a non-zero exit code; no tracebacks for
user mistakes. Heavy imports (torch, anny) happen inside commands so `--help` stays fast.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from functools import wraps
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console

from igavatar import __version__
from igavatar.artifacts.storage import storage_message
from igavatar.errors import IgavatarError, InputError, ResourceLimitError, StorageError, Terminated
from igavatar.interrupts import signals_as_interrupts
from igavatar_cli.help_panels import ADVANCED, CONSOLE, INPUTS, QUALITY, help_panels
from stages.layout import DEFAULT_RUN_DIR, RunLayout
from stages.resources import tune_host_allocator

app = typer.Typer(
    no_args_is_help=True,
    add_completion=False,
    help="Turn a monocular video of a person into an animatable 3D avatar (InstantGeoAvatar).",
    pretty_exceptions_enable=False,
)
err_console = Console(stderr=True)
out_console = Console()

RunDir = Annotated[Path, typer.Option("--run-dir", help="Run directory holding every artifact by default.")]
Quiet = Annotated[bool, typer.Option("--quiet", "-q", help="No progress bars; print only the result.")]
JsonOut = Annotated[bool, typer.Option("--json", help="Print a JSON summary on stdout.")]


def _version_callback(value: bool) -> None:
    if value:
        out_console.print(f"igavatar {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        Optional[bool], typer.Option("--version", callback=_version_callback, is_eager=True, help="Show the version and exit.")
    ] = None,
) -> None:
    """igavatar: hash-grid SDF avatars from monocular video, in minutes, on CPU or GPU."""
    # Every command that trains or renders allocates large short-lived tensors; see the docstring.
    tune_host_allocator()


def _error_line(message: str) -> None:
    # markup=False for the message: paths and shapes may contain [brackets].
    err_console.print("[bold red]error:[/] ", end="", highlight=False)
    err_console.print(message, markup=False, highlight=False, soft_wrap=True)


def user_errors(func: Callable) -> Callable:
    """Turn library errors, Ctrl-C, SIGTERM and fixable disk/memory failures into one line and an exit code."""

    @wraps(func)
    def wrapper(*args, **kwargs):
        try:
            with signals_as_interrupts():
                return func(*args, **kwargs)
        except IgavatarError as exc:
            _error_line(str(exc))
            raise typer.Exit(exc.exit_code) from None
        except Terminated:
            err_console.print("[yellow]terminated[/] (SIGTERM): nothing half-written was kept; earlier artifacts are untouched")
            raise typer.Exit(143) from None
        except KeyboardInterrupt:
            err_console.print("[yellow]interrupted[/]: nothing half-written was kept; earlier artifacts are untouched")
            raise typer.Exit(130) from None
        except OSError as exc:
            # A safety net: stages translate these themselves; one that slipped through is still the
            # user's disk, not a bug, when it is one of the fixable kinds.
            message = storage_message(exc, Path.cwd())
            if message is None:
                raise
            _error_line(message)
            raise typer.Exit(StorageError.exit_code) from None
        except MemoryError:
            _error_line("out of memory; lower the sizes you chose (--resolution, --rays, --samples, image sizes) "
                        "or free memory, then run the command again")
            raise typer.Exit(ResourceLimitError.exit_code) from None

    return wrapper


def _print_summary(summary: dict, as_json: bool) -> None:
    if as_json:
        typer.echo(json.dumps(summary, indent=2, default=str))
        return
    for key, value in summary.items():
        out_console.print(f"[bold]{key}[/]: {value}", highlight=False, soft_wrap=True)


@app.command()
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
    from igavatar_cli.progress import progress_sink
    from stages.synth import SynthOptions, run_synth

    options = SynthOptions(
        out=out or RunLayout(run_dir).capture, resolution=resolution, train_frames=train_frames,
        test_frames=test_frames, holdout_frames=holdout_frames, phenotype=tuple(phenotype or ()), garment=garment, texture=texture,
        seed=seed, skeleton=skeleton, anny_cache=anny_cache, force=force,
    )
    with progress_sink(err_console, quiet=quiet or json_out) as progress:
        summary = run_synth(options, progress=progress)
    _print_summary(summary, json_out)


@app.command()
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
    from igavatar_cli.progress import progress_sink
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
    with progress_sink(err_console, quiet=quiet or json_out) as progress:
        summary = run_preprocess(options, progress=progress)
    _print_summary(summary, json_out)


def _view_settings(view: bool, host: str, port: int, mesh_every: int, mesh_resolution: int):
    if not view:
        return None
    from stages.train_view import ViewSettings

    return ViewSettings(host=host, port=port, mesh_every=mesh_every, mesh_resolution=mesh_resolution)


@app.command()
@user_errors
@help_panels({INPUTS: ("dataset", "out", "run_dir", "resume", "force"), QUALITY: ("preset", "steps", "rays", "samples", "seed", "device", "decoupled_color"),
              "Poses from a video": ("refine_poses", "pose_lr", "pose_prior_weight"),
              "Watch it in a browser": ("view", "view_host", "view_port", "view_mesh_every", "view_mesh_resolution"),
              ADVANCED: ("regularizer", "smooth_weight", "smooth_pairs", "smooth_form", "smooth_band", "beta_init",
                         "beta_final", "free_space_weight", "body_inside_weight", "body_inside_max_spill", "sdf_encoding",
                         "table_adam", "table_lr_factor", "color_normal_gradient", "color_feature_gradient", "color_shapes_geometry",
                         "color_grid",
                         "error_sampling"),
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
        help="Optimise per-frame corrections of the training poses with the avatar, kept near the estimate; saved "
             "in the model (refined_poses.npz) and used by export, animate and eval for those frames "
             "\\[default: off: on synthetic clips it has not yet improved the avatar at the cpu preset's steps, "
             "and it costs about a quarter more time a step].")] = None,
    pose_lr: Annotated[Optional[float], typer.Option(
        help="Learning rate of the pose corrections \\[default: 0.002].")] = None,
    pose_prior_weight: Annotated[Optional[float], typer.Option(
        help="Weight that keeps the refined poses near the estimate \\[default: 0.01].")] = None,
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
    color_grid: Annotated[Optional[bool], typer.Option(
        "--color-grid/--no-color-grid",
        help="Give the colour network a hash grid of its own (the SDF grid's table, at most 8 levels up to 512 cells) beside the SDF's features "
             "\\[default: the preset's: off].")] = None,
    error_sampling: Annotated[Optional[float], typer.Option(
        help="Share of the subject's ray patches, and of the frame draws, sent where a running map of the colour "
             "error is highest (Instant-NGP's error map) instead of uniformly; 0 is uniform "
             "\\[default: the preset's: 0].")] = None,
    quiet: Quiet = False,
    json_out: JsonOut = False,
) -> None:
    """Train the hash-grid SDF avatar on a dataset artifact and write a model artifact."""
    from igavatar_cli.progress import progress_sink
    from stages.train import TrainOptions, run_train

    layout = RunLayout(run_dir)
    options = TrainOptions(
        dataset=dataset or layout.dataset, out=out or layout.model, preset=preset, steps=steps, rays_per_step=rays,
        samples_per_ray=samples, regularizer=regularizer, smooth_weight=smooth_weight, smooth_pairs=smooth_pairs, smooth_form=smooth_form, smooth_band=smooth_band,
        beta_init=beta_init, beta_final=beta_final, free_space_weight=free_space_weight,
        body_inside_weight=body_inside_weight, body_inside_max_spill=body_inside_max_spill, sdf_encoding=sdf_encoding, table_adam=table_adam, table_lr_factor=table_lr_factor,
        seed=seed, device=device, resume=resume, force=force, refine_poses=refine_poses, pose_lr=pose_lr,
        pose_prior_weight=pose_prior_weight, color_normal_gradient=color_normal_gradient, color_grid=color_grid,
        color_feature_gradient=color_feature_gradient, color_shapes_geometry=color_shapes_geometry,
        decoupled_color=decoupled_color,
        error_sampling=error_sampling,
        view=_view_settings(view, view_host, view_port, view_mesh_every, view_mesh_resolution),
    )
    with progress_sink(err_console, quiet=quiet or json_out) as progress:
        summary = run_train(options, progress=progress)
    _print_summary(summary, json_out)


@app.command()
@user_errors
@help_panels({INPUTS: ("model", "out", "run_dir", "formats", "force"), QUALITY: ("resolution", "target_faces", "device"),
              "Posed meshes": ("pose", "frame", "all_frames", "nonrigid", "posed_marching", "anny_cache"),
              "Game engines and textures": ("glb_faces", "influences", "texture_size", "textured_faces", "texture_from",
                                            "texture_views", "dataset"),
              ADVANCED: ("coarse_resolution", "min_component_ratio", "taubin_steps", "surface_level", "exr", "exr_size"),
              CONSOLE: ("quiet", "json_out")})
def export(
    model: Annotated[Optional[Path], typer.Option(help="Model directory \\[default: RUN_DIR/model].")] = None,
    out: Annotated[Optional[Path], typer.Option(help="Mesh directory to write \\[default: RUN_DIR/mesh].")] = None,
    run_dir: RunDir = DEFAULT_RUN_DIR,
    formats: Annotated[str, typer.Option(help="Comma-separated: ply, obj (vertex colors), glb (rigged, Y-up; with --pose animated).")] = "ply,obj,glb",
    resolution: Annotated[
        int, typer.Option(help="Marching-cubes samples on the longest axis of the surface box (the paper's 512; ~20-45 s on 2 CPU cores).", min=16)
    ] = 512,
    coarse_resolution: Annotated[int, typer.Option(help="Samples of the coarse pass that finds the surface box.", min=8)] = 64,
    min_component_ratio: Annotated[
        Optional[float], typer.Option(help="Keep components with at least this fraction of the largest one's faces \\[default: only the largest].")
    ] = None,
    taubin_steps: Annotated[int, typer.Option(help="Taubin smoothing iterations (0: none).", min=0)] = 0,
    target_faces: Annotated[Optional[int], typer.Option(help="Decimate the PLY/OBJ to at most this many faces \\[default: no decimation].", min=4)] = None,
    influences: Annotated[
        int, typer.Option(help="Skin weights per vertex in the GLB: 4 (JOINTS_0; web engines) or 8 (JOINTS_0/1; Blender).")
    ] = 4,
    texture_size: Annotated[
        int, typer.Option(help="Also write textured/avatar.glb|.obj|.png: decimated, UV-unwrapped, color baked into an SxS texture (e.g. 1024 or 2048; 0: none).", min=0)
    ] = 0,
    textured_faces: Annotated[int, typer.Option(help="Face budget of the textured mesh (quadric decimation).", min=4)] = 30_000,
    texture_from: Annotated[str, typer.Option(
        help="What --texture-size's texture is made from: images (the training images projected onto the posed "
             "mesh and fused, weighted by angle and distance; the color network fills what no camera saw; test "
             "frames are never used; needs the model's dataset) or field (the color network alone).")] = "images",
    texture_views: Annotated[int, typer.Option(
        help="--texture-from images: at most this many training frames, evenly spread (0: all).", min=0)] = 0,
    dataset: Annotated[Optional[Path], typer.Option(
        help="--texture-from images: the dataset whose training images are used \\[default: the model's].")] = None,
    glb_faces: Annotated[int, typer.Option(
        help="Face budget of canonical.glb, decimated for game engines and browsers (its distance to the full mesh "
             "is in the manifest); 0 keeps the full mesh. PLY/OBJ stay at full resolution.", min=0)] = 50_000,
    pose: Annotated[
        Optional[Path], typer.Option(help="Pose the avatar: a pose .npz (capture v1 Anny poses.npz), a capture directory or a dataset artifact \\[default: none: the canonical mesh only].")
    ] = None,
    frame: Annotated[Optional[int], typer.Option(help="Frame of --pose to export \\[default: 0].", min=0)] = None,
    all_frames: Annotated[bool, typer.Option("--all", help="Export every frame of --pose.")] = False,
    nonrigid: Annotated[bool, typer.Option(help="Apply the pose-conditioned non-rigid offset to posed meshes.")] = True,
    posed_marching: Annotated[
        bool, typer.Option(help="Also run marching cubes in posed space through the deformer (slow), to compare.")
    ] = False,
    exr: Annotated[bool, typer.Option(help="Write depth and normal maps (OpenEXR) of frontal views of each mesh.")] = False,
    surface_level: Annotated[str, typer.Option(
        help="Where the mesh is made: silhouette (the level set where the renderer's silhouette lies, ~3 beta outside the SDF's zero level) or zero (the zero level).")] = "silhouette",
    exr_size: Annotated[int, typer.Option(help="Size of the EXR maps in pixels.", min=8)] = 512,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda.")] = "auto",
    anny_cache: Annotated[Optional[Path], typer.Option(help="Anny body-model cache directory \\[default: ~/.cache/anny].")] = None,
    force: Annotated[bool, typer.Option(help="Redo even if the inputs and options are unchanged.")] = False,
    quiet: Quiet = False,
    json_out: JsonOut = False,
) -> None:
    """Extract the canonical mesh (PLY/OBJ/rigged GLB) and, with --pose, posed meshes in world coordinates."""
    from igavatar_cli.progress import progress_sink
    from stages.export import ExportOptions, parse_formats, run_export

    layout = RunLayout(run_dir)
    options = ExportOptions(
        model=model or layout.model, out=out or layout.mesh, formats=parse_formats(formats), resolution=resolution,
        coarse_resolution=coarse_resolution, min_component_ratio=min_component_ratio, taubin_steps=taubin_steps,
        target_faces=target_faces, influences=influences, texture_size=texture_size, textured_faces=textured_faces,
        texture_from=texture_from, texture_views=texture_views, dataset=dataset, glb_faces=glb_faces,
        pose=pose, frame=frame, all_frames=all_frames, nonrigid=nonrigid,
        posed_marching=posed_marching, exr=exr, exr_size=exr_size, device=device, anny_cache=anny_cache, force=force,
        surface_level=surface_level,
    )
    with progress_sink(err_console, quiet=quiet or json_out) as progress:
        summary = run_export(options, progress=progress)
    _print_summary(summary, json_out)


@app.command()
@user_errors
@help_panels({INPUTS: ("motion", "model", "out", "run_dir", "anny_cache"),
              "Motion": ("seconds", "fps", "frames", "travel", "seed"),
              "Camera": ("camera", "camera_file", "dataset", "revolutions"),
              QUALITY: ("resolution", "samples", "device"),
              "Meshes and GLB": ("meshes", "mesh_resolution", "surface_level", "glb", "influences"),
              CONSOLE: ("quiet", "json_out")})
def animate(
    motion_arg: Annotated[
        Optional[str], typer.Argument(metavar="[MOTION]", help="Procedural motion (walk, turn, arm_raise, squat, turntable), a pose .npz (Anny, SMPL, AMASS, skeleton), a capture directory or a dataset.")
    ] = None,
    motion: Annotated[Optional[str], typer.Option("--motion", help="Same as MOTION \\[default: walk].")] = None,
    model: Annotated[Optional[Path], typer.Option(help="Model directory \\[default: RUN_DIR/model].")] = None,
    out: Annotated[Optional[Path], typer.Option(help="Animation directory to write \\[default: RUN_DIR/animation].")] = None,
    run_dir: RunDir = DEFAULT_RUN_DIR,
    seconds: Annotated[float, typer.Option(help="Length of a procedural motion in seconds.")] = 2.0,
    fps: Annotated[Optional[float], typer.Option(help="Frames per second of the motion and the video \\[default: the pose file's, else 30].")] = None,
    frames: Annotated[Optional[int], typer.Option(help="Number of frames (procedural: instead of --seconds; pose file: its first N) \\[default: from --seconds, or the whole pose file].", min=1)] = None,
    travel: Annotated[bool, typer.Option(help="Let the walk move forward (~0.8 m/s) instead of walking in place.")] = False,
    seed: Annotated[int, typer.Option(help="Seed of the procedural motion (pace, amplitudes).")] = 0,
    camera: Annotated[str, typer.Option(help="turntable (orbits the subject), front (static) or capture (the dataset's first camera).")] = "turntable",
    camera_file: Annotated[Optional[Path], typer.Option(help="npz with K (3,3), w2c (4,4) (or per frame), height, width; overrides --camera \\[default: none: --camera].")] = None,
    dataset: Annotated[Optional[Path], typer.Option(help="Dataset for --camera capture \\[default: the one the model was trained on].")] = None,
    revolutions: Annotated[float, typer.Option(help="Turns of the turntable camera over the animation.")] = 1.0,
    resolution: Annotated[int, typer.Option(help="Longer image side in pixels.", min=8)] = 256,
    samples: Annotated[Optional[int], typer.Option(help="Samples per ray \\[default: the model's validation setting].", min=1)] = None,
    meshes: Annotated[bool, typer.Option(help="Also write the posed mesh of every frame (meshes/NNNN.ply).")] = False,
    mesh_resolution: Annotated[int, typer.Option(help="Marching-cubes resolution of the canonical mesh for --meshes and --glb.", min=16)] = 256,
    surface_level: Annotated[str, typer.Option(
        help="Where --meshes and --glb are made, as in export: silhouette (the level set where the renderer's "
             "silhouette lies, ~3 beta outside the SDF's zero level) or zero (the zero level).")] = "silhouette",
    glb: Annotated[bool, typer.Option(help="Also write animation.glb: the rigged avatar (Y-up) playing the motion as a glTF animation clip.")] = False,
    influences: Annotated[int, typer.Option(help="Skin weights per vertex in the --glb file: 4 (web engines) or 8 (Blender).")] = 4,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda.")] = "auto",
    anny_cache: Annotated[Optional[Path], typer.Option(help="Anny body-model cache directory (Anny pose files) \\[default: ~/.cache/anny].")] = None,
    quiet: Quiet = False,
    json_out: JsonOut = False,
) -> None:
    """Render the avatar driven by a motion: PNG frames, an mp4, optionally posed meshes per frame and an animated GLB."""
    from igavatar_cli.progress import progress_sink
    from stages.animate import AnimateOptions, run_animate

    if motion_arg is not None and motion is not None and motion_arg != motion:
        raise InputError(f"MOTION {motion_arg!r} and --motion {motion!r} disagree; give one of them")
    layout = RunLayout(run_dir)
    options = AnimateOptions(
        model=model or layout.model, out=out or layout.animation, motion=motion_arg or motion or "walk",
        seconds=seconds, fps=fps, frames=frames, travel=travel, seed=seed, camera=camera, camera_file=camera_file,
        dataset=dataset, revolutions=revolutions, resolution=resolution, samples=samples, meshes=meshes,
        mesh_resolution=mesh_resolution, surface_level=surface_level, glb=glb, influences=influences, device=device,
        anny_cache=anny_cache,
    )
    with progress_sink(err_console, quiet=quiet or json_out) as progress:
        summary = run_animate(options, progress=progress)
    _print_summary(summary, json_out)


@app.command(name="eval")
@user_errors
@help_panels({INPUTS: ("model", "gt", "dataset", "out", "run_dir", "force"),
              QUALITY: ("geometry", "images", "image_scale", "image_frames", "samples", "device"),
              "Estimated poses": ("refine_test_poses", "refine_test_pose_steps"),
              ADVANCED: ("mesh_resolution", "surface_level", "surface_samples", "iou_points", "iou_open_meshes", "seed"),
              CONSOLE: ("quiet", "json_out")})
def eval_(
    model: Annotated[Optional[Path], typer.Option(help="Model directory \\[default: RUN_DIR/model].")] = None,
    gt: Annotated[
        Optional[Path],
        typer.Option("--gt", help="Folder of ground-truth scans <frame>.ply|.obj \\[default: scans/ of the capture the dataset was made from]."),
    ] = None,
    dataset: Annotated[
        Optional[Path], typer.Option(help="Dataset with the test frames \\[default: the one the model was trained on].")
    ] = None,
    out: Annotated[Optional[Path], typer.Option(help="Report directory to write \\[default: RUN_DIR/report].")] = None,
    run_dir: RunDir = DEFAULT_RUN_DIR,
    geometry: Annotated[bool, typer.Option("--geometry/--no-geometry", help="Compare posed meshes with the scans.")] = True,
    images: Annotated[bool, typer.Option("--images/--no-images", help="Render test frames and compare PSNR/SSIM.")] = True,
    mesh_resolution: Annotated[int, typer.Option(help="Marching-cubes resolution of the canonical mesh.", min=16)] = 256,
    surface_level: Annotated[str, typer.Option(
        help="Where the mesh is made: silhouette (the level set where the renderer's silhouette lies, ~3 beta outside the SDF's zero level) or zero (the zero level).")] = "silhouette",
    surface_samples: Annotated[int, typer.Option(help="Points sampled per surface (surface protocol).", min=1)] = 10_000,
    iou_points: Annotated[int, typer.Option(help="Uniform points of the volumetric IoU (0 skips it).", min=0)] = 1_000_000,
    iou_open_meshes: Annotated[
        bool, typer.Option(help="Estimate the IoU by ray parity even when a mesh is not watertight (flagged approximate).")
    ] = False,
    image_scale: Annotated[
        Optional[float], typer.Option(help="Render test frames at this fraction of the dataset's image size; 1 scores at full size, as papers report \\[default: 1 on a GPU, 0.25 on CPU].")
    ] = None,
    samples: Annotated[
        Optional[int], typer.Option("--samples", help="Samples per ray of the test renders \\[default: 128 on a GPU, 32 on CPU].", min=1)
    ] = None,
    image_frames: Annotated[
        Optional[int], typer.Option(help="Render this many test frames, evenly spaced; 0 = all \\[default: all on a GPU, 10 on CPU].", min=0)
    ] = None,
    refine_test_poses: Annotated[bool, typer.Option(
        help="Before scoring a test image, optimise that frame's pose against it (the avatar fixed), as peers "
             "do for estimated poses; image metrics only, recorded in the report. Geometry keeps the given poses.")] = False,
    refine_test_pose_steps: Annotated[int, typer.Option(help="Optimisation steps per test frame with --refine-test-poses.", min=1)] = 80,
    seed: Annotated[int, typer.Option(help="Seed of the surface samples and IoU points.")] = 0,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda.")] = "auto",
    force: Annotated[bool, typer.Option(help="Redo even if the report is up to date (same model, dataset, scans and options).")] = False,
    quiet: Quiet = False,
    json_out: JsonOut = False,
) -> None:
    """Compare the posed avatar with ground-truth scans (Chamfer, normal consistency, IoU) and test images (PSNR, SSIM)."""
    from igavatar_cli.progress import progress_sink
    from stages.eval import EvalOptions, run_eval

    layout = RunLayout(run_dir)
    options = EvalOptions(
        model=model or layout.model, out=out or layout.report, gt=gt, dataset=dataset, geometry=geometry,
        images=images, mesh_resolution=mesh_resolution, surface_samples=surface_samples, iou_points=iou_points,
        iou_open_meshes=iou_open_meshes, image_scale=image_scale, samples_per_ray=samples, image_frames=image_frames,
        seed=seed, device=device, surface_level=surface_level, refine_test_poses=refine_test_poses,
        refine_test_pose_steps=refine_test_pose_steps, force=force,
    )
    with progress_sink(err_console, quiet=quiet or json_out) as progress:
        summary = run_eval(options, progress=progress)
    _print_summary(summary, json_out)


@app.command()
@user_errors
@help_panels({INPUTS: ("run_dir",), QUALITY: ("preset", "steps", "resolution", "train_frames", "test_frames", "device", "seed"),
              CONSOLE: ("quiet", "json_out")})
def demo(
    run_dir: RunDir = DEFAULT_RUN_DIR,
    preset: Annotated[Optional[str], typer.Option(help="Training preset \\[default: paper on a GPU, else cpu].")] = None,
    steps: Annotated[Optional[int], typer.Option(help="Training steps \\[default: the preset's].")] = None,
    resolution: Annotated[int, typer.Option(help="Synthetic image size in pixels.", min=32)] = 512,
    train_frames: Annotated[int, typer.Option(help="Synthetic training frames.", min=1)] = 100,
    test_frames: Annotated[int, typer.Option(help="Synthetic test frames.", min=0)] = 30,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda.")] = "auto",
    seed: Annotated[int, typer.Option(help="Random seed of every stage.")] = 0,
    quiet: Quiet = False,
    json_out: JsonOut = False,
) -> None:
    """Run every stage on the built-in synthetic subject and print one summary.

    synth -> preprocess -> train (cpu preset, or paper on a GPU) -> export -> animate (walk) -> eval.
    """
    from rich.table import Table

    from igavatar_cli.progress import progress_sink
    from stages.demo import DemoOptions, run_demo

    options = DemoOptions(run_dir=run_dir, preset=preset, steps=steps, resolution=resolution,
                          train_frames=train_frames, test_frames=test_frames, device=device, seed=seed)
    with progress_sink(err_console, quiet=quiet or json_out) as progress:
        summary = run_demo(options, progress=progress)
    if json_out:
        _print_summary(summary, True)
        return
    table = Table(title=f"igavatar demo ({summary['preset']} preset) in {summary['run_dir']}")
    table.add_column("stage")
    table.add_column("seconds", justify="right")
    table.add_column("result")
    for name, result in summary["stages"].items():
        seconds = str(result.get("stage_seconds", "-"))
        details = ", ".join(f"{k}={v}" for k, v in result.items() if k != "stage_seconds")
        table.add_row(name, seconds, details)
    out_console.print(table)


@app.command()
@user_errors
@help_panels({CONSOLE: ("json_out",)})
def validate(
    path: Annotated[Path, typer.Argument(help="An artifact directory (or a capture v1 directory).")],
    json_out: JsonOut = False,
) -> None:
    """Check an artifact against its JSON schema and the sha256 of every file it lists."""
    from stages.validate import validate_path

    summary = validate_path(path)
    _print_summary(
        {"valid": str(summary.path), "kind": summary.kind, "schema_version": summary.schema_version,
         "files_checked": summary.files_checked},
        json_out,
    )


from igavatar_cli import batch_command, view_command  # noqa: E402  (they need the helpers above)

batch_command.register(app, user_errors, err_console, _print_summary)
view_command.register(app, user_errors, err_console, _print_summary, DEFAULT_RUN_DIR)


if __name__ == "__main__":
    app()
