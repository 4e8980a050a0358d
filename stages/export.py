"""`igavatar export`: a model artifact -> a mesh artifact (canonical mesh, rigged GLB, posed meshes, maps).

    summary = run_export(ExportOptions(model=Path("run/model"), out=Path("run/mesh")))
    summary = run_export(ExportOptions(model=..., out=..., pose=Path("run/capture"), all_frames=True, exr=True))

Mesh layout (schema `mesh`, version 1; every position in metres):
    canonical.ply, canonical.obj   the canonical-space surface with sRGB vertex colours
    canonical.glb                  rigged: the same mesh, the skeleton (joints named, bind pose = the
                                   canonical pose), the 4 (--influences 8: 8, as JOINTS_0/1) largest
                                   skinning weights per vertex and the vertex colours, in glTF's
                                   +Y-up, +Z-forward frame (the capture's axes rotated in, see
                                   igavatar.mesh.gltf); with --pose it also holds the exported frames
                                   as an animation (linear blend skinning only: no non-rigid offset)
    textured/avatar.glb|.obj|.mtl|.png   --texture-size S: the canonical mesh decimated to
                                   --textured-faces (pymeshlab quadric), UV-unwrapped (xatlas), the
                                   colour field baked per texel into an S x S PNG (seams dilated);
                                   the GLB is rigged (and animated) like canonical.glb; both Y-up
    posed/<frame>.ply|.obj         the avatar in each exported pose, in WORLD coordinates (root
                                   transform applied): forward LBS of the canonical mesh plus the
                                   pose-conditioned non-rigid offset; same faces as canonical
    posed/<frame>.marched.ply      --posed-marching: marching cubes in posed space through the deformer
    maps/<view>.exr                --exr: Z (camera depth in m, 0 where empty), N (unit world-space
                                   normals), A (coverage 0/1), RGB (linear colour) of the exported mesh
    maps/cameras.npz               names (M,), K (M,3,3), w2c (M,4,4), height, width of those views

The canonical surface is marching cubes of the SDF intersected with the canonical box (the hash
grid is only defined there), so it is closed even when an undertrained surface reaches the box;
how many vertices lie on the box is recorded. Extraction is coarse-to-fine and narrow-band
(igavatar.mesh.extract), at the paper's 512 by default on CPU and GPU alike (20-45 s on two CPU
cores), then pymeshlab cleanup (igavatar.mesh.cleanup): largest component (or every component
above --min-component-ratio), optional Taubin smoothing and decimation.

`--pose` takes a pose .npz (DATA.md section 2), a capture v1 directory (its poses.npz, frames
named as in capture.json) or a dataset artifact (its stored bone transforms: no body model
needed). Anny poses are read with the phenotype recorded in the model (needs `anny`); SMPL
sequences are recognised and refused, since retargeting them to Anny's skeleton is not available.
`--frame K` picks one frame (default 0), `--all` every frame. Posed meshes use every skinning
weight of the grid and the non-rigid offset; the GLB keeps the 4 largest (what every glTF viewer
reads) or 8, and each posed frame's manifest record gives the distance between the GLB's top-4
skinning and full-weight LBS (glb_top4_gap_mm), and between top-4 / top-8 skinning and the posed
mesh itself (glb_drift_mm, mm, max and mean); glb.drift_mm is the largest over the frames.
`--exr` views: a frontal camera (the body's forward axis, rotated with the root in posed frames)
framing the mesh, for the canonical mesh and each exported frame; maps are ray-cast from the
exported meshes (Embree), so they match the files exactly.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.spatial
import torch
import trimesh

from igavatar.artifacts.atomic import atomic_directory
from igavatar.artifacts.targets import check_output_target
from igavatar.artifacts.manifest import (
    MANIFEST_NAME,
    InputRecord,
    build_manifest,
    read_artifact,
    read_manifest,
    sha256_json,
)
from igavatar.body.motions import body_to_world
from igavatar.body.skeleton import Skeleton
from igavatar.errors import ArtifactError, InputError
from igavatar.mesh.cleanup import clean_mesh, is_watertight, vertex_normals
from igavatar.mesh.exr import write_exr
from igavatar.mesh.extract import extract_mesh
from igavatar.mesh.gltf import INFLUENCE_CHOICES, INFLUENCES, gltf_axes, srgb_to_linear
from igavatar.mesh.skin_drift import lbs_sparse, skin_drift_mm, sparse_weight_sets
from igavatar.mesh.pose_files import local_pose_from_bone_transforms, read_pose_sequence, sequence_local_pose
from igavatar.mesh.posing import pose_canonical_vertices, surface_colors, vertex_colors, vertex_skin_weights
from igavatar.mesh.texture import png_bytes
from igavatar.mesh.textured_mesh import TexturedMesh, textured_mesh, textured_obj
from igavatar.model.avatar import Avatar
from igavatar.model.deformer import PreparedFrame
from igavatar.synth.raycast import CameraRays, MeshRayCaster, interpolate_vertex_values
from stages.glb_writer import write_model_glb
from stages.kernels import build_kernels
from stages.model_io import LoadedModel, load_model
from stages.progress import NULL_PROGRESS, ProgressSink
from stages.resources import IMAGE_BYTES_PER_PIXEL, peak_cuda_bytes, peak_ram_bytes, require_marching_memory, require_memory
from stages.train import resolve_device

FORMATS = ("ply", "obj", "glb")
DEFAULT_RESOLUTION = 512
"""Marching-cubes samples on the longest axis of the surface box: the paper's 512, on GPU and CPU
alike: the narrow band makes it cheap, 20-45 s on two shared CPU cores for a `cpu`-preset network,
cleanup and writing included (measured; 256 takes about 12 s)."""
COARSE_RESOLUTION = 64
CAMERA_FOV_DEG = 30.0
DEFAULT_FPS = 30.0
DEFAULT_TEXTURED_FACES = 30_000
"""Face budget of the textured mesh: a game-ready avatar (20-50k faces is the usual range)."""
_NO_ROOT_SDF = 1.0  # metres: "far outside" for posed points with no canonical correspondence
_BOX_PAD = 0.02  # of the canonical box's longest side, so the box's cap lies inside the grid


@dataclass(frozen=True)
class ExportOptions:
    """Options of `igavatar export` (see the CLI for each one's help)."""

    model: Path
    out: Path
    formats: tuple[str, ...] = FORMATS
    resolution: int = DEFAULT_RESOLUTION
    coarse_resolution: int = COARSE_RESOLUTION
    min_component_ratio: float | None = None
    taubin_steps: int = 0
    target_faces: int | None = None
    influences: int = INFLUENCES
    texture_size: int = 0
    textured_faces: int = DEFAULT_TEXTURED_FACES
    pose: Path | None = None
    frame: int | None = None
    all_frames: bool = False
    nonrigid: bool = True
    posed_marching: bool = False
    exr: bool = False
    exr_size: int = 512
    device: str = "auto"
    anny_cache: Path | None = None
    force: bool = False

    def config(self) -> dict:
        """The options that change the mesh artifact (recorded in the manifest, compared to skip)."""
        return {
            "formats": list(self.formats), "resolution": self.resolution, "coarse_resolution": self.coarse_resolution,
            "min_component_ratio": self.min_component_ratio, "taubin_steps": self.taubin_steps,
            "target_faces": self.target_faces, "influences": self.influences,
            "texture_size": self.texture_size, "textured_faces": self.textured_faces, "pose": None if self.pose is None else str(self.pose),
            "frame": self.frame, "all_frames": self.all_frames, "nonrigid": self.nonrigid,
            "posed_marching": self.posed_marching, "exr": self.exr, "exr_size": self.exr_size,
        }


@dataclass(frozen=True)
class ExportPoses:
    """The frames to export, as local rotations of the model's skeleton.

    Attributes:
        names: N frame names (file names under posed/).
        local_rotations: (N, J, 3, 3) relative to the rest pose; root_translation: (N, 3) world.
        fps: playback rate of the GLB animation.
        description: JSON-able facts for the manifest (source, format, skeleton, frames).
        inputs: the files/artifacts read, for the manifest.
    """

    names: list[str]
    local_rotations: torch.Tensor
    root_translation: torch.Tensor
    fps: float
    description: dict
    inputs: list[InputRecord]


def parse_formats(text: str) -> tuple[str, ...]:
    """'ply,glb' -> ('ply', 'glb'); InputError for unknown or no formats."""
    formats = tuple(dict.fromkeys(f.strip().lower() for f in text.split(",") if f.strip()))
    unknown = [f for f in formats if f not in FORMATS]
    if unknown or not formats:
        raise InputError(f"--formats {text!r}: expected a comma-separated subset of {', '.join(FORMATS)}")
    return formats


def _check_memory(options: ExportOptions, model_path: Path) -> None:
    """Refuse a --resolution or --exr-size this machine cannot hold, before the model is even loaded."""
    # The marching-cubes grid and the EXR maps live in host memory whatever --device says.
    require_marching_memory(read_manifest(model_path)["data"]["canonical_box"], options.resolution,
                            f"--resolution {options.resolution} (the marching-cubes grid)")
    if options.exr:
        require_memory(options.exr_size**2 * IMAGE_BYTES_PER_PIXEL, f"--exr-size {options.exr_size} (each depth/normal map)")


def _check_options(options: ExportOptions) -> None:
    if not options.formats or any(f not in FORMATS for f in options.formats):
        raise InputError(f"formats {list(options.formats)}: expected a non-empty subset of {', '.join(FORMATS)}")
    if options.resolution < 16:
        raise InputError(f"--resolution {options.resolution}: expected at least 16")
    if options.coarse_resolution < 8:
        raise InputError(f"--coarse-resolution {options.coarse_resolution}: expected at least 8")
    if options.min_component_ratio is not None and not 0.0 < options.min_component_ratio <= 1.0:
        raise InputError(f"--min-component-ratio {options.min_component_ratio}: expected a fraction in (0, 1]")
    if options.taubin_steps < 0:
        raise InputError(f"--taubin-steps {options.taubin_steps}: expected >= 0")
    if options.target_faces is not None and options.target_faces < 4:
        raise InputError(f"--target-faces {options.target_faces}: expected at least 4")
    if options.influences not in INFLUENCE_CHOICES:
        raise InputError(f"--influences {options.influences}: expected 4 (web engines) or 8 (JOINTS_1/WEIGHTS_1 too)")
    if options.texture_size and not 16 <= options.texture_size <= 8192:
        raise InputError(f"--texture-size {options.texture_size}: expected 0 (no textured mesh) or 16..8192 pixels")
    if options.textured_faces < 4:
        raise InputError(f"--textured-faces {options.textured_faces}: expected at least 4")
    if options.exr_size < 8:
        raise InputError(f"--exr-size {options.exr_size}: expected at least 8 pixels")
    if options.pose is None:
        for flag, used in (("--frame", options.frame is not None), ("--all", options.all_frames),
                           ("--posed-marching", options.posed_marching)):
            if used:
                raise InputError(f"{flag} needs --pose (a pose file, capture or dataset to pose the avatar with)")
    if options.frame is not None and options.all_frames:
        raise InputError("--frame and --all exclude each other: give one frame, or all of them")
    if options.frame is not None and options.frame < 0:
        raise InputError(f"--frame {options.frame}: expected a frame index >= 0")


# --------------------------------------------------------------------------------------------
# Pose sources


def _model_skeleton(model: LoadedModel) -> Skeleton:
    return Skeleton(model.subject["parents"], model.subject["rest_joints"], model.joint_names)


def _selection(options: ExportOptions, n_frames: int, source: Path) -> list[int]:
    if options.all_frames:
        return list(range(n_frames))
    frame = 0 if options.frame is None else options.frame
    if frame >= n_frames:
        raise InputError(f"--frame {frame}: {source} has {n_frames} frames (0..{n_frames - 1})")
    return [frame]


def _dataset_poses(options: ExportOptions, model: LoadedModel) -> ExportPoses:
    """Frames of a dataset artifact: its bone transforms turned back into local rotations."""
    dataset = Path(options.pose)
    read_artifact(dataset, expected="dataset")
    with np.load(dataset / "frames.npz") as stored:
        frames = {key: stored[key] for key in ("frame_names", "bone_transforms")}
    with np.load(dataset / "subject.npz") as stored:
        subject = {key: stored[key] for key in ("joint_names", "parents", "rest_joints", "canonical_rotations")}
    names = [str(n) for n in frames["frame_names"]]
    dataset_joints = [str(n) for n in subject["joint_names"]]
    if dataset_joints != model.joint_names or not np.array_equal(subject["parents"], model.subject["parents"]):
        raise InputError(
            f"{dataset}: its skeleton ({len(dataset_joints)} joints) is not the model's "
            f"({len(model.joint_names)} joints, {model.manifest['data']['body_model']}); retargeting is not available"
        )
    chosen = _selection(options, len(names), dataset / "frames.npz")
    rotations, translation = local_pose_from_bone_transforms(
        torch.from_numpy(frames["bone_transforms"][chosen]).double(), subject["parents"],
        torch.from_numpy(subject["rest_joints"]).double(), torch.from_numpy(subject["canonical_rotations"]).double(),
    )
    return ExportPoses(
        names=[names[i] for i in chosen], local_rotations=rotations.float(), root_translation=translation.float(),
        fps=DEFAULT_FPS,
        description={"source": str(dataset), "format": "dataset", "skeleton": model.manifest["data"]["body_model"],
                     "source_frames": len(names), "frame_indices": chosen},
        inputs=[InputRecord(dataset, "dataset")],
    )


def _sequence_poses(options: ExportOptions, model: LoadedModel, progress: ProgressSink) -> ExportPoses:
    """Frames of a pose file or capture directory, converted to the model's skeleton."""
    path = Path(options.pose)
    if path.is_dir() and (path / MANIFEST_NAME).is_file():
        read_artifact(path, expected="capture")  # an intact capture artifact, before reading it
    sequence = read_pose_sequence(path)
    chosen = _selection(options, sequence.n_frames, sequence.source)
    selected = sequence.select(chosen)
    data = model.manifest["data"]
    phenotype = data.get("subject", {}).get("phenotype")
    rotations, translation = sequence_local_pose(
        selected, _model_skeleton(model), data["body_model"], phenotype=phenotype,
        anny_cache=options.anny_cache, on_status=progress.status,
    )
    description = {"source": str(path), "format": sequence.format, "skeleton": sequence.skeleton_kind,
                   "source_frames": sequence.n_frames, "frame_indices": chosen}
    if sequence.phenotype is not None and phenotype is not None:
        description["phenotype_matches_model"] = all(
            abs(sequence.phenotype.get(k, v) - v) < 1e-6 for k, v in phenotype.items()
        )
        if not description["phenotype_matches_model"]:
            progress.status(f"{sequence.source}: recorded for another Anny phenotype; its pose parameters are "
                            "applied to the model's subject")
    if path.is_dir():
        captured = (path / MANIFEST_NAME).is_file()
        inputs = ([InputRecord(path, "capture")] if captured
                  else [InputRecord(sequence.source), InputRecord(path / "capture.json")])
    else:
        inputs = [InputRecord(path)]
    return ExportPoses(
        names=list(selected.frame_names), local_rotations=rotations, root_translation=translation,
        fps=float(sequence.fps or DEFAULT_FPS), description=description, inputs=inputs,
    )


def load_export_poses(options: ExportOptions, model: LoadedModel, progress: ProgressSink = NULL_PROGRESS) -> ExportPoses:
    """The frames `--pose` asks for (a pose file, a capture v1 directory or a dataset artifact)."""
    path = Path(options.pose)
    if not path.exists():
        raise InputError(f"--pose {path}: no such file or directory")
    if path.is_dir() and (path / MANIFEST_NAME).is_file():
        kind = read_manifest(path)["artifact"]
        if kind == "dataset":
            return _dataset_poses(options, model)
        if kind != "capture":
            raise ArtifactError(
                f"--pose {path}: is a {kind} artifact; --pose takes a pose .npz, a capture directory or a "
                "dataset artifact"
            )
    return _sequence_poses(options, model, progress)


# --------------------------------------------------------------------------------------------
# Geometry


def _closed_sdf(avatar: Avatar):
    """SDF of the canonical surface intersected with the canonical box: x (P, 3) -> (P,).

    max(sdf, box distance) is the SDF of the intersection (up to the usual max-bound), so a
    surface that reaches the box is capped there instead of left open.
    """
    box = avatar.canonical_box
    centre, half = (box[0] + box[1]) / 2, (box[1] - box[0]) / 2

    def sdf_fn(x_canonical: torch.Tensor) -> torch.Tensor:
        sdf = avatar.sdf_field(x_canonical)[0].reshape(-1)
        q = (x_canonical - centre).abs() - half
        box_sdf = q.clamp_min(0).norm(dim=-1) + q.amax(dim=-1).clamp_max(0)
        return torch.maximum(sdf, box_sdf)

    return sdf_fn


def _extract(sdf_fn, box_min: np.ndarray, box_max: np.ndarray, resolution: int, coarse: int, device,
             progress: ProgressSink, what: str, band: float = 1.0, chunk_points: int = 2**17):
    with progress.task(what, total=None) as advance:
        seen = [0]

        def report(done: int, total: int) -> None:
            advance(done - seen[0], points=f"{done / 1e6:.2f}M")
            seen[0] = done

        return extract_mesh(sdf_fn, box_min, box_max, resolution=resolution, coarse_resolution=coarse,
                            progress=report, device=device, band=band, chunk_points=chunk_points)


@torch.no_grad()
def canonical_surface(
    avatar: Avatar, resolution: int, coarse_resolution: int = COARSE_RESOLUTION, progress: ProgressSink = NULL_PROGRESS
) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes of the canonical SDF capped by the canonical box (closed), before cleanup.

    Returns vertices (V, 3) float32 in canonical space and faces (F, 3) int64, outward wound.
    """
    box = avatar.canonical_box.detach().cpu().numpy().astype(np.float64)
    pad = _BOX_PAD * float((box[1] - box[0]).max())
    return _extract(_closed_sdf(avatar), box[0] - pad, box[1] + pad, resolution, coarse_resolution,
                    avatar.canonical_box.device, progress, "marching cubes (canonical)")


@torch.no_grad()
def posed_surface(
    avatar: Avatar, frame: PreparedFrame, pose: torch.Tensor, box_min: np.ndarray, box_max: np.ndarray,
    resolution: int, coarse_resolution: int = COARSE_RESOLUTION // 2, progress: ProgressSink = NULL_PROGRESS,
) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes in posed space (the paper's alternative), before cleanup.

    The SDF of a posed point is the canonical SDF at its correspondence (root finding plus the
    non-rigid offset), +1 m where it has none. Returns world vertices (V, 3) and faces (F, 3).
    """

    def sdf_fn(x_posed: torch.Tensor) -> torch.Tensor:
        x_rigid, found = avatar.correspond(x_posed, frame, pose)
        sdf = avatar.sdf_field(avatar.offset_points(x_rigid, pose))[0].reshape(-1)
        return torch.where(found, sdf, torch.full_like(sdf, _NO_ROOT_SDF))

    # Skinning stretches distances a little, so the narrow band is widened (see extract_mesh).
    return _extract(sdf_fn, box_min, box_max, resolution, coarse_resolution, avatar.canonical_box.device,
                    progress, "marching cubes (posed)", band=2.0, chunk_points=2**15)


@torch.no_grad()
def posed_vertex_colors(avatar: Avatar, frame: PreparedFrame, pose: torch.Tensor, x_posed: np.ndarray) -> np.ndarray:
    """sRGB (V, 3) uint8 of the colour field at the canonical correspondences of posed points."""
    x_posed_torch = torch.from_numpy(np.asarray(x_posed, np.float32)).to(avatar.canonical_box.device)
    x_rigid, _ = avatar.correspond(x_posed_torch, frame, pose)
    return vertex_colors(avatar, avatar.offset_points(x_rigid, pose).cpu().numpy())


def _clean(vertices: np.ndarray, faces: np.ndarray, options: ExportOptions) -> tuple[np.ndarray, np.ndarray, dict]:
    return clean_mesh(
        vertices, faces, keep_largest=options.min_component_ratio is None,
        min_component_faces_ratio=options.min_component_ratio or 0.0, taubin_steps=options.taubin_steps,
        target_faces=options.target_faces,
    )


def _write_mesh(path: Path, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray) -> None:
    """PLY (binary) or OBJ with per-vertex sRGB colours, by the suffix."""
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh = trimesh.Trimesh(vertices, faces, vertex_colors=colors, process=False)
    if path.suffix == ".obj":
        mesh.export(path, include_normals=False, include_color=True, include_texture=False)
    else:
        mesh.export(path)


# --------------------------------------------------------------------------------------------
# Maps


def frontal_camera(vertices: np.ndarray, body_axes: np.ndarray, size: int, fov_deg: float = CAMERA_FOV_DEG
                   ) -> tuple[np.ndarray, np.ndarray]:
    """A pinhole camera in front of the body that frames all vertices.

    Args:
        vertices: (V, 3) world points to frame.
        body_axes: (3, 3) columns = the body's left, up, forward directions in world.
        size: image height = width in pixels; fov_deg: field of view.
    Returns:
        K (3, 3) and w2c (4, 4) (OpenCV: x right, y down, z forward), float64.
    """
    _, up, forward = body_axes.T
    z_axis = -forward  # the camera looks at the face
    y_axis = -up
    x_axis = np.cross(y_axis, z_axis)
    rotation = np.stack((x_axis, y_axis, z_axis))
    centre = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    local = (vertices - centre) @ rotation.T
    tan_half = math.tan(math.radians(fov_deg) / 2)
    # Each vertex needs |offset in the image plane| <= tan_half * (its depth from the camera) / margin.
    margin = 1.1
    distance = float(np.max(-local[:, 2] + np.abs(local[:, :2]).max(axis=1) * margin / tan_half))
    position = centre - z_axis * distance
    w2c = np.eye(4)
    w2c[:3, :3] = rotation
    w2c[:3, 3] = -rotation @ position
    focal = size / 2 / tan_half
    K = np.array([[focal, 0.0, (size - 1) / 2], [0.0, focal, (size - 1) / 2], [0.0, 0.0, 1.0]])
    return K, w2c


def mesh_maps(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray, K: np.ndarray, w2c: np.ndarray,
              size: int) -> dict[str, np.ndarray]:
    """Ray-cast depth (Z: camera z), unit world normals (N), coverage (A) and linear colour (RGB)."""
    rays = CameraRays(K, w2c, size, size, supersample=1)
    caster = MeshRayCaster(vertices, faces)
    directions = rays.directions.reshape(-1, 3)
    hits = caster.first_hits(np.broadcast_to(rays.origin, directions.shape), directions)
    hit = hits.hit
    x_world = rays.origin + directions.astype(np.float64) * np.where(hit, hits.distance, 0.0)[:, None]
    depth = np.where(hit, x_world @ w2c[2, :3] + w2c[2, 3], 0.0)
    normals = interpolate_vertex_values(vertex_normals(vertices, faces), faces, hits)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.where(hit[:, None] & (length > 0), normals / np.maximum(length, 1e-12), 0.0)
    rgb = srgb_to_linear(interpolate_vertex_values(colors / 255.0, faces, hits)) * hit[:, None]
    shape = (size, size)
    return {
        "Z": depth.reshape(shape).astype(np.float32),
        "N": normals.reshape(shape + (3,)).astype(np.float32),
        "A": hit.reshape(shape).astype(np.float32),
        "RGB": rgb.reshape(shape + (3,)).astype(np.float32),
    }


def _body_axes(body_model: str) -> np.ndarray:
    # Bare skeletons have no convention of their own; SMPL's (+Y up, +Z forward) is assumed.
    return body_to_world(body_model if body_model in ("anny", "smpl") else "smpl")


# --------------------------------------------------------------------------------------------
# The stage


def _input_json(records: list[InputRecord]) -> list[dict]:
    return [record.to_json() for record in records]


def _up_to_date(out: Path, config: dict, inputs: list[dict]) -> bool:
    if not (out / MANIFEST_NAME).is_file():
        return False
    try:
        manifest = read_artifact(out, expected="mesh")
    except ArtifactError:
        return False
    return (sha256_json(manifest["config"]) == sha256_json(config)
            and [i["sha256"] for i in manifest["inputs"]] == [i["sha256"] for i in inputs])


@dataclass(frozen=True)
class _Canonical:
    """The cleaned canonical mesh and what every output needs from it (numpy)."""

    vertices: np.ndarray  # (V, 3) float32
    faces: np.ndarray  # (F, 3) int64
    colors: np.ndarray  # (V, 3) uint8 sRGB
    skin_weights: np.ndarray | None  # (V, J) full grid weights, when a GLB is written
    sparse_sets: dict | None  # {4: (joints, weights), 8: ...} top-k of skin_weights (sparse_weight_sets)


def _export_frame(
    tmp: Path, model: LoadedModel, canonical: _Canonical, name: str, transforms: torch.Tensor, condition: torch.Tensor,
    options: ExportOptions, progress: ProgressSink,
) -> tuple[dict, dict | None, np.ndarray]:
    """Write posed/<name>.* (and the posed-marching mesh) of one frame.

    Args:
        transforms: (J, 4, 4) bone transforms; condition: (P,) pose conditioning.
    Returns:
        the frame's manifest record, its posed-marching record (None without --posed-marching) and
        the posed vertices (V, 3) in world coordinates.
    """
    avatar = model.avatar
    frame = avatar.deformer.prepare(transforms)
    x_posed = pose_canonical_vertices(avatar, canonical.vertices, frame, condition)
    record = {"name": name, "files": [], "bounds": [x_posed.min(axis=0).tolist(), x_posed.max(axis=0).tolist()]}
    for fmt in [f for f in options.formats if f in ("ply", "obj")] or ["ply"]:
        _write_mesh(tmp / "posed" / f"{name}.{fmt}", x_posed, canonical.faces, canonical.colors)
        record["files"].append(f"posed/{name}.{fmt}")
    if canonical.skin_weights is not None:
        # How far a glTF viewer's top-4 skinning of the GLB lands from full-weight LBS (no offset),
        x_canonical = torch.from_numpy(canonical.vertices).to(avatar.canonical_box.device)
        full_lbs = avatar.deformer.forward_skinning(x_canonical, frame).cpu().numpy()
        joints, weights = canonical.sparse_sets[4]
        gap = np.linalg.norm(lbs_sparse(canonical.vertices, joints, weights, transforms) - full_lbs, axis=1)
        record["glb_top4_gap_mm"] = {"max": float(gap.max() * 1e3), "mean": float(gap.mean() * 1e3)}
        # and how far top-4 and top-8 skinning land from igavatar's own posing (offset included).
        record["glb_drift_mm"] = skin_drift_mm(canonical.vertices, canonical.sparse_sets, transforms, x_posed)
    if not options.posed_marching:
        return record, None, x_posed

    started = time.perf_counter()
    margin = max(0.05, 0.05 * float((x_posed.max(axis=0) - x_posed.min(axis=0)).max()))
    vertices, faces = posed_surface(avatar, frame, condition, x_posed.min(axis=0) - margin, x_posed.max(axis=0) + margin,
                                    options.resolution, max(options.coarse_resolution // 2, 8), progress)
    vertices, faces, report = _clean(vertices, faces, options)
    marched = {"name": name, "vertices": int(vertices.shape[0]), "faces": int(faces.shape[0]),
               "watertight": bool(faces.shape[0] and is_watertight(vertices, faces)),
               "components_dropped": report["components_dropped"]}
    if faces.shape[0]:
        _write_mesh(tmp / "posed" / f"{name}.marched.ply", vertices, faces,
                    posed_vertex_colors(avatar, frame, condition, vertices))
        marched["file"] = f"posed/{name}.marched.ply"
        # Symmetric mean vertex distance to the LBS-posed mesh, to compare the two methods.
        to_lbs = scipy.spatial.cKDTree(x_posed).query(vertices)[0]
        to_marched = scipy.spatial.cKDTree(vertices).query(x_posed)[0]
        marched["mean_distance_to_posed_mm"] = float(0.5 * (to_lbs.mean() + to_marched.mean()) * 1e3)
    marched["seconds"] = time.perf_counter() - started
    return record, marched, x_posed


def _write_maps(tmp: Path, views: list[tuple[str, np.ndarray, np.ndarray]], canonical: _Canonical, size: int,
                progress: ProgressSink) -> list[dict]:
    """maps/<name>.exr of each (name, x_world (V, 3), body axes (3, 3)) view, and maps/cameras.npz."""
    records, cameras = [], []
    with progress.task("depth and normal maps", total=len(views)) as advance:
        for name, x_world, axes in views:
            K, w2c = frontal_camera(x_world, axes, size)
            write_exr(tmp / "maps" / f"{name}.exr", mesh_maps(x_world, canonical.faces, canonical.colors, K, w2c, size))
            cameras.append((K, w2c))
            records.append({"name": name, "file": f"maps/{name}.exr"})
            advance(1)
    np.savez(tmp / "maps" / "cameras.npz", names=np.array([r["name"] for r in records], dtype=np.str_),
             K=np.stack([c[0] for c in cameras]), w2c=np.stack([c[1] for c in cameras]), height=size, width=size)
    return records


def _write_textured(tmp: Path, model: LoadedModel, textured: TexturedMesh, options: ExportOptions,
                    poses: ExportPoses | None) -> dict:
    """textured/avatar.png, .obj + .mtl and (with glb) the textured, rigged avatar.glb; their manifest record.

    The OBJ is written in glTF's +Y-up frame like the GLB (both are for other tools; canonical.*
    stay in the capture frame).
    """
    folder = tmp / "textured"
    folder.mkdir()
    png = png_bytes(textured.image)
    (folder / "avatar.png").write_bytes(png)
    files = ["textured/avatar.png"]
    if "obj" in options.formats:
        axes = gltf_axes(model.manifest["data"]["body_model"])
        obj, mtl = textured_obj(textured.vertices.astype(np.float64) @ axes.T, textured.faces, textured.uv,
                                "avatar.mtl", "avatar.png")
        (folder / "avatar.obj").write_text(obj)
        (folder / "avatar.mtl").write_text(mtl)
        files += ["textured/avatar.obj", "textured/avatar.mtl"]
    glb = None
    if "glb" in options.formats:
        skin_weights = vertex_skin_weights(model.avatar, textured.vertices)
        motion = None if poses is None else (poses.local_rotations, poses.root_translation, poses.fps)
        glb = write_model_glb(folder / "avatar.glb", model, textured.vertices, textured.faces, None, skin_weights,
                              options.influences, motion=motion, texture=(textured.uv, png))
        files.append("textured/avatar.glb")
    return {
        "files": files, "vertices": int(textured.vertices.shape[0]), "faces": int(textured.faces.shape[0]),
        "decimated_vertices": textured.decimated_vertices, "target_faces": options.textured_faces,
        "texture_size": options.texture_size, "texel_coverage": textured.coverage,
        "bytes": {f: (tmp / f).stat().st_size for f in files}, "glb": glb,
    }


def run_export(options: ExportOptions, progress: ProgressSink = NULL_PROGRESS) -> dict:
    """Extract, clean, colour, rig and (with --pose) pose the avatar's mesh; write the mesh artifact.

    Returns a JSON-able summary. Raises InputError / ArtifactError / BodyModelError /
    NotAvailableError for problems a user can fix; nothing is written then.
    """
    started = time.perf_counter()
    _check_options(options)
    timings: dict[str, float] = {}
    device = resolve_device(options.device)
    build_kernels(device, progress)
    out, model_path = Path(options.out), Path(options.model)
    output_inputs = [model_path, options.pose]
    check_output_target(out, "mesh", output_inputs)
    _check_memory(options, model_path)

    tick = time.perf_counter()
    model = load_model(model_path, device)
    avatar, data, subject = model.avatar, model.manifest["data"], model.subject
    poses = load_export_poses(options, model, progress) if options.pose is not None else None
    timings["load_s"] = time.perf_counter() - tick
    config = options.config()
    inputs = [InputRecord(model_path, "model")] + (poses.inputs if poses else [])
    if not options.force and _up_to_date(out, config, _input_json(inputs)):
        return {"mesh": str(out), "skipped": "inputs and options unchanged (use --force to redo)"}

    tick = time.perf_counter()
    raw_vertices, raw_faces = canonical_surface(avatar, options.resolution, options.coarse_resolution, progress)
    timings["extract_s"] = time.perf_counter() - tick
    if raw_faces.shape[0] == 0:
        raise InputError(
            f"{model_path}: the model's SDF has no surface inside its canonical box (nothing to export); "
            "train longer or check the training log"
        )
    tick = time.perf_counter()
    vertices, faces, cleanup = _clean(raw_vertices, raw_faces, options)
    watertight = is_watertight(vertices, faces)
    timings["cleanup_s"] = time.perf_counter() - tick
    box = avatar.canonical_box.detach().cpu().numpy().astype(np.float64)
    half_voxel = 0.5 * float((box[1] - box[0]).max()) * (1 + 2 * _BOX_PAD) / (options.resolution - 1)
    on_box = np.any((np.abs(vertices - box[0]) < half_voxel) | (np.abs(vertices - box[1]) < half_voxel), axis=1)

    tick = time.perf_counter()
    colors = vertex_colors(avatar, vertices)
    timings["colors_s"] = time.perf_counter() - tick
    skin_weights = None
    if "glb" in options.formats:
        tick = time.perf_counter()
        skin_weights = vertex_skin_weights(avatar, vertices)
        timings["skin_weights_s"] = time.perf_counter() - tick
    canonical = _Canonical(vertices, faces, colors, skin_weights,
                           None if skin_weights is None else sparse_weight_sets(skin_weights))
    textured = None
    if options.texture_size:
        tick = time.perf_counter()
        textured = textured_mesh(vertices, faces, lambda points: surface_colors(avatar, points),
                                 options.textured_faces, options.texture_size)
        timings["textured_s"] = time.perf_counter() - tick

    canonical_files: list[str] = []
    posed_records: list[dict] = []
    marched_records: list[dict] = []
    map_records: list[dict] = []
    glb_info = None
    with atomic_directory(out, kind="mesh", inputs=output_inputs) as tmp:
        tick = time.perf_counter()
        for fmt in (f for f in options.formats if f in ("ply", "obj")):
            _write_mesh(tmp / f"canonical.{fmt}", vertices, faces, colors)
            canonical_files.append(f"canonical.{fmt}")
        if skin_weights is not None:
            motion = None if poses is None else (poses.local_rotations, poses.root_translation, poses.fps)
            facts = write_model_glb(tmp / "canonical.glb", model, vertices, faces, colors, skin_weights,
                                    options.influences, motion=motion)
            canonical_files.append("canonical.glb")
            glb_info = {"file": "canonical.glb", **facts, "drift_mm": None}
        timings["write_canonical_s"] = time.perf_counter() - tick
        textured_info = None
        if textured is not None:
            tick = time.perf_counter()
            textured_info = _write_textured(tmp, model, textured, options, poses)
            timings["write_textured_s"] = time.perf_counter() - tick

        body_axes = _body_axes(data["body_model"])
        map_views = [("canonical", vertices, body_axes)] if options.exr else []
        if poses is not None:
            avatar.nonrigid.set_enabled(avatar.nonrigid.enabled and options.nonrigid)
            posed = model.pose(poses.local_rotations, poses.root_translation)
            transforms, conditions = posed.bone_transforms.to(device), posed.pose_condition.to(device)
            tick = time.perf_counter()
            with progress.task("posing frames", total=len(poses.names)) as advance:
                for k, name in enumerate(poses.names):
                    record, marched, x_posed = _export_frame(tmp, model, canonical, name, transforms[k], conditions[k],
                                                             options, progress)
                    posed_records.append(record)
                    if marched is not None:
                        marched_records.append(marched)
                    # The frontal camera turns with the root: it faces the body in every pose.
                    if options.exr:
                        root_rotation = transforms[k, 0, :3, :3].double().cpu().numpy()
                        map_views.append((name, x_posed, root_rotation @ body_axes))
                    advance(1)
            timings["posing_s"] = time.perf_counter() - tick
            if glb_info is not None:
                glb_info["drift_mm"] = {
                    k: max(r["glb_drift_mm"][k]["max"] for r in posed_records) for k in ("4", "8")
                }
            if options.posed_marching:
                timings["posed_marching_s"] = sum(m["seconds"] for m in marched_records)
                timings["posing_s"] -= timings["posed_marching_s"]
        if map_views:
            tick = time.perf_counter()
            map_records = _write_maps(tmp, map_views, canonical, options.exr_size, progress)
            timings["maps_s"] = time.perf_counter() - tick

        data_json = {
            "model": str(model_path),
            "body_model": data["body_model"],
            "device": str(device),
            "canonical": {
                "files": canonical_files, "vertices": int(vertices.shape[0]), "faces": int(faces.shape[0]),
                "watertight": watertight, "resolution": options.resolution,
                "coarse_resolution": options.coarse_resolution,
                "raw_vertices": int(raw_vertices.shape[0]), "raw_faces": int(raw_faces.shape[0]),
                **{key: cleanup[key] for key in ("components", "components_dropped", "faces_dropped_in_components",
                                                 "taubin_steps", "decimated")},
                "vertices_on_box": int(on_box.sum()),
                "bounds": [vertices.min(axis=0).tolist(), vertices.max(axis=0).tolist()],
            },
            "glb": glb_info,
            "textured": textured_info,
            "posed": None if poses is None else {
                **poses.description, "nonrigid": bool(avatar.nonrigid.enabled), "frames": posed_records,
            },
            "posed_marching": marched_records if options.posed_marching else None,
            "maps": None if not map_records else {
                "size": [options.exr_size, options.exr_size], "cameras": "maps/cameras.npz",
                "channels": ["Z", "N", "A", "RGB"], "fov_deg": CAMERA_FOV_DEG, "views": map_records,
            },
        }
        timings["total_s"] = time.perf_counter() - started
        build_manifest(
            "mesh", tmp, stage="export", config=config, inputs=inputs, data=data_json, device=str(device),
            timings=timings, peak_memory={"ram_bytes": peak_ram_bytes(), "cuda_bytes": peak_cuda_bytes()},
        )

    summary = {
        "mesh": str(out), "device": str(device), "resolution": options.resolution,
        "vertices": int(vertices.shape[0]), "faces": int(faces.shape[0]), "watertight": watertight,
        "components_dropped": cleanup["components_dropped"],
        "files": [str(out / f) for f in canonical_files],
        "seconds": round(timings["total_s"], 1),
    }
    if textured_info is not None:
        summary["textured"] = [str(out / f) for f in textured_info["files"]]
    if poses is not None:
        summary["posed_frames"] = len(poses.names)
        summary["posed_dir"] = str(out / "posed")
    if map_records:
        summary["maps"] = str(out / "maps")
    return summary
