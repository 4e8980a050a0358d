"""`igavatar animate`: a model artifact + a motion -> an animation artifact (frames, video, meshes).

    summary = run_animate(AnimateOptions(model=Path("run/model"), out=Path("run/animation"), motion="walk"))

The motion is a procedural one (walk, turn, arm_raise, squat, turntable: no files needed), a pose
file (any format of `igavatar.mesh.pose_files`), a capture v1 directory or a dataset artifact
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
    meshes/<NNNN>.ply    with --meshes: the posed surface per frame (world coordinates, vertex colours)
    animation.glb        with --glb: the rigged avatar (canonical surface at --mesh-resolution, vertex
                         colours, top-4 or --influences 8 skin weights, glTF's +Y-up frame) holding the
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

import cv2
import imageio
import numpy as np
import torch
import trimesh

from igavatar.artifacts.atomic import atomic_directory
from igavatar.artifacts.targets import check_output_target
from igavatar.artifacts.manifest import MANIFEST_NAME, InputRecord, build_manifest, read_artifact, read_manifest
from igavatar.body.motions import MOTION_NAMES, SKELETON_KINDS, body_to_world, motion_by_name, walk
from igavatar.body.rotations import matrix_to_axis_angle
from igavatar.body.skeleton import Skeleton
from igavatar.errors import ArtifactError, InputError
from igavatar.mesh.cleanup import clean_mesh
from igavatar.mesh.gltf import INFLUENCE_CHOICES, INFLUENCES
from igavatar.mesh.pose_files import local_pose_from_bone_transforms, read_pose_sequence, sequence_local_pose
from igavatar.mesh.posing import canonical_mesh, pose_canonical_vertices, vertex_colors, vertex_skin_weights
from igavatar.mesh.skin_drift import skin_drift_mm, sparse_weight_sets
from igavatar.model.render_avatar import render_avatar_view
from igavatar.render.cameras import resize_intrinsics, turntable_cameras
from stages.glb_writer import write_model_glb
from stages.kernels import build_kernels
from stages.model_io import LoadedModel, load_model
from stages.progress import NULL_PROGRESS, ProgressSink
from stages.resources import IMAGE_BYTES_PER_PIXEL, peak_cuda_bytes, peak_ram_bytes, require_marching_memory, require_memory
from stages.train import resolve_device

CAMERAS = ("turntable", "front", "capture")
#: Frames per second of procedural motions, and of pose files that do not say.
DEFAULT_FPS = 30.0
#: Extra padding (metres) of a posed box beyond the skinned canonical cells and the offset bound.
BOX_PADDING_M = 0.03
#: Padding (metres) around the posed joints when the canonical grid has no occupied cell.
JOINT_BOX_PADDING_M = 0.3
#: Skinned cells per frame that the turntable's K keeps in view, and the free image border left.
FRAMING_POINTS = 4096
FRAMING_MARGIN = 0.06


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
    glb: bool = False
    influences: int = INFLUENCES
    device: str = "auto"
    anny_cache: Path | None = None


@dataclass(frozen=True)
class DrivingMotion:
    """A motion on the avatar's skeleton.

    Attributes:
        name: motion name (procedural) or file name; source: "procedural" or the path read.
        local_rotations: (N, J, 3, 3) relative to the rest pose; root_translation: (N, 3) metres.
        fps: frames per second; in_place: whether the motion stays over one spot.
        inputs: files and artifacts read (for the manifest).
    """

    name: str
    source: str
    local_rotations: torch.Tensor
    root_translation: torch.Tensor
    fps: float
    in_place: bool
    inputs: tuple[InputRecord, ...] = ()


@dataclass(frozen=True)
class CameraSequence:
    """Cameras of every frame: K (N, 3, 3), w2c (N, 4, 4), image height and width, description."""

    kind: str
    K: torch.Tensor
    w2c: torch.Tensor
    height: int
    width: int
    source: str | None


# ---------------------------------------------------------------------------------------- motion
def _model_skeleton(model: LoadedModel) -> Skeleton:
    return Skeleton(model.subject["parents"], model.subject["rest_joints"], tuple(model.joint_names))


def _frame_count(options: AnimateOptions, fps: float) -> int:
    if options.frames is not None:
        if options.frames < 1:
            raise InputError(f"--frames {options.frames}: expected a positive number of frames")
        return int(options.frames)
    if not (math.isfinite(options.seconds) and options.seconds > 0):
        raise InputError(f"--seconds {options.seconds}: expected a positive duration")
    return max(1, round(options.seconds * fps))


def procedural_motion(model: LoadedModel, options: AnimateOptions) -> DrivingMotion:
    """A shipped motion (MOTION_NAMES) for the model's skeleton; walk stays in place unless --travel."""
    kind = model.manifest["data"]["body_model"]
    if kind not in SKELETON_KINDS:
        raise InputError(
            f"procedural motions drive {' and '.join(SKELETON_KINDS)} skeletons; the model {model.path} "
            f"has body model '{kind}': give a pose file as MOTION instead"
        )
    fps = float(options.fps or DEFAULT_FPS)
    skeleton = _model_skeleton(model)
    n_frames = _frame_count(options, fps)
    if options.motion == "walk":
        motion = walk(kind, n_frames, options.seed, fps=fps, in_place=not options.travel, skeleton=skeleton)
    else:
        motion = motion_by_name(options.motion, kind, n_frames, options.seed, fps=fps, skeleton=skeleton)
    return DrivingMotion(
        name=options.motion, source="procedural", local_rotations=motion.local_rotations_for(skeleton),
        root_translation=motion.root_translation_tensor(), fps=fps,
        in_place=options.motion != "walk" or not options.travel,
    )


