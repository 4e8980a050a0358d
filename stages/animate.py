"""`igavatar animate`: a model artifact + a motion -> an animation artifact (frames, video, meshes).

    summary = run_animate(AnimateOptions(model=Path("run/model"), out=Path("run/animation"), motion="walk"))

The motion is a procedural one (walk, turn, arm_raise, squat, turntable: no files needed), a pose
file (any format of `igavatar.body.pose_files`), a capture v1 directory or a dataset artifact
(its training poses). The walk stays in place unless `travel`. Every frame gets its own posed box (the canonical
occupied cells pushed through forward skinning, padded by the non-rigid offset bound) and its own
posed occupancy grid, then is volume rendered with early ray termination; so out-of-distribution
poses render inside a bounded box and never reuse another frame's empty-space skipping.

Animation layout (schema `animation`, version 1):
    frames/<NNNN>.png    RGB renders on white, one per motion frame
    video.mp4            H.264 at the motion's fps (odd sizes padded by one edge pixel)
    cameras.npz          K (N,3,3), w2c (N,4,4), height, width (the `--camera-file` format)
    poses.npz            the driving motion as a skeleton pose sequence: parents (J,), rest_joints
                         (J,3), joint_names (J,), rotvecs (N,J,3) relative to the rest pose, transl (N,3)
    boxes.npz            posed_boxes (N,2,3) world boxes the frames were rendered in
    meshes/<NNNN>.ply    with --meshes: the posed surface per frame (world coordinates, vertex colors)
    animation.glb        with --glb: the rigged avatar (canonical surface at --mesh-resolution, vertex
                         colors, top-4 or --influences 8 skin weights, glTF's +Y-up frame) holding the
                         motion as one glTF animation clip: a rotation channel per joint and the root's
                         translation, one LINEAR key per frame at the motion's fps. The manifest gives,
                         per frame, how far the viewer's top-4 and top-8 skinning land from igavatar's
                         own posing (all weights + non-rigid offset), in mm.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import imageio
import numpy as np
import torch
import trimesh

from igavatar.artifacts.atomic import atomic_directory
from igavatar.artifacts.manifest import InputRecord, build_manifest
from igavatar.artifacts.targets import check_output_target
from igavatar.artifacts.png import png_bytes
from igavatar.avatar.boxes import posed_boxes
from igavatar.avatar.cameras import CameraSequence, camera_file, capture_camera, orbit_cameras
from igavatar.avatar.dataset import read_dataset
from igavatar.avatar.glb import write_model_glb
from igavatar.avatar.model import ModelArtifact, load_model, read_model_manifest
from igavatar.avatar.poses import DEFAULT_FPS, PoseSequence, procedural_poses, read_poses
from igavatar.avatar.surfaces import canonical_surface, vertex_colors, vertex_skin_weights
from igavatar.body.motions import MOTION_NAMES
from igavatar.body.rotations import matrix_to_axis_angle
from igavatar.errors import ArtifactError, InputError
from igavatar.mesh.cleanup import clean_mesh
from igavatar.model.avatar import SURFACE_LEVELS
from igavatar.mesh.gltf import INFLUENCE_CHOICES, INFLUENCES
from igavatar.mesh.skin_drift import skin_drift_mm, sparse_weight_sets
from igavatar.model.render_avatar import render_posed_view
from stages.common import StageClock
from stages.kernels import build_kernels, resolve_device
from stages.progress import NULL_PROGRESS, ProgressSink
from stages.resources import IMAGE_BYTES_PER_PIXEL, peak_cuda_bytes, peak_ram_bytes, require_marching_memory, require_memory

CAMERAS = ("turntable", "front", "capture")


@dataclass(frozen=True)
class AnimateOptions:
    """Options of `igavatar animate` (see the CLI for each one's help)."""

    model: Path
    out: Path
    motion: str = "walk"
    seconds: float = 2.0
    fps: float | None = None
    frames: int | None = None
    travel: bool = False
    seed: int = 0
    camera: str = "turntable"
    camera_file: Path | None = None
    dataset: Path | None = None
    revolutions: float = 1.0
    resolution: int = 256
    samples: int | None = None
    meshes: bool = False
    mesh_resolution: int = 256
    #: Where --meshes and --glb are made (SURFACE_LEVELS), as export and eval.
    surface_level: str = SURFACE_LEVELS[0]
    glb: bool = False
    influences: int = INFLUENCES
    device: str = "auto"
    anny_cache: Path | None = None


def _check_options(options: AnimateOptions) -> None:
    if options.camera not in CAMERAS:
        raise InputError(f"--camera {options.camera!r}: expected one of {', '.join(CAMERAS)}")
    if options.resolution < 8:
        raise InputError(f"--resolution {options.resolution}: expected at least 8 pixels")
    if options.samples is not None and options.samples < 1:
        raise InputError(f"--samples {options.samples}: expected at least 1")
    if (options.meshes or options.glb) and options.mesh_resolution < 16:
        raise InputError(f"--mesh-resolution {options.mesh_resolution}: expected at least 16")
    if options.surface_level not in SURFACE_LEVELS:
        raise InputError(f"--surface-level {options.surface_level!r}: choose one of {', '.join(SURFACE_LEVELS)}")
    if options.influences not in INFLUENCE_CHOICES:
        raise InputError(f"--influences {options.influences}: expected 4 (web engines) or 8 (JOINTS_1/WEIGHTS_1 too)")
    if options.fps is not None and not (math.isfinite(options.fps) and options.fps > 0):
        raise InputError(f"--fps {options.fps}: expected a positive number")
    if options.frames is not None and options.frames < 1:
        raise InputError(f"--frames {options.frames}: expected a positive number of frames")


# ---------------------------------------------------------------------------------------- motion
def _frame_count(options: AnimateOptions, fps: float) -> int:
    if options.frames is not None:
        return int(options.frames)
    if not (math.isfinite(options.seconds) and options.seconds > 0):
        raise InputError(f"--seconds {options.seconds}: expected a positive duration")
    return max(1, round(options.seconds * fps))


def resolve_motion(model: ModelArtifact, options: AnimateOptions, progress: ProgressSink = NULL_PROGRESS) -> PoseSequence:
    """MOTION as a procedural name, else as a pose file, capture or dataset (its first --frames frames)."""
    _check_options(options)
    if options.motion in MOTION_NAMES:
        fps = float(options.fps or DEFAULT_FPS)
        motion = procedural_poses(model, options.motion, _frame_count(options, fps), options.seed, fps, options.travel)
    else:
        path = Path(options.motion)
        if not path.exists():
            raise InputError(
                f"motion {options.motion!r}: neither a procedural motion ({', '.join(MOTION_NAMES)}) "
                "nor an existing pose file, capture directory or dataset"
            )

        def first_frames(n_frames: int, where: str) -> list[int]:
            return list(range(n_frames if options.frames is None else min(options.frames, n_frames)))

        motion = read_poses(model, path, first_frames, fps=options.fps, anny_cache=options.anny_cache,
                            on_status=progress.status, option="MOTION")
    if motion.n_frames == 0:
        raise InputError(f"motion {options.motion!r} has no frames")
    if motion.local_rotations.shape[1] != len(model.joint_names):
        raise InputError(f"motion {options.motion!r} has {motion.local_rotations.shape[1]} joints but the model "
                         f"{model.path} has {len(model.joint_names)}")
    if not (torch.isfinite(motion.local_rotations).all() and torch.isfinite(motion.root_translation).all()):
        raise InputError(f"motion {options.motion!r} contains NaN or infinite values")
    return motion


# --------------------------------------------------------------------------------------- cameras
def _cameras(model: ModelArtifact, options: AnimateOptions, motion: PoseSequence, boxes: torch.Tensor) -> CameraSequence:
    n_frames = motion.n_frames
    if options.camera_file is not None:
        return camera_file(options.camera_file, n_frames, options.resolution)
    if options.camera == "capture":
        dataset = Path(options.dataset) if options.dataset is not None else model.trained_dataset()
        if dataset is None or not (dataset / "frames.npz").is_file():
            raise InputError(
                f"--camera capture needs the dataset the model was trained on ({dataset or model.recorded_dataset}"
                "/frames.npz holds the capture cameras) and it is not there; pass --dataset DIR, or use --camera "
                "turntable or --camera-file"
            )
        return capture_camera(read_dataset(dataset, check_hashes=False), n_frames, options.resolution)
    revolutions = options.revolutions if options.camera == "turntable" else 0.0
    return orbit_cameras(model, boxes.cpu(), motion.bone_transforms, options.resolution, revolutions, options.camera)


# ---------------------------------------------------------------------------------------- output
def _even_frame(rgb: np.ndarray) -> np.ndarray:
    """H.264 (yuv420p) needs even sizes: repeat the last row/column when one is odd."""
    h, w = rgb.shape[:2]
    return np.pad(rgb, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


def _ply_bytes(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray) -> bytes:
    mesh = trimesh.Trimesh(vertices, faces, vertex_colors=colors, process=False)
    return mesh.export(file_type="ply")


@dataclass(frozen=True)
class _Surface:
    """The cleaned canonical mesh of --meshes/--glb: (V, 3), (F, 3), (V, 3) uint8 colors, (V, J) weights."""

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    skin_weights: np.ndarray | None


def _canonical_surface(model: ModelArtifact, options: AnimateOptions) -> _Surface:
    """Canonical mesh (largest component), its vertex colors and, for --glb, its skin weights.

    Closed by the canonical box at --surface-level, as export and eval make it."""
    vertices, faces = canonical_surface(model.avatar, resolution=options.mesh_resolution,
                                        surface_level=options.surface_level)
    if faces.shape[0] == 0:
        raise InputError(f"--meshes/--glb: the model {model.path} has no surface (its SDF never crosses zero); train it longer")
    vertices, faces, _ = clean_mesh(vertices, faces, keep_largest=True)
    weights = vertex_skin_weights(model.avatar, vertices) if options.glb else None
    return _Surface(vertices, faces, vertex_colors(model.avatar, vertices), weights)


@dataclass
class _Rendered:
    """What the render loop measured: per-frame subject coverage and skin drift, seconds spent."""

    coverage: list[float]
    drift: list[dict]
    render_s: float = 0.0
    render_cpu_s: float = 0.0
    mesh_s: float = 0.0


def _render_frames(tmp: Path, model: ModelArtifact, motion: PoseSequence, boxes: torch.Tensor, cameras: CameraSequence,
                   surface: _Surface | None, options: AnimateOptions, progress: ProgressSink) -> _Rendered:
    """frames/*.png, video.mp4 and meshes/*.ply of every frame; the skin drift of --glb."""
    device, n_frames = model.device, motion.n_frames
    num_samples = options.samples or model.config.validation_samples
    sparse_sets = sparse_weight_sets(surface.skin_weights) if surface is not None and surface.skin_weights is not None else None
    rendered = _Rendered([], [])
    (tmp / "frames").mkdir()
    if options.meshes:
        (tmp / "meshes").mkdir()
    writer = imageio.get_writer(tmp / "video.mp4", fps=motion.fps, codec="libx264", quality=8, macro_block_size=1,
                                ffmpeg_log_level="error")
    try:
        with progress.task(f"rendering {motion.name}", total=n_frames) as advance:
            for i in range(n_frames):
                tick, cpu_tick = time.perf_counter(), time.process_time()
                posed = model.posed(motion.bone_transforms[i], motion.pose_condition[i])
                image = render_posed_view(
                    posed, model.canonical_grid, cameras.K[i].to(device), cameras.w2c[i].to(device),
                    cameras.height, cameras.width, boxes[i].to(device), num_samples=num_samples,
                    occupancy_resolution=model.config.occupancy_resolution,
                )
                rgb = (image.rgb.clamp(0, 1).cpu().numpy() * 255).round().astype(np.uint8)
                rendered.render_s += time.perf_counter() - tick
                rendered.render_cpu_s += time.process_time() - cpu_tick
                rendered.coverage.append(float((image.opacity > 0.5).float().mean()))
                name = _frame_name(i, n_frames)
                (tmp / "frames" / f"{name}.png").write_bytes(png_bytes(rgb))
                writer.append_data(_even_frame(rgb))
                if surface is not None:
                    tick = time.perf_counter()
                    x_posed = posed.pose_vertices(surface.vertices)
                    if options.meshes:
                        (tmp / "meshes" / f"{name}.ply").write_bytes(_ply_bytes(x_posed, surface.faces, surface.colors))
                    if sparse_sets is not None:
                        rendered.drift.append(skin_drift_mm(surface.vertices, sparse_sets, motion.bone_transforms[i].to(device), x_posed))
                    rendered.mesh_s += time.perf_counter() - tick
                advance(1, **{"frames/s": f"{(i + 1) / max(rendered.render_s, 1e-9):.3f}"})
    finally:
        writer.close()
    return rendered


def _frame_name(index: int, n_frames: int) -> str:
    return f"{index:0{max(4, len(str(n_frames - 1)))}d}"


def _write_arrays(tmp: Path, model: ModelArtifact, motion: PoseSequence, cameras: CameraSequence, boxes: torch.Tensor) -> None:
    """cameras.npz, poses.npz (the motion on the model's skeleton) and boxes.npz."""
    np.savez_compressed(tmp / "cameras.npz", K=cameras.K.cpu().numpy(), w2c=cameras.w2c.cpu().numpy(),
                        height=np.int64(cameras.height), width=np.int64(cameras.width))
    np.savez_compressed(
        tmp / "poses.npz", parents=np.asarray(model.subject.parents, np.int64),
        rest_joints=np.asarray(model.subject.rest_joints, np.float32), joint_names=np.array(model.joint_names, dtype=np.str_),
        rotvecs=matrix_to_axis_angle(motion.local_rotations.double()).float().numpy(),
        transl=motion.root_translation.float().numpy(),
    )
    np.savez_compressed(tmp / "boxes.npz", posed_boxes=boxes.cpu().numpy())


def _write_glb(tmp: Path, model: ModelArtifact, motion: PoseSequence, surface: _Surface, options: AnimateOptions,
               drift: list[dict]) -> dict:
    facts = write_model_glb(tmp / "animation.glb", model, surface.vertices, surface.faces, surface.colors,
                            surface.skin_weights, options.influences,
                            motion=(motion.local_rotations, motion.root_translation, motion.fps))
    return {
        "file": "animation.glb", **facts,
        "drift_mm": {k: max(d[k]["max"] for d in drift) for k in ("4", "8")},
        "drift_mm_per_frame": {k: [d[k]["max"] for d in drift] for k in ("4", "8")},
        "drift_reference": "igavatar's posing of the same vertices: every skinning weight + non-rigid offset",
    }


def _animation_data(options: AnimateOptions, motion: PoseSequence, cameras: CameraSequence, boxes: torch.Tensor,
                    surface: _Surface | None, rendered: _Rendered, glb: dict | None, num_samples: int,
                    device: torch.device) -> dict:
    n_frames = motion.n_frames
    union = torch.stack((boxes[:, 0].amin(dim=0), boxes[:, 1].amax(dim=0))).cpu()
    return {
        "model": str(options.model),
        "motion": {"name": motion.name, "source": motion.source, "in_place": motion.in_place,
                   "seed": options.seed if motion.source == "procedural" else None},
        "frames": n_frames, "fps": motion.fps, "seconds": n_frames / motion.fps,
        "camera": {"kind": cameras.kind, "source": cameras.source,
                   "revolutions": options.revolutions if cameras.kind == "turntable" else None},
        "resolution": [cameras.height, cameras.width],
        "samples_per_ray": num_samples,
        "video": "video.mp4",
        "meshes": n_frames if options.meshes else 0,
        "mesh_vertices": int(surface.vertices.shape[0]) if surface is not None else None,
        "glb": glb,
        "posed_box_union": union.tolist(),
        "min_subject_fraction": min(rendered.coverage),
        "speed": {"frames_per_second": n_frames / max(rendered.render_s, 1e-9),
                  "seconds_per_frame": rendered.render_s / n_frames,
                  # CPU time (all threads) per frame: comparable across runs on a busy machine.
                  "cpu_seconds_per_frame": rendered.render_cpu_s / n_frames,
                  "threads": torch.get_num_threads(), "device": str(device)},
    }


def _load(options: AnimateOptions, progress: ProgressSink) -> ModelArtifact:
    """Check memory for the outputs asked for, then load the model on its device."""
    require_memory(options.resolution**2 * IMAGE_BYTES_PER_PIXEL, f"--resolution {options.resolution} (each rendered frame)")
    device = resolve_device(options.device)
    build_kernels(device, progress)
    if not (Path(options.model) / "manifest.json").is_file():
        raise ArtifactError(f"{options.model}: no model artifact there; run `igavatar train` first, or pass --model DIR")
    if options.meshes or options.glb:
        require_marching_memory(read_model_manifest(Path(options.model), check_hashes=False).canonical_box, options.mesh_resolution,
                                f"--mesh-resolution {options.mesh_resolution} (the marching-cubes grid)")
    return load_model(Path(options.model), device)


def run_animate(options: AnimateOptions, progress: ProgressSink = NULL_PROGRESS) -> dict:
    """Render the model driven by a motion and write the animation artifact.

    Raises InputError / ArtifactError (one line naming the file, key or option) for bad input;
    nothing is written then, and an interrupted run leaves any earlier animation untouched.
    """
    clock = StageClock()
    _check_options(options)
    out = Path(options.out)
    motion_path = Path(options.motion) if options.motion not in MOTION_NAMES else None
    output_inputs = [Path(options.model), motion_path, options.camera_file, options.dataset]
    check_output_target(out, "animation", output_inputs)
    with clock("load_s"):
        model = _load(options, progress)
        motion = resolve_motion(model, options, progress)
    with clock("pose_s"):
        boxes = posed_boxes(model, motion.bone_transforms.to(model.device), motion.posed_joints.to(model.device))
        cameras = _cameras(model, options, motion, boxes)
    surface = None
    if options.meshes or options.glb:
        progress.status(f"extracting the canonical surface at {options.mesh_resolution}^3 for --meshes/--glb")
        with clock("canonical_mesh_s"):
            surface = _canonical_surface(model, options)
    num_samples = options.samples or model.config.validation_samples
    with atomic_directory(out, kind="animation", inputs=output_inputs) as tmp:
        rendered = _render_frames(tmp, model, motion, boxes, cameras, surface, options, progress)
        clock.add("render_s", rendered.render_s)
        clock.add("mesh_s", rendered.mesh_s)
        _write_arrays(tmp, model, motion, cameras, boxes)
        glb = None
        if surface is not None and surface.skin_weights is not None:
            with clock("glb_s"):
                glb = _write_glb(tmp, model, motion, surface, options, rendered.drift)
        data = _animation_data(options, motion, cameras, boxes, surface, rendered, glb, num_samples, model.device)
        build_manifest(
            "animation", tmp, stage="animate",
            config={k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(options).items()},
            inputs=[InputRecord(Path(options.model), "model"), *motion.inputs]
            + ([InputRecord(Path(options.camera_file))] if options.camera_file is not None else []),
            data=data, seed=options.seed, device=str(model.device), timings=clock.finish(),
            peak_memory={"ram_bytes": peak_ram_bytes(), "cuda_bytes": peak_cuda_bytes()},
        )
    n_frames = motion.n_frames
    return {
        "animation": str(out), "motion": motion.name, "frames": n_frames, "fps": motion.fps,
        "camera": cameras.kind, "resolution": f"{cameras.width}x{cameras.height}",
        "frames_per_s": round(data["speed"]["frames_per_second"], 3), "render_seconds": round(rendered.render_s, 1),
        "video": str(out / "video.mp4"),
        "sample_frames": [str(out / "frames" / f"{_frame_name(i, n_frames)}.png") for i in sorted({0, n_frames // 2, n_frames - 1})],
        "meshes": str(out / "meshes") if options.meshes else None,
        "glb": str(out / "animation.glb") if glb is not None else None,
        "seconds": round(clock.elapsed(), 1),
    }
