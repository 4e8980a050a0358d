"""Cameras to film a posed avatar: a camera file, the capture's camera, or an orbit around the body.

    cameras = orbit_cameras(model, boxes, bone_transforms, 256, revolutions=1.0)   # turntable
    cameras = camera_file(Path("cams.npz"), n_frames, 256)
    cameras = capture_camera(dataset, n_frames, 256)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from igavatar.avatar.boxes import skinned_cells
from igavatar.avatar.dataset import DatasetArtifact
from igavatar.avatar.model import ModelArtifact
from igavatar.errors import InputError
from igavatar.render.cameras import resize_intrinsics, turntable_cameras

#: Skinned cells per frame that the orbit's K keeps in view, and the free image border left.
FRAMING_POINTS = 4096
FRAMING_MARGIN = 0.06


@dataclass(frozen=True)
class CameraSequence:
    """Cameras of N frames: K (N, 3, 3), w2c (N, 4, 4), image height and width, and where they came from."""

    kind: str
    K: torch.Tensor
    w2c: torch.Tensor
    height: int
    width: int
    source: str | None


def render_size(height: int, width: int, resolution: int) -> tuple[int, int]:
    """(H, W) with the camera's aspect ratio and the longer side equal to `resolution`."""
    scale = resolution / max(height, width)
    return max(1, round(height * scale)), max(1, round(width * scale))


def capture_camera(dataset: DatasetArtifact, n_frames: int, resolution: int) -> CameraSequence:
    """The dataset's first frame's camera for every frame, rescaled to `resolution`."""
    frames = dataset.frames()
    height, width = dataset.image_size
    h, w = render_size(height, width, resolution)
    K = resize_intrinsics(torch.from_numpy(frames.K[0]).float(), (height, width), (h, w))
    w2c = torch.from_numpy(frames.w2c[0]).float()
    return CameraSequence("capture", K.expand(n_frames, 3, 3).clone(), w2c.expand(n_frames, 4, 4).clone(), h, w,
                          str(dataset.path))


def _array(arrays: dict, key: str, path: Path) -> np.ndarray:
    if key not in arrays:
        raise InputError(f"{path}: key {key!r} is missing; a camera file holds K, w2c, height and width")
    return np.asarray(arrays[key])


def camera_file(path: Path, n_frames: int, resolution: int) -> CameraSequence:
    """K (3,3)|(N,3,3), w2c (4,4)|(N,4,4), height, width from an npz, rescaled to `resolution`."""
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
    h, w = render_size(height, width, resolution)
    K_t = resize_intrinsics(torch.from_numpy(K).float(), (height, width), (h, w))
    return CameraSequence(
        "file", K_t.expand(n_frames, 3, 3).clone(), torch.from_numpy(w2c).float().expand(n_frames, 4, 4).clone(),
        h, w, str(path),
    )


def orbit_cameras(
    model: ModelArtifact, boxes: torch.Tensor, bone_transforms: torch.Tensor, resolution: int, revolutions: float,
    kind: str = "turntable",
) -> CameraSequence:
    """Turntable (revolutions > 0) or static front cameras around the union of (N, 2, 3) posed boxes.

    Up and front are the body's (the kind's body frame; bare skeletons count as SMPL-like, +Y up,
    facing +Z) turned by the first frame's root rotation, so azimuth 0 faces the subject's front
    whatever the capture's world axes are. K frames each frame's skinned occupied cells (the body
    itself, not its padded box), so the subject fills the image.
    """
    axes = torch.from_numpy(model.body_axes).float()
    root_rotation = bone_transforms[0, 0, :3, :3].float().cpu()
    up, front = root_rotation @ axes[:, 1], root_rotation @ axes[:, 2]
    n = boxes.shape[0]
    fit_points = None
    if bool(model.canonical_grid.occupied.any()):
        fit_points = skinned_cells(model, bone_transforms, FRAMING_POINTS).cpu()
    K, w2c = turntable_cameras(
        boxes[:, 0].amin(dim=0), boxes[:, 1].amax(dim=0), n, resolution, resolution,
        up=up, front=front, revolutions=revolutions, margin=FRAMING_MARGIN, fit_points=fit_points,
    )
    return CameraSequence(kind, K.expand(n, 3, 3).clone(), w2c, resolution, resolution, None)
