"""`igavatar export`: a model artifact -> a mesh artifact (canonical mesh, rigged GLB, posed meshes, maps).

    summary = run_export(ExportOptions(model=Path("run/model"), out=Path("run/mesh")))
    summary = run_export(ExportOptions(model=..., out=..., pose=Path("run/capture"), all_frames=True, exr=True))

Mesh layout (schema `mesh`, version 1; every position in meters):
    canonical.ply, canonical.obj   the canonical-space surface with sRGB vertex colors
    canonical.glb                  rigged, for engines and browsers: the same surface decimated to
                                   --glb-faces (default 50k; its distance to the full mesh is in the
                                   manifest), the skeleton (joints named, bind pose = the canonical
                                   pose), the 4 (--influences 8: 8, as JOINTS_0/1) largest skinning
                                   weights per vertex and the vertex colors, in glTF's +Y-up,
                                   +Z-forward frame with the origin on the floor under the root joint
                                   (igavatar.mesh.gltf); with --pose it also holds the exported frames
                                   as an animation (linear blend skinning only: no non-rigid offset)
    textured/avatar.glb|.obj|.mtl|.png   --texture-size S: the canonical mesh decimated to
                                   --textured-faces (pymeshlab quadric), UV-unwrapped (xatlas), the
                                   color field baked per texel into an S x S PNG (seams dilated);
                                   the GLB is rigged (and animated) like canonical.glb; both Y-up
    posed/<frame>.ply|.obj         the avatar in each exported pose, in WORLD coordinates (root
                                   transform applied): forward LBS of the canonical mesh plus the
                                   pose-conditioned non-rigid offset; same faces as canonical
    posed/<frame>.marched.ply      --posed-marching: marching cubes in posed space through the deformer
    maps/<view>.exr                --exr: Z (camera depth in m, 0 where empty), N (unit world-space
                                   normals), A (coverage 0/1), RGB (linear color) of the exported mesh
    maps/cameras.npz               names (M,), K (M,3,3), w2c (M,4,4), height, width of those views

The canonical surface is marching cubes of the SDF intersected with the canonical box (the hash
grid is only defined there), so it is closed even when an undertrained surface reaches the box;
how many vertices lie on the box is recorded. Extraction is coarse-to-fine and narrow-band
(igavatar.geometry.extract), at the paper's 512 by default on CPU and GPU alike (20-45 s on two CPU
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

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.spatial
import torch
import trimesh

from igavatar.artifacts.atomic import atomic_directory
from igavatar.artifacts.manifest import InputRecord, build_manifest
from igavatar.artifacts.targets import check_output_target
from igavatar.artifacts.png import png_bytes
from igavatar.avatar.glb import write_model_glb
from igavatar.avatar.model import ModelArtifact, load_model
from igavatar.avatar.poses import PoseSequence
from igavatar.avatar.surfaces import (
    canonical_surface,
    posed_surface,
    posed_vertex_colors,
    surface_colors,
    vertex_colors,
    vertex_skin_weights,
    vertices_on_box,
)
from igavatar.errors import InputError
from igavatar.mesh.cleanup import clean_mesh, is_watertight
from igavatar.mesh.exr import write_exr
from igavatar.mesh.gltf import floor_origin_offset, gltf_axes
from igavatar.mesh.maps import CAMERA_FOV_DEG, frontal_camera, mesh_maps
from igavatar.mesh.engine_mesh import engine_mesh
from igavatar.mesh.skin_drift import lbs_sparse, skin_drift_mm, sparse_weight_sets
from igavatar.mesh.textured_mesh import TexturedMesh, textured_mesh, textured_obj
from igavatar.model.posed import PosedAvatar
from stages.common import StageClock, skipped, unchanged
from stages.kernels import build_kernels, resolve_device
from stages.progress import NULL_PROGRESS, ProgressSink
from stages.texture_views import image_painter
from stages.export_options import ExportOptions, check_memory, check_options, load_export_poses
from stages.resources import peak_cuda_bytes, peak_ram_bytes


# --------------------------------------------------------------------------------------------
# Geometry


def _clean(vertices: np.ndarray, faces: np.ndarray, options: ExportOptions) -> tuple[np.ndarray, np.ndarray, dict]:
    return clean_mesh(
        vertices, faces, keep_largest=options.min_component_ratio is None,
        min_component_faces_ratio=options.min_component_ratio or 0.0, taubin_steps=options.taubin_steps,
        target_faces=options.target_faces,
    )


def _write_mesh(path: Path, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray) -> None:
    """PLY (binary) or OBJ with per-vertex sRGB colors, by the suffix."""
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh = trimesh.Trimesh(vertices, faces, vertex_colors=colors, process=False)
    if path.suffix == ".obj":
        mesh.export(path, include_normals=False, include_color=True, include_texture=False)
    else:
        mesh.export(path)


@contextmanager
def _marching_progress(progress: ProgressSink, what: str) -> Iterator[Callable[[int, int], None]]:
    """extract_mesh's progress(done, total) callback, drawn as a progress task."""
    with progress.task(what, total=None) as advance:
        seen = [0]

        def report(done: int, total: int) -> None:
            advance(done - seen[0], points=f"{done / 1e6:.2f}M")
            seen[0] = done

        yield report