def _first_frames(options: AnimateOptions, n_frames: int) -> list[int]:
    if options.frames is not None and options.frames < 1:
        raise InputError(f"--frames {options.frames}: expected a positive number of frames")
    return list(range(n_frames if options.frames is None else min(options.frames, n_frames)))


def _dataset_motion(model: LoadedModel, dataset: Path, options: AnimateOptions) -> DrivingMotion:
    """The frames of a dataset artifact: its bone transforms turned back into local rotations."""
    read_artifact(dataset, expected="dataset")
    with np.load(dataset / "frames.npz") as frames, np.load(dataset / "subject.npz") as subject:
        same_names = [str(n) for n in subject["joint_names"]] == model.joint_names
        if not (same_names and np.array_equal(subject["parents"], model.subject["parents"])):
            raise InputError(
                f"{dataset}: its skeleton ({len(subject['joint_names'])} joints) is not the model's "
                f"({len(model.joint_names)} joints); retargeting is not available"
            )
        chosen = _first_frames(options, frames["bone_transforms"].shape[0])
        rotations, translation = local_pose_from_bone_transforms(
            torch.from_numpy(frames["bone_transforms"][chosen]).double(), subject["parents"],
            torch.from_numpy(subject["rest_joints"]).double(), torch.from_numpy(subject["canonical_rotations"]).double(),
        )
    return DrivingMotion(
        name=dataset.name, source=str(dataset), local_rotations=rotations.float(), root_translation=translation.float(),
        fps=float(options.fps or DEFAULT_FPS), in_place=False, inputs=(InputRecord(dataset, "dataset"),),
    )


def motion_from_path(model: LoadedModel, path: Path, options: AnimateOptions, progress: ProgressSink) -> DrivingMotion:
    """A pose file (any format of igavatar.mesh.pose_files), a capture v1 directory or a dataset artifact."""
    inputs: tuple[InputRecord, ...]
    if path.is_dir() and (path / MANIFEST_NAME).is_file():
        kind = read_manifest(path)["artifact"]
        if kind == "dataset":
            return _dataset_motion(model, path, options)
        if kind != "capture":
            raise ArtifactError(
                f"MOTION {path}: is a {kind} artifact; give a pose .npz, a capture directory or a dataset artifact"
            )
        read_artifact(path, expected="capture")  # an intact capture, before reading its poses
        inputs = (InputRecord(path, "capture"),)
    sequence = read_pose_sequence(path)
    if not (path.is_dir() and (path / MANIFEST_NAME).is_file()):
        inputs = (InputRecord(sequence.source),)
    selected = sequence.select(_first_frames(options, sequence.n_frames))
    data = model.manifest["data"]
    rotations, translation = sequence_local_pose(
        selected, _model_skeleton(model), data["body_model"], phenotype=data.get("subject", {}).get("phenotype"),
        anny_cache=options.anny_cache, on_status=progress.status,
    )
    return DrivingMotion(
        name=path.stem, source=str(path), local_rotations=rotations, root_translation=translation,
        fps=float(options.fps or sequence.fps or DEFAULT_FPS), in_place=False, inputs=inputs,
    )


