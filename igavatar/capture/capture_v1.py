"""Read and validate an igavatar capture v1 directory (DATA.md section 1d).

    capture = read_capture_v1(Path("runs/capture"))
    rgb = load_image(capture.image_path(capture.frames[0]))      # (H, W, 3) uint8 RGB

Everything a capture promises is checked once here, with errors that name the file, key and shape,
so the stages after it can trust what they get. `CaptureV1` is also what the importers of other
layouts (igavatar.capture.importers) return: the native format in memory, with each frame's image
and mask file wherever that layout keeps it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from igavatar.artifacts.manifest import first_schema_error
from igavatar.capture.arrays import bad_intrinsics, read_npz
from igavatar.errors import InputError

CAPTURE_FILE = "capture.json"

#: Per-body-model pose arrays in poses.npz: key -> shape with "N" = frames, other ints fixed,
#: letters free but consistent across keys.
POSE_LAYOUTS: dict[str, dict[str, tuple]] = {
    "anny": {"pose_parameters": ("N", 104, 4, 4), "phenotype_labels": ("P",), "phenotype_values": ("P",)},
    "smpl": {"betas": (10,), "global_orient": ("N", 3), "body_pose": ("N", 69), "transl": ("N", 3)},
    "skeleton": {"parents": ("J",), "rest_joints": ("J", 3), "rotvecs": ("N", "J", 3), "transl": ("N", 3)},
}
OPTIONAL_POSE_KEYS = {"skeleton": {"joint_names"}}


@dataclass(frozen=True)
class CaptureV1:
    """A validated capture v1 on disk. Arrays are numpy; cameras are expanded per frame.

    Attributes:
        root: the capture directory.
        meta: the parsed capture.json.
        frames: frame names (N).
        K: (N, 3, 3) intrinsics in pixels.
        w2c: (N, 4, 4) world-to-camera extrinsics.
        height, width: image size in pixels.
        dist: (5,) or (N, 5) OpenCV distortion coefficients, or None.
        poses: arrays of poses.npz, shapes per POSE_LAYOUTS.
        has_masks: whether there is one mask per frame.
        scans: frame -> path of the ground-truth posed mesh, for the frames that have one.
        image_files: frame -> image file (empty: images/<frame><image_ext>).
        mask_files: frame -> mask file (.png 0/255, .npy {0,1}, .tif/.tiff depth: > 0 is the
            subject); empty: masks/<frame>.png.
        source_files: the files besides images and masks the capture was read from (hashed into
            the dataset manifest); empty: capture.json, cameras.npz, poses.npz.
    """

    root: Path
    meta: dict
    frames: list[str]
    K: np.ndarray
    w2c: np.ndarray
    height: int
    width: int
    dist: np.ndarray | None
    poses: dict[str, np.ndarray]
    has_masks: bool
    scans: dict[str, Path] = field(default_factory=dict)
    image_files: dict[str, Path] = field(default_factory=dict)
    mask_files: dict[str, Path] = field(default_factory=dict)
    source_files: tuple[Path, ...] = ()

    @property
    def body_model(self) -> str:
        return self.meta["body_model"]

    @property
    def splits(self) -> dict[str, list[str]]:
        return self.meta["splits"]

    @property
    def input_format(self) -> str:
        """The layout it was read from: 'capture-v1' or an importer's name."""
        return self.meta.get("source_format", "capture-v1")

    def image_path(self, frame: str) -> Path:
        if frame in self.image_files:
            return self.image_files[frame]
        return self.root / "images" / f"{frame}{self.meta.get('image_ext', '.png')}"

    def mask_path(self, frame: str) -> Path:
        if frame in self.mask_files:
            return self.mask_files[frame]
        return self.root / "masks" / f"{frame}.png"

    def frame_dist(self, index: int) -> np.ndarray | None:
        """(5,) distortion coefficients of frame `index`, or None when the images are undistorted."""
        if self.dist is None:
            return None
        return self.dist if self.dist.ndim == 1 else self.dist[index]

    def input_files(self) -> list[Path]:
        """Every file the capture was read from: sources, then images, then masks."""
        sources = list(self.source_files) or [self.root / CAPTURE_FILE, self.root / "cameras.npz", self.root / "poses.npz"]
        paths = sources + [self.image_path(f) for f in self.frames]
        if self.has_masks:
            paths += [self.mask_path(f) for f in self.frames]
        return paths


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise InputError(f"{path}: missing; a capture v1 needs it (see DATA.md section 1d)")
    return read_npz(path)


