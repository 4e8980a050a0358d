"""Build a validated in-memory capture v1 from what an importer read from another layout.

    capture = assemble_capture(CaptureParts(root, "peoplesnapshot", "smpl", frames, splits, K, w2c,
                                            height, width, poses, image_files, mask_files, source_files))

Importers check their own files (naming the file, key and shape that is wrong); this module then
checks the result once more against the promises of capture v1 (DATA.md section 1d: the capture
schema, per-frame cameras, the body model's pose layout, every image and mask present), so that
every stage after `preprocess` treats an imported capture exactly like a native one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from igavatar.artifacts.manifest import first_schema_error
from igavatar.capture.arrays import bad_intrinsics
from igavatar.capture.capture_v1 import POSE_LAYOUTS, CaptureV1, _at_frame, _check_shape
from igavatar.errors import InputError


@dataclass(frozen=True)
class CaptureParts:
    """What an importer read, in capture v1 terms (numpy arrays, float64).

    Attributes:
        root: the directory the capture was read from.
        source_format: the importer's name (recorded as meta 'source_format').
        body_model: 'anny', 'smpl' or 'skeleton'.
        frames: N frame names (unique, [A-Za-z0-9_.-]).
        splits: split name -> frame names; 'train' required and non-empty.
        K: (N, 3, 3) intrinsics in pixels. w2c: (N, 4, 4) world-to-camera.
        height, width: image size in pixels.
        poses: arrays in the capture v1 layout of `body_model` (POSE_LAYOUTS).
        image_files: frame -> image file, one per frame.
        mask_files: frame -> mask file, one per frame, or empty (masks are then estimated).
        source_files: the other files read (hashed into the dataset manifest), at least one.
        scans: frame -> ground-truth posed mesh (world coordinates), for the frames that have one.
        subject: JSON-able facts about the subject (gender, ...), recorded in the capture meta.
        dist: (5,) or (N, 5) OpenCV distortion coefficients, or None for undistorted images.
    """

    root: Path
    source_format: str
    body_model: str
    frames: list[str]
    splits: dict[str, list[str]]
    K: np.ndarray
    w2c: np.ndarray
    height: int
    width: int
    poses: dict[str, np.ndarray]
    image_files: dict[str, Path]
    mask_files: dict[str, Path]
    source_files: Sequence[Path]
    scans: dict[str, Path] = field(default_factory=dict)
    subject: dict = field(default_factory=dict)
    dist: np.ndarray | None = None


def assemble_capture(parts: CaptureParts) -> CaptureV1:
    """Validate `parts` as a capture v1 and return it; InputError naming the root and the problem."""
    where = f"{parts.root} ({parts.source_format})"
    meta = {
        "format": "igavatar-capture", "version": 1, "body_model": parts.body_model,
        "frames": list(parts.frames), "splits": {k: list(v) for k, v in parts.splits.items()},
        "source_format": parts.source_format,
    }
    if parts.subject:
        meta["subject"] = dict(parts.subject)
    error = first_schema_error("capture", meta)
    if error is not None:
        raise InputError(f"{where}: the imported capture is not valid capture v1: {error}")
    frames = meta["frames"]
    known = set(frames)
    for split, names in meta["splits"].items():
        unknown = [n for n in names if n not in known]
        if unknown:
            raise InputError(f"{where}: split '{split}' names frames that were not imported: {unknown[:3]}")

    n_frames = len(frames)
    K = np.asarray(parts.K, dtype=np.float64)
    w2c = np.asarray(parts.w2c, dtype=np.float64)
    if K.shape != (n_frames, 3, 3) or w2c.shape != (n_frames, 4, 4):
        raise InputError(
            f"{where}: cameras have K {K.shape} and w2c {w2c.shape}, expected ({n_frames}, 3, 3) and ({n_frames}, 4, 4)"
        )
    if not np.all(np.isfinite(w2c)):
        raise InputError(f"{where}: camera extrinsics hold NaN or infinite values")
    bad = bad_intrinsics(K, parts.height, parts.width)
    if bad is not None:
        raise InputError(f"{where}: {bad[1]}{_at_frame(frames, bad[0])}")
    if not np.allclose(w2c[:, 3], [0, 0, 0, 1], atol=1e-6):
        raise InputError(f"{where}: a world-to-camera matrix whose last row is not [0, 0, 0, 1]")
    rotations = w2c[:, :3, :3]
    if not np.allclose(rotations @ rotations.transpose(0, 2, 1), np.eye(3), atol=1e-4):
        raise InputError(f"{where}: a world-to-camera rotation block is not orthonormal")
    if parts.height < 1 or parts.width < 1:
        raise InputError(f"{where}: image size {parts.width}x{parts.height} is not positive")
    dist = None if parts.dist is None else np.asarray(parts.dist, dtype=np.float64)
    if dist is not None and dist.shape not in ((5,), (n_frames, 5)):
        raise InputError(f"{where}: distortion coefficients have shape {dist.shape}, expected (5,) or ({n_frames}, 5)")

    layout = POSE_LAYOUTS[parts.body_model]
    poses = {key: np.asarray(value) for key, value in parts.poses.items()}
    sizes: dict[str, int] = {"N": n_frames}
    for key, expected in layout.items():
        if key not in poses:
            raise InputError(f"{where}: pose array '{key}' missing for body model '{parts.body_model}'")
        _check_shape(Path(where), key, poses[key], expected, sizes)
        if poses[key].dtype.kind in "fc" and not np.all(np.isfinite(poses[key])):
            raise InputError(f"{where}: pose array '{key}' holds NaN or infinite values")

    _check_files(where, "image", frames, parts.image_files, required=True)
    _check_files(where, "mask", frames, parts.mask_files, required=False)
    sources = tuple(Path(p) for p in parts.source_files)
    if not sources:
        raise InputError(f"{where}: the importer recorded no source files")
    missing = [p for p in sources if not p.is_file()]
    if missing:
        raise InputError(f"{missing[0]}: missing")
    return CaptureV1(
        root=Path(parts.root), meta=meta, frames=frames, K=K, w2c=w2c, height=int(parts.height),
        width=int(parts.width), dist=dist, poses=poses, has_masks=bool(parts.mask_files),
        scans={f: Path(p) for f, p in parts.scans.items() if f in known},
        image_files={f: Path(parts.image_files[f]) for f in frames},
        mask_files={f: Path(parts.mask_files[f]) for f in frames} if parts.mask_files else {},
        source_files=sources,
    )


def _check_files(where: str, kind: str, frames: list[str], files: dict[str, Path], required: bool) -> None:
    """One existing file per frame (or none at all when not required)."""
    if not files and not required:
        return
    without = [f for f in frames if f not in files]
    if without:
        raise InputError(f"{where}: no {kind} for {len(without)} of {len(frames)} frames, e.g. '{without[0]}'")
    absent = [files[f] for f in frames if not Path(files[f]).is_file()]
    if absent:
        raise InputError(f"{absent[0]}: missing ({len(absent)} {kind} file(s) of {len(frames)} frames are)")