def resolve_motion(
    model: LoadedModel, options: AnimateOptions, progress: ProgressSink = NULL_PROGRESS
) -> DrivingMotion:
    """MOTION as a procedural name, else as a path; InputError naming both choices otherwise."""
    if options.fps is not None and not (math.isfinite(options.fps) and options.fps > 0):
        raise InputError(f"--fps {options.fps}: expected a positive number")
    if options.motion in MOTION_NAMES:
        motion = procedural_motion(model, options)
    else:
        path = Path(options.motion)
        if not path.exists():
            raise InputError(
                f"motion {options.motion!r}: neither a procedural motion ({', '.join(MOTION_NAMES)}) "
                "nor an existing pose file, capture directory or dataset"
            )
        motion = motion_from_path(model, path, options, progress)
    n, j = motion.local_rotations.shape[:2]
    if n == 0:
        raise InputError(f"motion {options.motion!r} has no frames")
    if j != len(model.joint_names):
        raise InputError(f"motion {options.motion!r} has {j} joints but the model {model.path} has {len(model.joint_names)}")
    if not (torch.isfinite(motion.local_rotations).all() and torch.isfinite(motion.root_translation).all()):
        raise InputError(f"motion {options.motion!r} contains NaN or infinite values")
    return motion


# ----------------------------------------------------------------------------------- posed boxes
def _canonical_cell_centres(model: LoadedModel) -> torch.Tensor:
    """(C, 3) canonical centres of the occupied cells of the model's canonical occupancy grid."""
    grid = model.canonical_grid
    iz, iy, ix = torch.nonzero(grid.occupied, as_tuple=True)
    return grid.box_min + (torch.stack((ix, iy, iz), dim=-1).to(grid.box_min.dtype) + 0.5) * grid.cell_size()