def _image_ext_hint(image_dir: Path, frame: str, ext: str) -> str:
    """'; the images are .jpg: set "image_ext": ".jpg" in capture.json' when another suffix is there."""
    for other in (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG"):
        if other != ext and (image_dir / f"{frame}{other}").is_file():
            return f"; the images there are {other} files: set \"image_ext\": \"{other}\" in {CAPTURE_FILE}"
    return ""


def _at_frame(frames: list[str], bad: np.ndarray) -> str:
    """' at frame NAME (index i; k frames in all)' for the first frame whose entries of `bad` are set."""
    per_frame = np.asarray(bad).reshape(len(frames), -1).any(axis=1)
    first = int(np.argmax(per_frame))
    count = int(per_frame.sum())
    return f" at frame {frames[first]} (index {first}" + (f"; {count} frames in all)" if count > 1 else ")")


def _check_shape(path: Path, key: str, array: np.ndarray, expected: tuple, sizes: dict[str, int]) -> None:
    shape_text = "(" + ", ".join(str(e) for e in expected) + ")"
    if array.ndim != len(expected):
        raise InputError(f"{path}: key '{key}' has shape {tuple(array.shape)}, expected {shape_text}")
    for dim, want in zip(array.shape, expected):
        if isinstance(want, str):
            if sizes.setdefault(want, dim) != dim:
                raise InputError(
                    f"{path}: key '{key}' has shape {tuple(array.shape)}, expected {shape_text} "
                    f"with {want}={sizes[want]}"
                )
        elif dim != want:
            raise InputError(f"{path}: key '{key}' has shape {tuple(array.shape)}, expected {shape_text}")


def _per_frame(path: Path, key: str, array: np.ndarray, n_frames: int, tail: tuple[int, ...]) -> np.ndarray:
    """Expand a single (tail) array or check an (N, *tail) array."""
    array = np.asarray(array, dtype=np.float64)
    if array.shape == tail:
        return np.broadcast_to(array, (n_frames, *tail)).copy()
    if array.shape == (n_frames, *tail):
        return array
    raise InputError(
        f"{path}: key '{key}' has shape {tuple(array.shape)}, expected {tail} or ({n_frames}, {', '.join(map(str, tail))})"
    )


def read_capture_v1(root: Path) -> CaptureV1:
    """Read and validate a capture v1 directory; raise InputError naming the file/key on any problem."""
    root = Path(root)
    if not root.exists():
        raise InputError(f"{root}: no such capture directory (make one with `igavatar synth` or `igavatar preprocess --video CLIP`, or pass --capture)")
    if not root.is_dir():
        raise InputError(f"{root}: is a file, expected a capture directory holding {CAPTURE_FILE}")
    meta_path = root / CAPTURE_FILE
    if not meta_path.is_file():
        raise InputError(f"{meta_path}: missing; {root} is not an igavatar capture v1")
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{meta_path}: not valid JSON ({exc})") from exc
    if not isinstance(meta, dict):
        raise InputError(f"{meta_path}: expected a JSON object")
    if meta.get("format") != "igavatar-capture":
        raise InputError(
            f"{meta_path}: key 'format' is {meta.get('format')!r}, expected 'igavatar-capture' "
            "(other layouts are imported with --format)"
        )
    if meta.get("version") != 1:
        raise InputError(f"{meta_path}: key 'version' is {meta.get('version')!r}; this igavatar reads capture version 1")
    if meta.get("body_model") not in POSE_LAYOUTS:
        raise InputError(
            f"{meta_path}: unknown body model {meta.get('body_model')!r} in key 'body_model'; "
            f"expected one of {', '.join(POSE_LAYOUTS)}"
        )
    error = first_schema_error("capture", meta)
    if error is not None:
        raise InputError(f"{meta_path}: {error}")

    frames: list[str] = list(meta["frames"])
    frame_set = set(frames)
    for split, names in meta["splits"].items():
        unknown = [n for n in names if n not in frame_set]
        if unknown:
            raise InputError(f"{meta_path}: splits.{split} names frames not in 'frames': {unknown[:3]}")
    n_frames = len(frames)

    ext = meta.get("image_ext", ".png")
    missing_images = [f for f in frames if not (root / "images" / f"{f}{ext}").is_file()]
    if missing_images:
        raise InputError(
            f"{root / 'images'}: {len(missing_images)} of {n_frames} images missing, e.g. {missing_images[0]}{ext}"
            + _image_ext_hint(root / "images", missing_images[0], ext)
        )
    mask_dir = root / "masks"
    n_masks = sum((mask_dir / f"{f}.png").is_file() for f in frames) if mask_dir.is_dir() else 0
    if 0 < n_masks < n_frames:
        missing = next(f for f in frames if not (mask_dir / f"{f}.png").is_file())
        raise InputError(
            f"{mask_dir}: fewer masks ({n_masks}) than images ({n_frames}); e.g. {missing}.png is missing "
            "(give a mask for every frame, or none)"
        )

    cam_path = root / "cameras.npz"
    cams = _load_npz(cam_path)
    for key in ("K", "w2c", "height", "width"):
        if key not in cams:
            raise InputError(f"{cam_path}: key '{key}' missing (expected K, w2c, height, width, optional dist)")
    K = _per_frame(cam_path, "K", cams["K"], n_frames, (3, 3))
    w2c = _per_frame(cam_path, "w2c", cams["w2c"], n_frames, (4, 4))
    if not np.all(np.isfinite(w2c)):
        raise InputError(f"{cam_path}: key 'w2c' holds NaN or infinite values{_at_frame(frames, ~np.isfinite(w2c))}")
    bad_row = ~np.all(np.isclose(w2c[:, 3], [0, 0, 0, 1], atol=1e-6), axis=-1)
    if bad_row.any():
        raise InputError(f"{cam_path}: key 'w2c' last row must be [0, 0, 0, 1]{_at_frame(frames, bad_row)}")
    rot = w2c[:, :3, :3]
    not_rigid = ~np.all(np.isclose(rot @ rot.transpose(0, 2, 1), np.eye(3), atol=1e-4), axis=(-2, -1))
    if not_rigid.any():
        raise InputError(
            f"{cam_path}: key 'w2c' rotation block is not orthonormal (scale or shear: not a rigid camera)"
            f"{_at_frame(frames, not_rigid)}; w2c must be a rotation and a translation in meters"
        )
    height, width = int(np.asarray(cams["height"]).reshape(-1)[0]), int(np.asarray(cams["width"]).reshape(-1)[0])
    if height < 1 or width < 1:
        raise InputError(f"{cam_path}: height/width must be positive, got {height}x{width}")
    bad = bad_intrinsics(K, height, width)
    if bad is not None:
        raise InputError(f"{cam_path}: key 'K': {bad[1]}{_at_frame(frames, bad[0])}")
    dist = None
    if "dist" in cams:
        dist = np.asarray(cams["dist"], dtype=np.float64).reshape(-1)
        if dist.shape != (5,):
            raise InputError(f"{cam_path}: key 'dist' has shape {cams['dist'].shape}, expected (5,)")

    pose_path = root / "poses.npz"
    poses = _load_npz(pose_path)
    sizes: dict[str, int] = {"N": n_frames}
    layout = POSE_LAYOUTS[meta["body_model"]]
    for key, expected in layout.items():
        if key not in poses:
            raise InputError(
                f"{pose_path}: key '{key}' missing for body model '{meta['body_model']}' "
                f"(expected keys: {', '.join(layout)})"
            )
        _check_shape(pose_path, key, poses[key], expected, sizes)
        if poses[key].dtype.kind in "fc" and not np.all(np.isfinite(poses[key])):
            per_frame = poses[key].ndim >= 1 and poses[key].shape[0] == n_frames and expected[0] == "N"
            where = _at_frame(frames, ~np.isfinite(poses[key])) if per_frame else ""
            raise InputError(f"{pose_path}: key '{key}' holds NaN or infinite values{where}")
    allowed = set(layout) | OPTIONAL_POSE_KEYS.get(meta["body_model"], set())
    extra = sorted(set(poses) - allowed)
    if extra:
        raise InputError(f"{pose_path}: unexpected keys {extra} for body model '{meta['body_model']}'")

    scans = {}
    scan_dir = root / "scans"
    if scan_dir.is_dir():
        for frame in frames:
            for suffix in (".ply", ".obj"):
                if (scan_dir / f"{frame}{suffix}").is_file():
                    scans[frame] = scan_dir / f"{frame}{suffix}"
                    break

    return CaptureV1(
        root=root, meta=meta, frames=frames, K=K, w2c=w2c, height=height, width=width, dist=dist,
        poses=poses, has_masks=n_masks == n_frames, scans=scans,
    )


def load_image(path: Path, expected_hw: tuple[int, int] | None = None) -> np.ndarray:
    """Read an 8-bit image as RGB (H, W, 3) uint8; InputError if it is not an image or has the wrong size."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise InputError(f"{path}: not a readable image (PNG/JPEG expected)")
    if expected_hw is not None and image.shape[:2] != tuple(expected_hw):
        raise InputError(
            f"{path}: image is {image.shape[1]}x{image.shape[0]}, but cameras.npz says {expected_hw[1]}x{expected_hw[0]}"
        )
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def load_mask(path: Path, expected_hw: tuple[int, int] | None = None) -> np.ndarray:
    """Read a mask as (H, W) bool.

    By suffix: .png/.jpg 0 background, >0 foreground (1 or 3 channels); .npy an (H, W) array,
    nonzero foreground (PeopleSnapshot); .tif/.tiff a depth render, subject where depth > 0,
    finite and nearer than a far-plane background (X-Humans).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        try:
            mask = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise InputError(f"{path}: not a readable .npy mask ({exc})") from exc
        if mask.ndim == 3 and mask.shape[-1] in (1, 3):
            mask = mask.max(axis=-1)
        if mask.ndim != 2:
            raise InputError(f"{path}: mask array has shape {mask.shape}, expected (H, W)")
        if expected_hw is not None and mask.shape != tuple(expected_hw):
            raise InputError(f"{path}: mask is {mask.shape[1]}x{mask.shape[0]}, expected {expected_hw[1]}x{expected_hw[0]}")
        return mask > 0
    if suffix in (".tif", ".tiff"):
        depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
        if depth is None:
            raise InputError(f"{path}: not a readable depth image (TIFF) to derive the mask from")
        if depth.ndim == 3:
            depth = depth[..., 0]
        if expected_hw is not None and depth.shape[:2] != tuple(expected_hw):
            raise InputError(f"{path}: depth is {depth.shape[1]}x{depth.shape[0]}, expected {expected_hw[1]}x{expected_hw[0]}")
        depth = depth.astype(np.float64)
        subject = np.isfinite(depth) & (depth > 0)
        if subject.any():
            # Renderers clear the depth buffer to the far plane (aitviewer, which rendered X-Humans,
            # writes eye-space z with the background at the far distance): pixels at the maximum,
            # when it stands well apart from every other depth, are background, not subject.
            far = depth[subject].max()
            at_far = subject & (depth >= far * (1.0 - 1e-6))
            nearer = depth[subject & ~at_far]
            if nearer.size and far > 1.5 * nearer.max():
                subject &= ~at_far
        return subject
    mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if mask is None:
        raise InputError(f"{path}: not a readable mask image (PNG, 0 background / 255 foreground)")
    if mask.ndim == 3:
        mask = mask[..., :3].max(axis=-1)
    if expected_hw is not None and mask.shape[:2] != tuple(expected_hw):
        raise InputError(f"{path}: mask is {mask.shape[1]}x{mask.shape[0]}, expected {expected_hw[1]}x{expected_hw[0]}")
    return mask > 127 if mask.dtype == np.uint8 and mask.max() > 1 else mask > 0
