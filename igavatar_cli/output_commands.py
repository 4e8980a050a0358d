"""`igavatar export`, `animate` and `eval`: the commands that read a model (registered on the app by
igavatar_cli.main)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from igavatar.errors import InputError
from igavatar_cli.cli_common import JsonOut, Quiet, RunDir, run_stage, user_errors
from igavatar_cli.help_panels import ADVANCED, CONSOLE, INPUTS, QUALITY, help_panels
from stages.layout import DEFAULT_RUN_DIR, RunLayout


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
    from stages.export import ExportOptions, run_export
    from stages.export_options import parse_formats

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
    run_stage(run_export, options, quiet, json_out)


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
    run_stage(run_animate, options, quiet, json_out)


@user_errors
@help_panels({INPUTS: ("model", "gt", "dataset", "out", "run_dir", "force"),
              QUALITY: ("geometry", "images", "image_scale", "image_frames", "samples", "device"),
              "Estimated poses": ("carry_poses", "refine_test_poses", "refine_test_pose_steps"),
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
        Optional[int], typer.Option("--samples", help="Samples per ray of the test renders \\[default: the model's validation setting, 96 for the cpu preset, 128 for paper].", min=1)
    ] = None,
    image_frames: Annotated[
        Optional[int], typer.Option(help="Render this many test frames, evenly spaced; 0 = all \\[default: all on a GPU, 10 on CPU].", min=0)
    ] = None,
    carry_poses: Annotated[bool, typer.Option(
        "--carry-poses/--no-carry-poses",
        help="For a model trained with --refine-poses: a test frame between refined training frames of the same clip "
             "(names frame_000123) takes their pose corrections, interpolated in time, for geometry and images; no "
             "test image is used; recorded per frame in the report. Off: the dataset's poses. On three synthetic video "
             "clips it gave +0.1 to +0.9 dB box PSNR, and CD-L1 -3.2 to +1.3 mm. export and animate always pose such "
             "frames so.")] = False,
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
    from stages.eval import EvalOptions, run_eval

    layout = RunLayout(run_dir)
    options = EvalOptions(
        model=model or layout.model, out=out or layout.report, gt=gt, dataset=dataset, geometry=geometry,
        images=images, mesh_resolution=mesh_resolution, surface_samples=surface_samples, iou_points=iou_points,
        iou_open_meshes=iou_open_meshes, image_scale=image_scale, samples_per_ray=samples, image_frames=image_frames,
        seed=seed, device=device, surface_level=surface_level, carry_poses=carry_poses, refine_test_poses=refine_test_poses,
        refine_test_pose_steps=refine_test_pose_steps, force=force,
    )
    run_stage(run_eval, options, quiet, json_out)