@torch.no_grad()
def skinned_cells(model: LoadedModel, bone_transforms: torch.Tensor, max_points: int | None = None) -> torch.Tensor:
    """Occupied canonical cell centres pushed through forward LBS: (N, C, 3) posed world points.

    Args:
        bone_transforms: (N, J, 4, 4) canonical -> posed world.
        max_points: keep every k-th cell so that C <= max_points (for framing); None keeps all.
    """
    x_canonical = _canonical_cell_centres(model)
    if max_points is not None and x_canonical.shape[0] > max_points:
        x_canonical = x_canonical[:: -(-x_canonical.shape[0] // max_points)]
    deformer = model.avatar.deformer
    return torch.stack([
        deformer.forward_skinning(x_canonical, deformer.prepare(transforms.to(x_canonical.device)))
        for transforms in bone_transforms
    ])


@torch.no_grad()
def posed_boxes(model: LoadedModel, bone_transforms: torch.Tensor, posed_joints: torch.Tensor) -> torch.Tensor:
    """World boxes (N, 2, 3) that bound the posed avatar in each frame (rendering bounds).

    The centres of the canonical occupied cells are forward-skinned; the box of the results is
    padded by half a cell diagonal (a cell's content around its centre), the non-rigid offset
    bound when the offset is on (the surface moves at most that far from its rigid
    correspondence) and BOX_PADDING_M. Because LBS of a bounded canonical set stays bounded, any
    pose, however far from the training poses, gets a box the size of the body. Without occupied
    cells the posed joints padded by JOINT_BOX_PADDING_M are used.

    Args:
        bone_transforms: (N, J, 4, 4) canonical -> posed world; posed_joints: (N, J, 3).
    """
    if not bool(model.canonical_grid.occupied.any()):
        low, high = posed_joints.amin(dim=1), posed_joints.amax(dim=1)
        return torch.stack((low - JOINT_BOX_PADDING_M, high + JOINT_BOX_PADDING_M), dim=1)
    nonrigid = model.avatar.nonrigid
    # Each offset component is bounded by max_offset, so its length (after any rotation) by sqrt(3) x.
    offset_bound = math.sqrt(3.0) * nonrigid.config.max_offset if nonrigid.enabled else 0.0
    cell = model.canonical_grid.cell_size()
    pad = 0.5 * float(torch.linalg.vector_norm(cell)) + offset_bound + BOX_PADDING_M
    boxes = [
        torch.stack((x_posed.amin(dim=0) - pad, x_posed.amax(dim=0) + pad))
        for x_posed in (skinned_cells(model, transforms[None])[0] for transforms in bone_transforms)
    ]
    return torch.stack(boxes).to(torch.float32)


# --------------------------------------------------------------------------------------- cameras
def render_size(height: int, width: int, resolution: int) -> tuple[int, int]:
    """(H, W) with the camera's aspect ratio and the longer side equal to `resolution`."""
    scale = resolution / max(height, width)
    return max(1, round(height * scale)), max(1, round(width * scale))


def _dataset_path(model: LoadedModel, override: Path | None) -> Path:
    if override is not None:
        return Path(override)
    recorded = Path(model.manifest["data"]["dataset"])
    # A relative path was relative to where `train` ran; the run layout keeps it beside the model.
    for candidate in (recorded, model.path.parent / recorded.name):
        if (candidate / "frames.npz").is_file():
            return candidate
    return recorded


def capture_camera(model: LoadedModel, options: AnimateOptions, n_frames: int) -> CameraSequence:
    """The first training-data frame's camera (dataset frames.npz), rescaled to --resolution."""
    dataset = _dataset_path(model, options.dataset)
    if not (dataset / "frames.npz").is_file():
        raise InputError(
            f"--camera capture needs the dataset the model was trained on ({dataset}/frames.npz holds "
            "the capture cameras) and it is not there; pass --dataset DIR, or use --camera turntable or --camera-file"
        )
    manifest = read_artifact(dataset, expected="dataset", check_hashes=False)
    with np.load(dataset / "frames.npz") as frames:
        if "K" not in frames.files or "w2c" not in frames.files:
            raise ArtifactError(f"{dataset / 'frames.npz'}: keys K and w2c are missing; re-run `igavatar preprocess`")
        K, w2c = torch.from_numpy(frames["K"][0]).float(), torch.from_numpy(frames["w2c"][0]).float()
    height, width = (int(v) for v in manifest["data"]["image_size"])
    h, w = render_size(height, width, options.resolution)
    K = resize_intrinsics(K, (height, width), (h, w))
    return CameraSequence(
        "capture", K.expand(n_frames, 3, 3).clone(), w2c.expand(n_frames, 4, 4).clone(), h, w, str(dataset)
    )


def _array(arrays: dict, key: str, path: Path) -> np.ndarray:
    if key not in arrays:
        raise InputError(f"{path}: key {key!r} is missing; a camera file holds K, w2c, height and width")
    return np.asarray(arrays[key])


def camera_from_file(path: Path, options: AnimateOptions, n_frames: int) -> CameraSequence:
    """K (3,3)|(N,3,3), w2c (4,4)|(N,4,4), height, width from an npz, rescaled to --resolution."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {key: npz[key] for key in npz.files}
    except (OSError, ValueError) as error:
        raise InputError(f"--camera-file {path}: not a readable npz file ({error})") from None
    K = _array(arrays, "K", path).astype(np.float64)
    w2c = _array(arrays, "w2c", path).astype(np.float64)
    try:
        height, width = int(_array(arrays, "height", path)), int(_array(arrays, "width", path))
    except (TypeError, ValueError):
        raise InputError(f"{path}: keys 'height' and 'width' must be single integers") from None
    if height < 1 or width < 1:
        raise InputError(f"{path}: height {height} and width {width} must be positive")
    for key, value, shape in (("K", K, (3, 3)), ("w2c", w2c, (4, 4))):
        if value.shape not in (shape, (n_frames, *shape)):
            raise InputError(
                f"{path}: key {key!r} has shape {value.shape}, expected {shape} or "
                f"({n_frames}, {shape[0]}, {shape[1]}) for {n_frames} frames"
            )
        if not np.all(np.isfinite(value)):
            raise InputError(f"{path}: key {key!r} contains NaN or infinite values")
    rotation = w2c[..., :3, :3]
    orthonormal_error = np.abs(rotation @ np.swapaxes(rotation, -1, -2) - np.eye(3)).max()
    if orthonormal_error > 1e-3 or np.abs(w2c[..., 3, :] - [0, 0, 0, 1]).max() > 1e-6:
        raise InputError(
            f"{path}: key 'w2c' is not a rigid world-to-camera transform (rotation, translation, last row 0 0 0 1)"
        )
    if np.abs(K[..., 2, :] - [0, 0, 1]).max() > 1e-6 or np.any(K[..., 0, 0] <= 0) or np.any(K[..., 1, 1] <= 0):
        raise InputError(f"{path}: key 'K' is not a pinhole intrinsic matrix (positive focal lengths, last row 0 0 1)")
    h, w = render_size(height, width, options.resolution)
    K_t = resize_intrinsics(torch.from_numpy(K).float(), (height, width), (h, w))
    return CameraSequence(
        "file", K_t.expand(n_frames, 3, 3).clone(), torch.from_numpy(w2c).float().expand(n_frames, 4, 4).clone(),
        h, w, str(path),
    )


def orbit_cameras(
    model: LoadedModel, options: AnimateOptions, boxes: torch.Tensor, bone_transforms: torch.Tensor
) -> CameraSequence:
    """Turntable (or static front) cameras around the union of the posed boxes.

    Up and front are the body's (the kind's body frame; bare skeletons count as SMPL-like, +Y up,
    facing +Z) turned by the first frame's root rotation, so azimuth 0 faces the subject's front
    whatever the capture's world axes are. K frames each frame's skinned occupied cells (the body
    itself, not its padded box), so the subject fills the image.
    """
    kind = model.manifest["data"]["body_model"]
    axes = torch.from_numpy(body_to_world(kind if kind in SKELETON_KINDS else "smpl")).float()
    root_rotation = bone_transforms[0, 0, :3, :3].float().cpu()
    up, front = root_rotation @ axes[:, 1], root_rotation @ axes[:, 2]
    revolutions = options.revolutions if options.camera == "turntable" else 0.0
    n = boxes.shape[0]
    fit_points = None
    if bool(model.canonical_grid.occupied.any()):
        fit_points = skinned_cells(model, bone_transforms, FRAMING_POINTS).cpu()
    K, w2c = turntable_cameras(
        boxes[:, 0].amin(dim=0), boxes[:, 1].amax(dim=0), n, options.resolution, options.resolution,
        up=up, front=front, revolutions=revolutions, margin=FRAMING_MARGIN, fit_points=fit_points,
    )
    return CameraSequence(options.camera, K.expand(n, 3, 3).clone(), w2c, options.resolution, options.resolution, None)


# ---------------------------------------------------------------------------------------- output
def _png_bytes(rgb: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return data.tobytes()


def _even_frame(rgb: np.ndarray) -> np.ndarray:
    """H.264 (yuv420p) needs even sizes: repeat the last row/column when one is odd."""
    h, w = rgb.shape[:2]
    return np.pad(rgb, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


def _ply_bytes(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray) -> bytes:
    mesh = trimesh.Trimesh(vertices, faces, vertex_colors=colors, process=False)
    return mesh.export(file_type="ply")


def _canonical_surface(model: LoadedModel, resolution: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Canonical mesh (largest component) and its vertex colours, for --meshes and --glb."""
    vertices, faces = canonical_mesh(model.avatar, resolution=resolution)
    if faces.shape[0] == 0:
        raise InputError(f"--meshes/--glb: the model {model.path} has no surface (its SDF never crosses zero); train it longer")
    vertices, faces, _ = clean_mesh(vertices, faces, keep_largest=True)
    return vertices, faces, vertex_colors(model.avatar, vertices)


def run_animate(options: AnimateOptions, progress: ProgressSink = NULL_PROGRESS) -> dict:
    """Render the model driven by a motion and write the animation artifact.

    Raises InputError / ArtifactError (one line naming the file, key or option) for bad input;
    nothing is written then, and an interrupted run leaves any earlier animation untouched.
    """
    started = time.perf_counter()
    if options.camera not in CAMERAS:
        raise InputError(f"--camera {options.camera!r}: expected one of {', '.join(CAMERAS)}")
    if options.resolution < 8:
        raise InputError(f"--resolution {options.resolution}: expected at least 8 pixels")
    if options.samples is not None and options.samples < 1:
        raise InputError(f"--samples {options.samples}: expected at least 1")
    if (options.meshes or options.glb) and options.mesh_resolution < 16:
        raise InputError(f"--mesh-resolution {options.mesh_resolution}: expected at least 16")
    out = Path(options.out)
    motion_path = Path(options.motion) if options.motion not in MOTION_NAMES else None
    output_inputs = [Path(options.model), motion_path, options.camera_file, options.dataset]
    check_output_target(out, "animation", output_inputs)
    require_memory(options.resolution**2 * IMAGE_BYTES_PER_PIXEL, f"--resolution {options.resolution} (each rendered frame)")
    if options.influences not in INFLUENCE_CHOICES:
        raise InputError(f"--influences {options.influences}: expected 4 (web engines) or 8 (JOINTS_1/WEIGHTS_1 too)")
    device = resolve_device(options.device)
    build_kernels(device, progress)
    if not (Path(options.model) / "manifest.json").is_file():
        raise ArtifactError(f"{options.model}: no model artifact there; run `igavatar train` first, or pass --model DIR")
    if options.meshes or options.glb:
        require_marching_memory(read_manifest(Path(options.model))["data"]["canonical_box"], options.mesh_resolution,
                                f"--mesh-resolution {options.mesh_resolution} (the marching-cubes grid)")
    model = load_model(Path(options.model), device)
    motion = resolve_motion(model, options, progress)
    n_frames = motion.local_rotations.shape[0]
    timings: dict[str, float] = {"load_s": time.perf_counter() - started}

    tick = time.perf_counter()
    posed = model.pose(motion.local_rotations, motion.root_translation)
    bone_transforms = posed.bone_transforms.to(device)
    pose_condition = posed.pose_condition.to(device)
    boxes = posed_boxes(model, bone_transforms, posed.posed_joints.to(device))
    if options.camera_file is not None:
        cameras = camera_from_file(options.camera_file, options, n_frames)
    elif options.camera == "capture":
        cameras = capture_camera(model, options, n_frames)
    else:
        cameras = orbit_cameras(model, options, boxes.cpu(), posed.bone_transforms)
    timings["pose_s"] = time.perf_counter() - tick
    num_samples = options.samples or model.config.validation_samples

    surface = skin_weights = None
    if options.meshes or options.glb:
        tick = time.perf_counter()
        progress.status(f"extracting the canonical surface at {options.mesh_resolution}^3 for --meshes/--glb")
        surface = _canonical_surface(model, options.mesh_resolution)
        if options.glb:
            skin_weights = vertex_skin_weights(model.avatar, surface[0])
            sparse_sets = sparse_weight_sets(skin_weights)
        timings["canonical_mesh_s"] = time.perf_counter() - tick
    drift: list[dict] = []

    width_digits = max(4, len(str(n_frames - 1)))
    coverage: list[float] = []
    render_seconds = mesh_seconds = render_cpu_seconds = 0.0
    with atomic_directory(out, kind="animation", inputs=output_inputs) as tmp:
        (tmp / "frames").mkdir()
        if options.meshes:
            (tmp / "meshes").mkdir()
        writer = imageio.get_writer(
            tmp / "video.mp4", fps=motion.fps, codec="libx264", quality=8, macro_block_size=1,
            ffmpeg_log_level="error",
        )
        try:
            with progress.task(f"rendering {motion.name}", total=n_frames) as advance:
                for i in range(n_frames):
                    tick, cpu_tick = time.perf_counter(), time.process_time()
                    image = render_avatar_view(
                        model.avatar, model.canonical_grid, bone_transforms[i], pose_condition[i],
                        cameras.K[i].to(device), cameras.w2c[i].to(device), cameras.height, cameras.width,
                        boxes[i].to(device), num_samples=num_samples,
                        occupancy_resolution=model.config.occupancy_resolution,
                    )
                    rgb = (image.rgb.clamp(0, 1).cpu().numpy() * 255).round().astype(np.uint8)
                    render_seconds += time.perf_counter() - tick
                    render_cpu_seconds += time.process_time() - cpu_tick
                    coverage.append(float((image.opacity > 0.5).float().mean()))
                    name = f"{i:0{width_digits}d}"
                    (tmp / "frames" / f"{name}.png").write_bytes(_png_bytes(rgb))
                    writer.append_data(_even_frame(rgb))
                    if surface is not None:
                        tick = time.perf_counter()
                        frame = model.avatar.deformer.prepare(bone_transforms[i])
                        x_posed = pose_canonical_vertices(model.avatar, surface[0], frame, pose_condition[i])
                        if options.meshes:
                            (tmp / "meshes" / f"{name}.ply").write_bytes(_ply_bytes(x_posed, surface[1], surface[2]))
                        if skin_weights is not None:
                            drift.append(skin_drift_mm(surface[0], sparse_sets, bone_transforms[i], x_posed))
                        mesh_seconds += time.perf_counter() - tick
                    rate = (i + 1) / max(render_seconds, 1e-9)
                    advance(1, **{"frames/s": f"{rate:.3f}"})
        finally:
            writer.close()

        np.savez_compressed(
            tmp / "cameras.npz", K=cameras.K.cpu().numpy(), w2c=cameras.w2c.cpu().numpy(),
            height=np.int64(cameras.height), width=np.int64(cameras.width),
        )
        np.savez_compressed(
            tmp / "poses.npz", parents=np.asarray(model.subject["parents"], np.int64),
            rest_joints=np.asarray(model.subject["rest_joints"], np.float32),
            joint_names=np.array(model.joint_names, dtype=np.str_),
            rotvecs=matrix_to_axis_angle(motion.local_rotations.double()).float().numpy(),
            transl=motion.root_translation.float().numpy(),
        )
        np.savez_compressed(tmp / "boxes.npz", posed_boxes=boxes.cpu().numpy())
        glb_info = None
        if skin_weights is not None:
            tick = time.perf_counter()
            facts = write_model_glb(
                tmp / "animation.glb", model, surface[0], surface[1], surface[2], skin_weights, options.influences,
                motion=(motion.local_rotations, motion.root_translation, motion.fps),
            )
            glb_info = {
                "file": "animation.glb", **facts,
                "drift_mm": {k: max(d[k]["max"] for d in drift) for k in ("4", "8")},
                "drift_mm_per_frame": {k: [d[k]["max"] for d in drift] for k in ("4", "8")},
                "drift_reference": "igavatar's posing of the same vertices: every skinning weight + non-rigid offset",
            }
            timings["glb_s"] = time.perf_counter() - tick
        fps_rendered = n_frames / max(render_seconds, 1e-9)
        union = torch.stack((boxes[:, 0].amin(dim=0), boxes[:, 1].amax(dim=0))).cpu()
        data = {
            "model": str(options.model),
            "motion": {"name": motion.name, "source": motion.source, "in_place": motion.in_place,
                       "seed": options.seed if motion.source == "procedural" else None},
            "frames": n_frames,
            "fps": motion.fps,
            "seconds": n_frames / motion.fps,
            "camera": {"kind": cameras.kind, "source": cameras.source,
                       "revolutions": options.revolutions if cameras.kind == "turntable" else None},
            "resolution": [cameras.height, cameras.width],
            "samples_per_ray": num_samples,
            "video": "video.mp4",
            "meshes": n_frames if options.meshes else 0,
            "mesh_vertices": int(surface[0].shape[0]) if surface is not None else None,
            "glb": glb_info,
            "posed_box_union": union.tolist(),
            "min_subject_fraction": min(coverage),
            "speed": {"frames_per_second": fps_rendered, "seconds_per_frame": render_seconds / n_frames,
                      # CPU time (all threads) per frame: comparable across runs on a busy machine.
                      "cpu_seconds_per_frame": render_cpu_seconds / n_frames,
                      "threads": torch.get_num_threads(), "device": str(device)},
        }
        timings.update(render_s=render_seconds, mesh_s=mesh_seconds, total_s=time.perf_counter() - started)
        build_manifest(
            "animation", tmp, stage="animate",
            config={k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(options).items()},
            inputs=[InputRecord(Path(options.model), "model"), *motion.inputs]
            + ([InputRecord(Path(options.camera_file))] if options.camera_file is not None else []),
            data=data, seed=options.seed, device=str(device), timings=timings,
            peak_memory={"ram_bytes": peak_ram_bytes(), "cuda_bytes": peak_cuda_bytes()},
        )
    picks = sorted({0, n_frames // 2, n_frames - 1})
    return {
        "animation": str(out), "motion": motion.name, "frames": n_frames, "fps": motion.fps,
        "camera": cameras.kind, "resolution": f"{cameras.width}x{cameras.height}",
        "frames_per_s": round(fps_rendered, 3), "render_seconds": round(render_seconds, 1),
        "video": str(out / "video.mp4"),
        "sample_frames": [str(out / "frames" / f"{i:0{width_digits}d}.png") for i in picks],
        "meshes": str(out / "meshes") if options.meshes else None,
        "glb": str(out / "animation.glb") if glb_info is not None else None,
        "seconds": round(time.perf_counter() - started, 1),
    }
