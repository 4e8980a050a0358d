"""`igavatar view`: the avatar in a browser (viser), posed by the capture's frames or a motion.

    content = load_view(ViewOptions(model=Path("run/model")))       # everything the page shows
    summary = serve_view(ViewOptions(model=..., port=0), progress)   # serves until Ctrl-C

What the page shows (igavatar.viewer.scene): the canonical mesh on its skeleton with the top-4
skinning, in its vertex colors or the baked texture of `export --texture-size`, a frame slider and
a play button over the pose sequence, the capture's cameras with the current frame's image, the
skeleton, and after `eval` the scan of the current frame and the avatar's distance to it.

Where each part comes from:
    mesh     --mesh (default RUN_DIR/mesh when export wrote it): canonical.ply decimated to --faces,
             and textured/avatar.obj; else marching cubes of the model at --mesh-resolution
    poses    --motion: a procedural motion, a pose file, capture or dataset (as `animate` reads
             them); default the dataset's training and test frames with their stored transforms
    cameras  the dataset the model was trained on (--dataset)
    scans    --gt, else the scans the eval report (RUN_DIR/report) scored
Nothing is written except the screenshots the page's button saves (--screenshots).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from igavatar.artifacts.manifest import MANIFEST_NAME, read_manifest
from igavatar.avatar.dataset import DatasetArtifact, DatasetFrames, read_dataset
from igavatar.avatar.model import ModelArtifact, load_model
from igavatar.avatar.poses import DEFAULT_FPS, PoseSequence, procedural_poses, read_poses
from igavatar.avatar.surfaces import canonical_surface, vertex_colors, vertex_skin_weights
from igavatar.body.motions import MOTION_NAMES
from igavatar.errors import ArtifactError, InputError
from igavatar.mesh.cleanup import clean_mesh
from igavatar.mesh.engine_mesh import engine_mesh
from igavatar.viewer.rig import ViewerRig
from igavatar.viewer.scene import AvatarScene, CameraView, ViewerFrames
from igavatar.viewer.server import DEFAULT_HOST, DEFAULT_PORT, check_port_free, open_server, server_url, stop_server
from stages.progress import NULL_PROGRESS, ProgressSink

#: At most this many camera frustums (a moving camera has one per frame).
MAX_CAMERAS = 48
#: Longer side of the frame images shown on the cameras.
CAMERA_IMAGE_SIZE = 256


@dataclass(frozen=True)
class ViewOptions:
    """Options of `igavatar view` (see the CLI for each one's help)."""

    model: Path
    dataset: Path | None = None
    mesh: Path | None = None
    gt: Path | None = None
    report: Path | None = None
    motion: str | None = None
    seconds: float = 4.0
    mesh_resolution: int = 192
    faces: int = 60_000
    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT
    screenshots: Path | None = None


@dataclass(frozen=True, eq=False)
class ViewContent:
    """What the page shows: the rig (and textured mesh), the frames, cameras, scans and facts."""

    rig: ViewerRig
    frames: ViewerFrames
    up: np.ndarray
    forward: np.ndarray
    cameras: list[CameraView]
    dataset: DatasetArtifact | None
    frame_of_dataset: dict[int, str]
    scans: dict[str, trimesh.Trimesh]
    textured: trimesh.Trimesh | None
    textured_rig: ViewerRig | None
    facts: dict


# ------------------------------------------------------------------------------------------ mesh
def _mesh_manifest(mesh_dir: Path | None) -> dict | None:
    if mesh_dir is None or not (mesh_dir / MANIFEST_NAME).is_file():
        return None
    manifest = read_manifest(mesh_dir)
    if manifest.get("artifact") != "mesh":
        raise ArtifactError(f"--mesh {mesh_dir}: is a {manifest.get('artifact')} artifact, not a mesh artifact")
    return manifest


def _canonical_mesh(model: ModelArtifact, options: ViewOptions, mesh: dict | None,
                    progress: ProgressSink) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """Canonical vertices (V, 3), faces (F, 3), colors (V, 3) uint8 and where they came from."""
    ply = None if mesh is None else Path(options.mesh) / "canonical.ply"
    if ply is not None and ply.is_file():
        loaded = trimesh.load(ply, process=False)
        vertices, faces = np.asarray(loaded.vertices, np.float32), np.asarray(loaded.faces, np.int64)
        source = str(ply)
    else:
        progress.status(f"canonical mesh: marching cubes at {options.mesh_resolution} (no export in {options.mesh})")
        vertices, faces = canonical_surface(model.avatar, resolution=options.mesh_resolution)
        if faces.shape[0] == 0:
            raise InputError(f"model {model.path}: has no surface (its SDF never crosses zero); train it longer")
        vertices, faces, _ = clean_mesh(vertices, faces, keep_largest=True)
        source = f"marching cubes of {model.path} at {options.mesh_resolution}"
    if options.faces and faces.shape[0] > options.faces:  # a browser mesh, as canonical.glb is
        vertices, faces, _ = engine_mesh(vertices, faces, options.faces)
    return vertices, faces, vertex_colors(model.avatar, vertices), source


def _textured(model: ModelArtifact, options: ViewOptions, mesh: dict | None) -> tuple[trimesh.Trimesh | None, ViewerRig | None]:
    """The baked-texture mesh of the export, moved back from glTF's frame to canonical space."""
    record = None if mesh is None else mesh.get("data", {}).get("textured")
    obj = None if record is None else Path(options.mesh) / "textured" / "avatar.obj"
    if obj is None or not obj.is_file() or not record.get("glb"):
        return None, None  # no textured OBJ, or no record of the frame it was written in (export without glb)
    loaded = trimesh.load(obj, process=False, maintain_order=True)
    a, offset = np.asarray(record["glb"]["world_to_gltf"]), np.asarray(record["glb"]["world_to_gltf_offset"])
    loaded.vertices = (np.asarray(loaded.vertices) - offset) @ a  # x = A^T (x_gltf - offset)
    subject = model.subject
    rig = ViewerRig.build(loaded.vertices, loaded.faces, np.full((len(loaded.vertices), 3), 200, np.uint8),
                          vertex_skin_weights(model.avatar, loaded.vertices), subject.canonical_joints, subject.parents)
    return loaded, rig


# ------------------------------------------------------------------------------------------ poses
def _dataset_path(model: ModelArtifact, options: ViewOptions) -> Path | None:
    if options.dataset is not None:
        return Path(options.dataset)
    return model.trained_dataset()


def _poses(model: ModelArtifact, options: ViewOptions, dataset_path: Path | None, progress: ProgressSink) -> PoseSequence:
    motion = options.motion
    if motion is None:
        if dataset_path is None:
            motion = "walk"
            progress.status("no dataset of this model found: showing the walk motion (give --dataset or --motion)")
        else:
            return read_poses(model, dataset_path, lambda n, where: list(range(n)), option="--dataset")
    if motion in MOTION_NAMES:
        n_frames = max(1, round(options.seconds * DEFAULT_FPS))
        return procedural_poses(model, motion, n_frames, seed=0, fps=DEFAULT_FPS)
    if not Path(motion).exists():
        raise InputError(f"--motion {motion!r}: neither a procedural motion ({', '.join(MOTION_NAMES)}) "
                         "nor an existing pose file, capture directory or dataset")
    return read_poses(model, Path(motion), lambda n, where: list(range(n)), on_status=progress.status, option="--motion")


def _cameras(dataset: DatasetArtifact, frames: DatasetFrames) -> list[CameraView]:
    """The dataset's distinct cameras (a still camera is one), at most MAX_CAMERAS evenly spread."""
    groups: dict[bytes, list[int]] = {}
    for i in range(frames.n_frames):
        key = np.round(np.concatenate([frames.w2c[i].ravel(), frames.K[i].ravel()]), 4).tobytes()
        groups.setdefault(key, []).append(i)
    members = list(groups.values())
    if len(members) > MAX_CAMERAS:
        members = [members[int(k)] for k in np.linspace(0, len(members) - 1, MAX_CAMERAS)]
    return [CameraView(frames.K[m[0]], frames.w2c[m[0]], dataset.image_size, tuple(m)) for m in members]


def _scans(options: ViewOptions, names: list[str]) -> dict[str, trimesh.Trimesh]:
    """World scans of the frames shown: --gt DIR/<frame>.ply, else those the eval report read."""
    paths: dict[str, Path] = {}
    if options.gt is not None:
        if not Path(options.gt).is_dir():
            raise InputError(f"--gt {options.gt}: no such directory")
        paths = {p.stem: p for p in sorted(Path(options.gt).glob("*.ply"))}
    elif options.report is not None and (Path(options.report) / MANIFEST_NAME).is_file():
        inputs = read_manifest(Path(options.report)).get("inputs", [])
        run = Path(options.report).resolve().parent
        paths = {Path(i["path"]).stem: _recorded(Path(i["path"]), run) for i in inputs if str(i.get("path", "")).endswith(".ply")}
    return {name: trimesh.load(paths[name], process=False) for name in names if paths.get(name) is not None}


def _recorded(path: Path, run: Path) -> Path | None:
    """A path an eval recorded (relative to where it ran), found from here: as it is, else its tail
    under the run directory (igavatar-run/capture/scans/x.ply -> RUN/capture/scans/x.ply)."""
    if path.is_file():
        return path
    parts = path.parts
    for k in range(len(parts)):
        candidate = run.joinpath(*parts[k:])
        if candidate.is_file():
            return candidate
    return None


def load_view(options: ViewOptions, progress: ProgressSink = NULL_PROGRESS) -> ViewContent:
    """Read the model, its mesh, poses, cameras and scans: everything the page needs."""
    with torch.no_grad():
        model = load_model(Path(options.model))
        mesh = _mesh_manifest(None if options.mesh is None else Path(options.mesh))
        vertices, faces, colors, mesh_source = _canonical_mesh(model, options, mesh, progress)
        subject = model.subject
        rig = ViewerRig.build(vertices, faces, colors, vertex_skin_weights(model.avatar, vertices),
                              subject.canonical_joints, subject.parents)
        textured, textured_rig = _textured(model, options, mesh)
    dataset_path = _dataset_path(model, options)
    dataset = read_dataset(dataset_path) if dataset_path is not None and dataset_path.is_dir() else None
    poses = _poses(model, options, dataset_path if dataset is not None else None, progress)
    split_of = {name: split for split, names in (dataset.splits if dataset else {}).items() for name in names}
    names = list(poses.frame_names)
    frames = ViewerFrames(names, poses.bone_transforms.double().cpu().numpy(), float(poses.fps),
                          [split_of.get(n, "") for n in names])
    dataset_frames = dataset.frames() if dataset is not None else None
    dataset_names = set(dataset_frames.names) if dataset_frames is not None else set()
    frame_of_dataset = {i: n for i, n in enumerate(names) if n in dataset_names}
    scans = _scans(options, names)
    facts = {"model": str(model.path), "mesh": mesh_source, "textured": textured is not None,
             "vertices": int(vertices.shape[0]), "faces": int(faces.shape[0]), "frames": frames.n_frames,
             "poses": poses.source, "scans": len(scans)}
    axes = np.asarray(model.body_axes)  # columns: left, up, forward
    return ViewContent(rig, frames, axes[:, 1], axes[:, 2], _cameras(dataset, dataset_frames) if dataset else [],
                       dataset, frame_of_dataset, scans, textured, textured_rig, facts)


# ------------------------------------------------------------------------------------------ serving
def frame_image_reader(content: ViewContent):
    """frame index -> (H, W, 3) uint8 image on white at CAMERA_IMAGE_SIZE, or None (cached)."""
    cache: dict[int, np.ndarray] = {}

    def image(index: int) -> np.ndarray | None:
        name = content.frame_of_dataset.get(index)
        if name is None or content.dataset is None:
            return None
        if index not in cache:
            h, w = content.dataset.image_size
            scale = min(1.0, CAMERA_IMAGE_SIZE / max(h, w))  # never larger than the photograph
            rgb, _ = content.dataset.image_on_white(name, (max(1, round(h * scale)), max(1, round(w * scale))))
            cache[index] = (rgb * 255).round().astype(np.uint8)
        return cache[index]

    return image


def build_scene(server, content: ViewContent, screenshots: Path | None) -> AvatarScene:
    return AvatarScene(server, content.rig, content.frames, up=content.up, forward=content.forward, cameras=content.cameras,
                       frame_image=frame_image_reader(content), scans=content.scans, textured=content.textured,
                       textured_rig=content.textured_rig, screenshot_dir=screenshots)


def serve_view(options: ViewOptions, progress: ProgressSink = NULL_PROGRESS,
               stop: threading.Event | None = None, on_ready=None) -> dict:
    """Serve the page until Ctrl-C (or `stop` is set); returns what was shown.

    on_ready(server, scene), when given, is called once the page is up (tests, the browser check).
    """
    check_port_free(options.host, options.port)  # a busy port fails now, not after the mesh is loaded
    content = load_view(options, progress)
    server = open_server(options.host, options.port)
    url = server_url(server)
    try:
        scene = build_scene(server, content, options.screenshots)
        if on_ready is not None:
            on_ready(server, scene)
        stop = stop or threading.Event()
        try:
            while not stop.wait(1.0 / max(float(scene.fps.value), 1.0)):
                scene.step_playback()
        except KeyboardInterrupt:  # the way to stop a server: not an error
            progress.status("viewer stopped")
    finally:
        stop_server(server)
    return {"url": url, **content.facts, "screenshots": [str(p) for p in scene.screenshots]}