@dataclass(frozen=True)
class _Canonical:
    """The cleaned canonical mesh and what every output needs from it (numpy)."""

    vertices: np.ndarray  # (V, 3) float32
    faces: np.ndarray  # (F, 3) int64
    colors: np.ndarray  # (V, 3) uint8 sRGB
    glb: _GlbMesh | None  # the GLB's (decimated) mesh, when a GLB is written
    record: dict  # the manifest's canonical record (without its files)


@dataclass(frozen=True)
class _GlbMesh:
    """canonical.glb's mesh (`engine_mesh`), its colors and skinning weights (numpy)."""

    vertices: np.ndarray  # (V', 3) float32
    faces: np.ndarray  # (F', 3) int64
    colors: np.ndarray  # (V', 3) uint8 sRGB
    skin_weights: np.ndarray  # (V', J) full grid weights
    sparse_sets: dict  # {4: (joints, weights), 8: ...} top-k of skin_weights (sparse_weight_sets)
    record: dict  # engine_mesh's record

    @classmethod
    def of(cls, avatar, vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray, target_faces: int) -> _GlbMesh:
        glb_vertices, glb_faces, record = engine_mesh(vertices, faces, target_faces)
        if record["decimated"]:  # the color field at the new vertices, not an average of old ones
            colors = vertex_colors(avatar, glb_vertices)
        weights = vertex_skin_weights(avatar, glb_vertices)
        return cls(glb_vertices, glb_faces, colors, weights, sparse_weight_sets(weights), record)


def _canonical(model: ModelArtifact, options: ExportOptions, clock: StageClock, progress: ProgressSink) -> _Canonical:
    """Extract, clean and color the canonical surface (and weigh it for the GLB)."""
    avatar = model.avatar
    with clock("extract_s"), _marching_progress(progress, "marching cubes (canonical)") as report:
        raw_vertices, raw_faces = canonical_surface(avatar, options.resolution, options.coarse_resolution, report,
                                                    surface_level=options.surface_level)
    if raw_faces.shape[0] == 0:
        raise InputError(
            f"{model.path}: the model's SDF has no surface inside its canonical box (nothing to export); "
            "train longer or check the training log"
        )
    with clock("cleanup_s"):
        vertices, faces, cleanup = _clean(raw_vertices, raw_faces, options)
        watertight = is_watertight(vertices, faces)
    on_box = vertices_on_box(avatar, vertices, options.resolution)
    with clock("colors_s"):
        colors = vertex_colors(avatar, vertices)
    glb = None
    if "glb" in options.formats:
        with clock("glb_mesh_s"):
            glb = _GlbMesh.of(avatar, vertices, faces, colors, options.glb_faces)
    record = {
        "vertices": int(vertices.shape[0]), "faces": int(faces.shape[0]),
        "watertight": watertight, "resolution": options.resolution, "coarse_resolution": options.coarse_resolution,
        "surface_level": options.surface_level, "surface_level_m": avatar.surface_level(options.surface_level),
        "raw_vertices": int(raw_vertices.shape[0]), "raw_faces": int(raw_faces.shape[0]),
        **{key: cleanup[key] for key in ("components", "components_dropped", "faces_dropped_in_components",
                                         "taubin_steps", "decimated")},
        "vertices_on_box": int(on_box.sum()),
        "bounds": [vertices.min(axis=0).tolist(), vertices.max(axis=0).tolist()],
    }
    return _Canonical(vertices, faces, colors, glb, record)


