"""The options of `igavatar export`: their dataclass, their checks, and the poses `--pose` names.

    options = ExportOptions(model=Path("run/model"), out=Path("run/mesh"), formats=parse_formats("ply,glb"))
    check_options(options); check_memory(options, options.model)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from igavatar.avatar.model import ModelArtifact, read_model_manifest
from igavatar.avatar.poses import PoseSequence, read_poses
from igavatar.avatar.surfaces import COARSE_RESOLUTION
from igavatar.errors import InputError
from igavatar.mesh.engine_mesh import DEFAULT_GLB_FACES
from igavatar.mesh.gltf import INFLUENCE_CHOICES, INFLUENCES
from igavatar.model.avatar import SURFACE_LEVELS
from stages.progress import NULL_PROGRESS, ProgressSink
from stages.resources import IMAGE_BYTES_PER_PIXEL, require_marching_memory, require_memory

FORMATS = ("ply", "obj", "glb")
TEXTURE_SOURCES = ("images", "field")
DEFAULT_RESOLUTION = 512
"""Marching-cubes samples on the longest axis of the surface box: the paper's 512, on GPU and CPU
alike: the narrow band makes it cheap, 20-45 s on two shared CPU cores for a `cpu`-preset network,
cleanup and writing included (measured; 256 takes about 12 s)."""
DEFAULT_TEXTURED_FACES = 30_000
"""Face budget of the textured mesh: a game-ready avatar (20-50k faces is the usual range)."""


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
    #: What the textured mesh's texture is made from: "images" (the training images fused onto the
    #: mesh, stages.texture_views; sharper than the field on every subject measured,
    #: tests/benchmarks/results/texture-from-*.md) or "field" (the color network).
    texture_from: str = "images"
    #: --texture-from images: at most this many training frames, evenly spread (0: all).
    texture_views: int = 0
    #: --texture-from images: the dataset whose training images are used (None: the model's own).
    dataset: Path | None = None
    textured_faces: int = DEFAULT_TEXTURED_FACES
    #: canonical.glb's face budget (0: the full mesh).
    glb_faces: int = DEFAULT_GLB_FACES
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
    surface_level: str = SURFACE_LEVELS[0]
    """Where meshes are made: "silhouette" or "zero" (igavatar.model.avatar.SURFACE_LEVELS)."""

    def config(self) -> dict:
        """The options that change the mesh artifact (recorded in the manifest, compared to skip)."""
        return {
            "formats": list(self.formats), "resolution": self.resolution, "coarse_resolution": self.coarse_resolution,
            "min_component_ratio": self.min_component_ratio, "taubin_steps": self.taubin_steps,
            "target_faces": self.target_faces, "influences": self.influences,
            "texture_size": self.texture_size, "texture_from": self.texture_from, "texture_views": self.texture_views,
            "textured_faces": self.textured_faces, "glb_faces": self.glb_faces, "pose": None if self.pose is None else str(self.pose),
            "frame": self.frame, "all_frames": self.all_frames, "nonrigid": self.nonrigid,
            "posed_marching": self.posed_marching, "exr": self.exr, "exr_size": self.exr_size,
            "surface_level": self.surface_level,
        }


def parse_formats(text: str) -> tuple[str, ...]:
    """'ply,glb' -> ('ply', 'glb'); InputError for unknown or no formats."""
    formats = tuple(dict.fromkeys(f.strip().lower() for f in text.split(",") if f.strip()))
    unknown = [f for f in formats if f not in FORMATS]
    if unknown or not formats:
        raise InputError(f"--formats {text!r}: expected a comma-separated subset of {', '.join(FORMATS)}")
    return formats


def check_memory(options: ExportOptions, model_path: Path) -> None:
    """Refuse a --resolution or --exr-size this machine cannot hold, before the model is even loaded."""
    # The marching-cubes grid and the EXR maps live in host memory whatever --device says.
    require_marching_memory(read_model_manifest(model_path, check_hashes=False).canonical_box, options.resolution,
                            f"--resolution {options.resolution} (the marching-cubes grid)")
    if options.exr:
        require_memory(options.exr_size**2 * IMAGE_BYTES_PER_PIXEL, f"--exr-size {options.exr_size} (each depth/normal map)")


def check_options(options: ExportOptions) -> None:
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
    if options.texture_from not in TEXTURE_SOURCES:
        raise InputError(f"--texture-from {options.texture_from!r}: choose one of {', '.join(TEXTURE_SOURCES)}")
    if options.dataset is not None and not (options.texture_size and options.texture_from == "images"):
        raise InputError("--dataset (the images of --texture-from images) needs --texture-size (the textured mesh they "
                         "paint) and --texture-from images")
    if options.texture_views < 0:
        raise InputError(f"--texture-views {options.texture_views}: expected >= 0 (0: every training frame)")
    if options.textured_faces < 4:
        raise InputError(f"--textured-faces {options.textured_faces}: expected at least 4")
    if options.glb_faces and options.glb_faces < 4:
        raise InputError(f"--glb-faces {options.glb_faces}: expected at least 4, or 0 for the full mesh")
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
    if options.surface_level not in SURFACE_LEVELS:
        raise InputError(f"--surface-level {options.surface_level!r}: choose one of {', '.join(SURFACE_LEVELS)}")


# --------------------------------------------------------------------------------------------
# Pose sources


def load_export_poses(options: ExportOptions, model: ModelArtifact, progress: ProgressSink = NULL_PROGRESS) -> PoseSequence:
    """The frames `--pose` asks for (a pose file, a capture v1 directory or a dataset artifact)."""

    def selection(n_frames: int, where: str) -> list[int]:
        if options.all_frames:
            return list(range(n_frames))
        frame = 0 if options.frame is None else options.frame
        if frame >= n_frames:
            raise InputError(f"--frame {frame}: {where} has {n_frames} frames (0..{n_frames - 1})")
        return [frame]

    return read_poses(model, Path(options.pose), selection, anny_cache=options.anny_cache, on_status=progress.status,
                      option="--pose")
