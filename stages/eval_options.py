"""The options of `igavatar eval`, their checks, and what they resolve to (dataset, image size and frames).

    options = EvalOptions(model=Path("run/model"), out=Path("run/report"))
    check_options(options); settings = resolve_image_settings(options, torch.device("cpu"), model_samples=96)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from igavatar.avatar.model import ModelManifest
from igavatar.errors import InputError
from igavatar.model.avatar import SURFACE_LEVELS

#: Smallest rendered side: SSIM needs an 11 x 11 window.
MIN_IMAGE_SIDE = 16


@dataclass(frozen=True)
class EvalOptions:
    """Options of `igavatar eval` (see the CLI for each one's help)."""

    model: Path
    out: Path
    gt: Path | None = None
    dataset: Path | None = None
    geometry: bool = True
    images: bool = True
    mesh_resolution: int = 256
    surface_samples: int = 10_000
    iou_points: int = 1_000_000
    iou_open_meshes: bool = False
    image_scale: float | None = None
    samples_per_ray: int | None = None
    image_frames: int | None = None
    seed: int = 0
    device: str = "auto"
    surface_level: str = SURFACE_LEVELS[0]
    """Where meshes are made: "silhouette" or "zero" (igavatar.model.avatar.SURFACE_LEVELS)."""
    carry_poses: bool = False
    """Pose the test frames between a model's refined training frames of one clip by their
    neighbours' corrections, interpolated in time (igavatar.avatar.pose_carry); no test image is used."""
    refine_test_poses: bool = False
    """Refine each rendered test frame's pose against its image first (image metrics only)."""
    refine_test_pose_steps: int = 80
    force: bool = False
    """Redo even if the report is up to date (same model, dataset, scans and options)."""

    def config(self) -> dict:
        """The options that change the numbers (recorded in the manifest)."""
        return {
            "geometry": self.geometry, "images": self.images, "mesh_resolution": self.mesh_resolution,
            "surface_samples": self.surface_samples, "iou_points": self.iou_points,
            "iou_open_meshes": self.iou_open_meshes, "image_scale": self.image_scale,
            "samples_per_ray": self.samples_per_ray, "image_frames": self.image_frames, "seed": self.seed,
            "device": self.device,
            "carry_poses": self.carry_poses,
            "test_time_pose_refinement": self.refine_test_poses,
            **({"test_pose_steps": self.refine_test_pose_steps} if self.refine_test_poses else {}),
            "surface_level": self.surface_level,
        }


def resolve_dataset(model: ModelManifest, override: Path | None) -> Path:
    """The dataset the model was trained on (manifest data.dataset), or --dataset."""
    if override is not None:
        if not Path(override).exists():
            raise InputError(f"--dataset {override}: no such dataset directory")
        return Path(override)
    found = model.trained_dataset()
    if found is None:
        recorded = model.recorded_dataset
        raise InputError(
            f"{model.path}/manifest.json: data.dataset = {recorded} does not exist (nor {model.path.parent / recorded.name}); "
            "pass the dataset the model was trained on with --dataset"
        )
    return found


def render_size(dataset_hw: tuple[int, int], scale: float) -> tuple[int, int]:
    h, w = (max(MIN_IMAGE_SIDE, round(side * scale)) for side in dataset_hw)
    return int(h), int(w)


def check_options(options: EvalOptions) -> None:
    if not (options.geometry or options.images):
        raise InputError("--no-geometry and --no-images together leave nothing to evaluate")
    if options.mesh_resolution < 16:
        raise InputError(f"--mesh-resolution {options.mesh_resolution}: expected >= 16")
    if options.surface_samples < 1:
        raise InputError(f"--surface-samples {options.surface_samples}: expected >= 1")
    if options.iou_points < 0:
        raise InputError(f"--iou-points {options.iou_points}: expected >= 0 (0 skips the IoU)")
    if options.image_scale is not None and not 0 < options.image_scale <= 1:
        raise InputError(f"--image-scale {options.image_scale}: expected a fraction in (0, 1]")
    if options.samples_per_ray is not None and options.samples_per_ray < 1:
        raise InputError(f"--samples {options.samples_per_ray}: expected >= 1")
    if options.refine_test_poses and not options.images:
        raise InputError("--refine-test-poses refines poses for the image metrics; it needs --images")
    if options.refine_test_pose_steps < 1:
        raise InputError(f"--refine-test-pose-steps {options.refine_test_pose_steps}: expected >= 1")
    if options.image_frames is not None and options.image_frames < 0:
        raise InputError(f"--image-frames {options.image_frames}: expected >= 0 (0 = every test frame)")
    if options.surface_level not in SURFACE_LEVELS:
        raise InputError(f"--surface-level {options.surface_level!r}: choose one of {', '.join(SURFACE_LEVELS)}")


@dataclass(frozen=True)
class ImageSettings:
    """How test frames are rendered: resolved from the options and the device."""

    scale: float
    """Fraction of the dataset's image size."""
    samples_per_ray: int
    max_frames: int
    """Frames rendered, evenly spaced over the test frames (0 = all)."""


#: Size and frames when an option is not given. Volume rendering with root finding costs ~1 s a
#: 128 x 128 frame on two CPU cores at 96 samples, so on a CPU the demo's 30 test frames are
#: rendered at a quarter of 512 px, and only 10 of them; a GPU renders every frame at full size.
#: The samples per ray are not the device's but the model's (`resolve_image_settings`).
IMAGE_DEFAULTS = {"cpu": (0.25, 10), "cuda": (1.0, 0)}


def resolve_image_settings(options: EvalOptions, device: torch.device, model_samples: int) -> ImageSettings:
    """The options' image settings: a missing scale or frame count from IMAGE_DEFAULTS for the device,
    missing samples per ray from the model (`model_samples`: its TrainConfig.validation_samples, what
    its validation renders and `animate` use). Rendering with fewer samples than the model was
    trained and validated with puts each ray's colour off the surface and quantizes the outline:
    on the demo subject, 32 samples instead of 96 cost 0.44 dB box PSNR and 0.019 box SSIM at a
    quarter size (tests/benchmarks/results/eval-samples-quarter.md)."""
    scale, max_frames = IMAGE_DEFAULTS["cuda" if device.type == "cuda" else "cpu"]
    return ImageSettings(
        scale=options.image_scale if options.image_scale is not None else scale,
        samples_per_ray=options.samples_per_ray if options.samples_per_ray is not None else int(model_samples),
        max_frames=options.image_frames if options.image_frames is not None else max_frames,
    )


def image_frame_indices(n_frames: int, max_frames: int) -> set[int]:
    """Indices of the frames to render: all, or `max_frames` evenly spaced (first and last included)."""
    if max_frames <= 0 or max_frames >= n_frames:
        return set(range(n_frames))
    return {int(i) for i in np.linspace(0, n_frames - 1, max_frames).round()}