def _export_frame(tmp: Path, model: ModelArtifact, canonical: _Canonical, poses: PoseSequence, k: int,
                  options: ExportOptions, progress: ProgressSink) -> tuple[dict, dict | None, np.ndarray]:
    """Write posed/<name>.* (and the posed-marching mesh) of frame k.

    Returns:
        the frame's manifest record, its posed-marching record (None without --posed-marching) and
        the posed vertices (V, 3) in world coordinates.
    """
    name, transforms = poses.frame_names[k], poses.bone_transforms[k].to(model.device)
    posed = model.posed(transforms, poses.pose_condition[k], nonrigid=options.nonrigid)
    x_posed = posed.pose_vertices(canonical.vertices)
    record = {"name": name, "files": [], "bounds": [x_posed.min(axis=0).tolist(), x_posed.max(axis=0).tolist()]}
    for fmt in [f for f in options.formats if f in ("ply", "obj")] or ["ply"]:
        _write_mesh(tmp / "posed" / f"{name}.{fmt}", x_posed, canonical.faces, canonical.colors)
        record["files"].append(f"posed/{name}.{fmt}")
    glb = canonical.glb
    if glb is not None:
        # How far a glTF viewer's top-4 skinning of the GLB lands from full-weight LBS (no offset),
        full_lbs = posed.skin(torch.from_numpy(glb.vertices)).cpu().numpy()
        joints, weights = glb.sparse_sets[4]
        gap = np.linalg.norm(lbs_sparse(glb.vertices, joints, weights, transforms) - full_lbs, axis=1)
        record["glb_top4_gap_mm"] = {"max": float(gap.max() * 1e3), "mean": float(gap.mean() * 1e3)}
        # and how far top-4 and top-8 skinning land from igavatar's own posing of the same vertices.
        x_posed_glb = posed.pose_vertices(glb.vertices) if glb.record["decimated"] else x_posed
        record["glb_drift_mm"] = skin_drift_mm(glb.vertices, glb.sparse_sets, transforms, x_posed_glb)
    if not options.posed_marching:
        return record, None, x_posed
    return record, _posed_marching(tmp, posed, name, x_posed, options, progress), x_posed


