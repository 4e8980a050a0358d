"""SMPL poses that a GPU pose estimator wrote for a clip (WHAM, TRAM), read for `preprocess --video --poses-from`.

    poses = read_estimator_poses(Path("output/demo/clip/wham_output.pkl"))      # or results/clip/hps/hps_track_0.npy
    poses.source_frames        # (F,) indices of the clip's frames the estimate covers
    poses.global_orient        # (F, 3) axis-angle, in the camera frame (x right, y down, z forward)

Both tools estimate SMPL (24 joints, 10 betas) per frame in the camera's frame, which is what an
avatar needs (the body relative to the camera that filmed it); their world frames (SLAM, gravity)
are not used:
- WHAM (`demo.py --save_pkl`): `wham_output.pkl`, written by joblib: {track id: {'pose' (F, 72)
  camera-frame axis-angles, 'trans' (F, 3) SMPL transl in the camera frame, 'betas' (F, 10),
  'frame_ids' (F,), ...}}. No intrinsics are saved: WHAM assumes a focal length of the image
  diagonal in pixels and the principal point at the image centre, unless run with --calib.
- TRAM (`scripts/estimate_humans.py`): `hps/hps_track_K.npy`, a saved dict of torch tensors:
  'pred_rotmat' (F, 24, 3, 3), 'pred_trans' (F, 1, 3) camera-frame transl, 'pred_shape' (F, 10),
  'frame' (F,), 'img_focal', 'img_center'.
The betas are averaged over the clip (one body), as both tools' own viewers do.

GVHMR writes SMPL-X parameters (21 body joints, SMPL-X shape space). igavatar has no SMPL-X body
model, and SMPL-X betas mean nothing to SMPL, so such a file is refused with a line that says so.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from igavatar.body.rotations import matrix_to_axis_angle
from igavatar.capture.pickles import load_array_pickle, load_joblib_pickle
from igavatar.errors import InputError

ESTIMATORS = ("wham", "tram")


@dataclass(frozen=True)
class EstimatorPoses:
    """One person's SMPL estimate over a clip, in the camera frame of the source video.

    Attributes:
        estimator: 'wham' or 'tram'; path: the file read; track: the person's track in it, of `tracks`.
        source_frames: (F,) int indices of the source video's frames, increasing.
        global_orient: (F, 3), body_pose: (F, 69) axis-angles; transl: (F, 3) meters (smplx's transl),
            all in the camera frame (OpenCV: x right, y down, z forward).
        betas: (10,) the clip's body shape.
        focal_px: focal length in pixels of the source frames, or None (the tool saved none).
        center_px: (2,) principal point (x, y) in source pixels, or None.
    """

    estimator: str
    path: Path
    track: str
    tracks: int
    source_frames: np.ndarray
    global_orient: np.ndarray
    body_pose: np.ndarray
    transl: np.ndarray
    betas: np.ndarray
    focal_px: float | None
    center_px: np.ndarray | None


def _numpy(value) -> np.ndarray:
    """A numpy array of a numpy array, torch tensor or number."""
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    return np.asarray(value)


def _array(path: Path, data: dict, key: str, shape: tuple, where: str = "") -> np.ndarray:
    """data[key] as float64 with `shape` (None = any size; the same None must agree in the caller)."""
    if key not in data:
        raise InputError(f"{path}: {where}no key '{key}' (keys: {', '.join(sorted(map(str, data)))}); "
                         "is this the estimator's own result file?")
    array = _numpy(data[key]).astype(np.float64)
    if array.ndim != len(shape) or any(e is not None and e != a for e, a in zip(shape, array.shape)):
        wanted = "(" + ", ".join("N" if e is None else str(e) for e in shape) + ")"
        raise InputError(f"{path}: {where}key '{key}' has shape {tuple(array.shape)}, expected {wanted}")
    return array


def _frames(path: Path, data: dict, key: str, count: int, where: str = "") -> np.ndarray:
    frames = _numpy(data.get(key, np.arange(count))).reshape(-1)
    if frames.shape != (count,) or not np.all(np.diff(frames) > 0) or frames.min(initial=0) < 0:
        raise InputError(f"{path}: {where}key '{key}' must hold {count} increasing frame indices, one per row")
    return frames.astype(np.int64)


def _betas(path: Path, betas: np.ndarray) -> np.ndarray:
    if betas.ndim == 2:
        betas = betas.mean(axis=0)
    if betas.shape[-1] < 10:
        raise InputError(f"{path}: {betas.shape[-1]} betas, expected SMPL's 10")
    return betas[:10]


def _smplx_refusal(path: Path) -> InputError:
    return InputError(
        f"{path}: holds SMPL-X parameters (body_pose of 63 values, as GVHMR writes); igavatar poses SMPL "
        "(72 values) and has no SMPL-X body, whose shape space SMPL cannot use. Run WHAM or TRAM, or "
        "preprocess the clip with --video alone (igavatar's own fit)")


def _read_wham(path: Path) -> EstimatorPoses:
    results = load_joblib_pickle(path)
    if not isinstance(results, dict) or not results or not all(isinstance(v, dict) for v in results.values()):
        raise InputError(f"{path}: expected WHAM's results, a dict of tracks (each a dict with pose, trans, betas, frame_ids)")
    # WHAM keeps every tracked person; a passer-by's track is short. The clip's person is the longest.
    track = max(results, key=lambda k: len(_numpy(results[k].get("frame_ids", []))))
    data, where = results[track], f"track {track}: "
    if "pose" in data and _numpy(data["pose"]).shape[-1] == 66:
        raise _smplx_refusal(path)
    pose = _array(path, data, "pose", (None, 72), where)
    count = pose.shape[0]
    return EstimatorPoses(
        estimator="wham", path=path, track=str(track), tracks=len(results),
        source_frames=_frames(path, data, "frame_ids", count, where),
        global_orient=pose[:, :3], body_pose=pose[:, 3:], transl=_array(path, data, "trans", (count, 3), where),
        betas=_betas(path, _array(path, data, "betas", (count, None), where)), focal_px=None, center_px=None)


def _read_tram(path: Path) -> EstimatorPoses:
    data = load_array_pickle(path, torch_tensors=True)
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected TRAM's saved dict (pred_rotmat, pred_trans, pred_shape, frame)")
    rotmat = _array(path, data, "pred_rotmat", (None, 24, 3, 3))
    count = rotmat.shape[0]
    rotvecs = matrix_to_axis_angle(torch.as_tensor(rotmat)).numpy()
    focal = float(_numpy(data["img_focal"]).reshape(-1)[0]) if "img_focal" in data else None
    center = _numpy(data["img_center"]).astype(np.float64).reshape(-1)[:2] if "img_center" in data else None
    tracks = len(list(path.parent.glob("hps_track_*.npy"))) or 1
    return EstimatorPoses(
        estimator="tram", path=path, track=path.stem.removeprefix("hps_track_"), tracks=tracks,
        source_frames=_frames(path, data, "frame", count),
        global_orient=rotvecs[:, 0], body_pose=rotvecs[:, 1:].reshape(count, 69),
        transl=_array(path, data, "pred_trans", (count, 1, 3)).reshape(count, 3),
        betas=_betas(path, _array(path, data, "pred_shape", (count, None))), focal_px=focal, center_px=center)


def detect_estimator(path: Path) -> str:
    """'wham' for a .pkl, 'tram' for a .npy; an InputError for GVHMR's and other files."""
    suffix = path.suffix.lower()
    if suffix == ".pkl":
        return "wham"
    if suffix == ".npy":
        return "tram"
    if suffix in (".pt", ".npz"):
        raise _smplx_refusal(path)
    raise InputError(f"{path}: not a pose estimator's result file igavatar reads; expected WHAM's wham_output.pkl "
                     "or TRAM's hps/hps_track_K.npy")


def read_estimator_poses(path: Path) -> EstimatorPoses:
    """The SMPL estimate in `path` (WHAM's .pkl or TRAM's .npy; see the module docstring).

    Raises:
        InputError: a missing or unreadable file, a foreign layout (naming the key and shape),
            or GVHMR's SMPL-X parameters.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"--poses-from {path}: no such file")
    estimator = detect_estimator(path)
    poses = _read_wham(path) if estimator == "wham" else _read_tram(path)
    if not (np.isfinite(poses.body_pose).all() and np.isfinite(poses.transl).all()):
        raise InputError(f"{path}: the estimate holds NaN or infinite values")
    return poses