def _posed_marching(tmp: Path, posed: PosedAvatar, name: str, x_posed: np.ndarray, options: ExportOptions,
                    progress: ProgressSink) -> dict:
    """posed/<name>.marched.ply: marching cubes in posed space; its record (sizes, distance to the LBS mesh)."""
    started = time.perf_counter()
    margin = max(0.05, 0.05 * float((x_posed.max(axis=0) - x_posed.min(axis=0)).max()))
    with _marching_progress(progress, "marching cubes (posed)") as report:
        vertices, faces = posed_surface(posed, x_posed.min(axis=0) - margin, x_posed.max(axis=0) + margin,
                                        options.resolution, max(options.coarse_resolution // 2, 8), report,
                                        surface_level=options.surface_level)
    vertices, faces, cleanup = _clean(vertices, faces, options)
    marched = {"name": name, "vertices": int(vertices.shape[0]), "faces": int(faces.shape[0]),
               "watertight": bool(faces.shape[0] and is_watertight(vertices, faces)),
               "components_dropped": cleanup["components_dropped"]}
    if faces.shape[0]:
        _write_mesh(tmp / "posed" / f"{name}.marched.ply", vertices, faces, posed_vertex_colors(posed, vertices))
        marched["file"] = f"posed/{name}.marched.ply"
        # Symmetric mean vertex distance to the LBS-posed mesh, to compare the two methods.
        to_lbs = scipy.spatial.cKDTree(x_posed).query(vertices)[0]
        to_marched = scipy.spatial.cKDTree(vertices).query(x_posed)[0]
        marched["mean_distance_to_posed_mm"] = float(0.5 * (to_lbs.mean() + to_marched.mean()) * 1e3)
    marched["seconds"] = time.perf_counter() - started
    return marched


@dataclass
class _Posed:
    """What posing the frames wrote: per-frame records, posed-marching records, EXR views."""

    frames: list[dict]
    marched: list[dict]
    map_views: list[tuple[str, np.ndarray, np.ndarray]]


def _pose_frames(tmp: Path, model: ModelArtifact, canonical: _Canonical, poses: PoseSequence | None,
                 options: ExportOptions, clock: StageClock, progress: ProgressSink) -> _Posed:
    body_axes = model.body_axes
    result = _Posed([], [], [("canonical", canonical.vertices, body_axes)] if options.exr else [])
    if poses is None:
        return result
    with clock("posing_s"), progress.task("posing frames", total=poses.n_frames) as advance:
        for k in range(poses.n_frames):
            record, marched, x_posed = _export_frame(tmp, model, canonical, poses, k, options, progress)
            result.frames.append(record)
            if marched is not None:
                result.marched.append(marched)
            # The frontal camera turns with the root: it faces the body in every pose.
            if options.exr:
                root_rotation = poses.bone_transforms[k, 0, :3, :3].double().cpu().numpy()
                result.map_views.append((poses.frame_names[k], x_posed, root_rotation @ body_axes))
            advance(1)
    if options.posed_marching:
        clock.timings["posed_marching_s"] = sum(m["seconds"] for m in result.marched)
        clock.timings["posing_s"] -= clock.timings["posed_marching_s"]
    return result


# --------------------------------------------------------------------------------------------
# Maps and textures


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


def _write_textured(tmp: Path, model: ModelArtifact, textured: TexturedMesh, options: ExportOptions,
                    poses: PoseSequence | None) -> dict:
    """textured/avatar.png, .obj + .mtl and (with glb) the textured, rigged avatar.glb; their manifest record.

    The OBJ is written in glTF's +Y-up frame with the origin on the floor, like the GLB (both are for
    other tools; canonical.* stay in the capture frame).
    """
    folder = tmp / "textured"
    folder.mkdir()
    png = png_bytes(textured.image)
    (folder / "avatar.png").write_bytes(png)
    files = ["textured/avatar.png"]
    if "obj" in options.formats:
        axes = gltf_axes(model.axes_kind)
        vertices_gltf = textured.vertices.astype(np.float64) @ axes.T
        root_gltf = np.asarray(model.subject.canonical_joints[0], np.float64) @ axes.T
        obj, mtl = textured_obj(vertices_gltf + floor_origin_offset(vertices_gltf, root_gltf), textured.faces, textured.uv,
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


def _write_canonical(tmp: Path, model: ModelArtifact, canonical: _Canonical, poses: PoseSequence | None,
                     options: ExportOptions) -> tuple[list[str], dict | None]:
    """canonical.ply/.obj/.glb; the files written and the GLB's record."""
    files: list[str] = []
    for fmt in (f for f in options.formats if f in ("ply", "obj")):
        _write_mesh(tmp / f"canonical.{fmt}", canonical.vertices, canonical.faces, canonical.colors)
        files.append(f"canonical.{fmt}")
    glb = canonical.glb
    if glb is None:
        return files, None
    motion = None if poses is None else (poses.local_rotations, poses.root_translation, poses.fps)
    facts = write_model_glb(tmp / "canonical.glb", model, glb.vertices, glb.faces, glb.colors, glb.skin_weights,
                            options.influences, motion=motion)
    files.append("canonical.glb")
    return files, {"file": "canonical.glb", **facts, "mesh": glb.record,
                   "bytes": (tmp / "canonical.glb").stat().st_size, "drift_mm": None}


def _summary(out: Path, device: torch.device, options: ExportOptions, canonical: _Canonical, files: list[str],
             textured: dict | None, poses: PoseSequence | None, maps: list[dict], seconds: float) -> dict:
    summary = {
        "mesh": str(out), "device": str(device), "resolution": options.resolution,
        "vertices": canonical.record["vertices"], "faces": canonical.record["faces"],
        "watertight": canonical.record["watertight"], "components_dropped": canonical.record["components_dropped"],
        "files": [str(out / f) for f in files], "seconds": round(seconds, 1),
    }
    if textured is not None:
        summary["textured"] = [str(out / f) for f in textured["files"]]
    if poses is not None:
        summary["posed_frames"] = poses.n_frames
        summary["posed_dir"] = str(out / "posed")
    if maps:
        summary["maps"] = str(out / "maps")
    return summary


def _texture_dataset(options: ExportOptions, model: ModelArtifact) -> Path | None:
    """The dataset whose training images --texture-from images fuses (None for the field or no texture)."""
    if options.texture_from != "images" or not options.texture_size:
        return None
    dataset = Path(options.dataset) if options.dataset is not None else model.trained_dataset()
    if dataset is None or not (dataset / "manifest.json").is_file():
        raise InputError(f"--texture-from images: the dataset {options.dataset or model.recorded_dataset} the model was "
                         "trained on is not there; give it with --dataset, or bake the color field with --texture-from field")
    return dataset


def run_export(options: ExportOptions, progress: ProgressSink = NULL_PROGRESS) -> dict:
    """Extract, clean, color, rig and (with --pose) pose the avatar's mesh; write the mesh artifact.

    Returns a JSON-able summary. Raises InputError / ArtifactError / BodyModelError /
    NotAvailableError for problems a user can fix; nothing is written then.
    """
    clock = StageClock()
    check_options(options)
    device = resolve_device(options.device)
    build_kernels(device, progress)
    out, model_path = Path(options.out), Path(options.model)
    output_inputs = [model_path, options.pose]
    check_output_target(out, "mesh", output_inputs)
    check_memory(options, model_path)
    with clock("load_s"):
        model = load_model(model_path, device)
        poses = load_export_poses(options, model, progress) if options.pose is not None else None
    texture_dataset = _texture_dataset(options, model)
    inputs = [InputRecord(model_path, "model"), *(poses.inputs if poses else ()),
              *([InputRecord(texture_dataset, "dataset")] if texture_dataset else [])]
    if not options.force and unchanged(out, "mesh", options.config(), inputs):
        return skipped("mesh", out)

    canonical = _canonical(model, options, clock, progress)
    textured, fusion = None, {}
    if options.texture_size:
        paint = None if texture_dataset is None else image_painter(model, texture_dataset, options.texture_views, progress, fusion)
        with clock("textured_s"):
            textured = textured_mesh(canonical.vertices, canonical.faces, lambda x: surface_colors(model.avatar, x),
                                     options.textured_faces, options.texture_size, paint=paint)
    with atomic_directory(out, kind="mesh", inputs=output_inputs) as tmp:
        with clock("write_canonical_s"):
            files, glb = _write_canonical(tmp, model, canonical, poses, options)
        textured_info = None
        if textured is not None:
            with clock("write_textured_s"):
                textured_info = _write_textured(tmp, model, textured, options, poses)
                textured_info["texture_from"] = {"source": options.texture_from, **fusion}
        posed = _pose_frames(tmp, model, canonical, poses, options, clock, progress)
        if glb is not None and posed.frames:
            glb["drift_mm"] = {k: max(r["glb_drift_mm"][k]["max"] for r in posed.frames) for k in ("4", "8")}
        maps = []
        if posed.map_views:
            with clock("maps_s"):
                maps = _write_maps(tmp, posed.map_views, canonical, options.exr_size, progress)
        data = {
            "model": str(model_path), "body_model": model.body_model, "device": str(device),
            "canonical": {"files": files, **canonical.record},
            "glb": glb, "textured": textured_info,
            "posed": None if poses is None else {
                **poses.description, "nonrigid": bool(model.avatar.nonrigid.enabled and options.nonrigid), "frames": posed.frames,
            },
            "posed_marching": posed.marched if options.posed_marching else None,
            "maps": None if not maps else {
                "size": [options.exr_size, options.exr_size], "cameras": "maps/cameras.npz",
                "channels": ["Z", "N", "A", "RGB"], "fov_deg": CAMERA_FOV_DEG, "views": maps,
            },
        }
        build_manifest("mesh", tmp, stage="export", config=options.config(), inputs=inputs, data=data, device=str(device),
                       timings=clock.finish(), peak_memory={"ram_bytes": peak_ram_bytes(), "cuda_bytes": peak_cuda_bytes()})
    return _summary(out, device, options, canonical, files, textured_info, poses, maps, clock.timings["total_s"])
