"""Import the HumanNeRF / ZJU-MoCap monocular layout (DATA.md section 1c) as a skeleton capture.

    if detect_humannerf(root): capture = read_humannerf(root)     # CaptureV1, body model 'skeleton'

Layout: images/<frame>.png (raw, distorted), masks/<frame>.png (0/255, maybe 3-channel),
cameras.pkl {frame: {intrinsics (3,3), extrinsics (4,4) w2c, distortions (5,)}},
mesh_infos.pkl {frame: {Rh (3,), Th (3,), poses (72,), joints (24,3), tpose_joints (24,3)}},
canonical_joints.pkl {joints (24,3)} (optional here).

The SMPL betas are not stored, but the rest joints are, so the SMPL *skeleton* is known without
the SMPL model file: the capture uses the 'skeleton' body model on SMPL's tree. Conventions:
  - world = R(Rh) X + Th, with X the SMPL model-space point posed by `poses` (the root entry is
    usually zero: the global rotation lives in Rh). igavatar's forward kinematics rotates the root
    about the root joint, so the root rotation is R(Rh) R(poses[:3]) and the translation is
    t = R(Rh) tpose_joints[0] + Th - rest_joints[0]; the posed joints are checked against
    R(Rh) joints + Th (JOINT_TOLERANCE_M).
  - rest joints: canonical_joints.pkl when present (HumanNeRF's canonical skeleton, the T-pose of
    the mean shape), else the mean of the frames' tpose_joints (the same thing: SMPL's rest joints
    are linear in the shape).
  - splits: HumanNeRF has none for one camera; the last TEST_FRACTION of the frames (later poses)
    are the test split, the rest train (every frame trains when there are fewer than 5).
  - distortion: kept per frame; preprocess undistorts images and masks with it.
Pickles are read by igavatar.capture.pickles (plain numpy arrays only, nothing executed), and
every value's type and shape is checked before use.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import torch

from igavatar.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from igavatar.body.skeleton import SMPL_JOINT_NAMES, SMPL_PARENTS, forward_kinematics
from igavatar.capture.arrays import array_of
from igavatar.capture.assemble import CaptureParts, assemble_capture
from igavatar.capture.capture_v1 import CaptureV1
from igavatar.capture.pickles import load_array_pickle
from igavatar.errors import InputError

CAMERAS, MESH_INFOS, CANONICAL_JOINTS = "cameras.pkl", "mesh_infos.pkl", "canonical_joints.pkl"
TEST_FRACTION = 0.2
#: Largest allowed distance (m) between igavatar's posed joints and mesh_infos' world joints:
#: the per-frame shapes differ a little from the mean one; a wrong convention is off by decimeters.
JOINT_TOLERANCE_M = 0.03
_NUM_JOINTS = len(SMPL_PARENTS)
_FRAME_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")


def detect_humannerf(root: Path) -> bool:
    """Whether `root` looks like a HumanNeRF subject (its two pickles are there)."""
    return (root / CAMERAS).is_file() and (root / MESH_INFOS).is_file()


def _dict_of_dicts(path: Path, data: object) -> dict[str, dict]:
    """A {frame name: dict} pickle, type-checked."""
    if not isinstance(data, dict) or not data:
        raise InputError(
            f"{path}: holds a {type(data).__name__}{' (empty)' if isinstance(data, dict) else ''}, "
            "expected a non-empty dict {frame name: {...}}"
        )
    for frame, value in data.items():
        if not isinstance(frame, str) or not _FRAME_NAME.match(frame):
            raise InputError(f"{path}: frame key {frame!r} is not a frame name (letters, digits, _ . -)")
        if not isinstance(value, dict):
            raise InputError(f"{path}: frame '{frame}' holds a {type(value).__name__}, expected a dict")
    return data


def _frame_array(path: Path, frame: str, entry: dict, key: str, *shapes: tuple) -> np.ndarray:
    """entry[key] checked (InputError naming the file, the frame and the key)."""
    return array_of(Path(f"{path} [frame '{frame}']"), entry, key, *shapes)


def _cameras(path: Path, frames: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """K (N, 3, 3), w2c (N, 4, 4), dist (N, 5) or None when no frame has distortion."""
    cameras = _dict_of_dicts(path, load_array_pickle(path))
    missing = [f for f in frames if f not in cameras]
    if missing:
        raise InputError(f"{path}: no camera for {len(missing)} frame(s) of {MESH_INFOS}, e.g. '{missing[0]}'")
    K, w2c, dist = [], [], []
    for frame in frames:
        entry = cameras[frame]
        K.append(_frame_array(path, frame, entry, "intrinsics", (3, 3)))
        w2c.append(_frame_array(path, frame, entry, "extrinsics", (4, 4)))
        if "distortions" in entry:  # ZJU stores (5, 1); wild captures have none
            dist.append(_frame_array(path, frame, entry, "distortions", (5,), (5, 1), (1, 5)).reshape(5))
        else:
            dist.append(np.zeros(5))
    dist_array = np.stack(dist)
    return np.stack(K), np.stack(w2c), (dist_array if np.any(dist_array) else None)


def _rest_joints(root: Path, tpose: np.ndarray) -> np.ndarray:
    path = root / CANONICAL_JOINTS
    if not path.is_file():
        return tpose.mean(axis=0)
    data = load_array_pickle(path)
    if not isinstance(data, dict):
        raise InputError(f"{path}: holds a {type(data).__name__}, expected a dict {{'joints': (24, 3) array}}")
    return array_of(path, data, "joints", (_NUM_JOINTS, 3))


def _skeleton_poses(path: Path, rest: np.ndarray, mesh: dict[str, dict[str, np.ndarray]], frames: list[str]) -> dict[str, np.ndarray]:
    """Capture v1 'skeleton' poses from Rh, Th, poses and tpose_joints; checked against joints."""
    stack = {key: torch.as_tensor(np.stack([mesh[f][key] for f in frames])) for key in mesh[frames[0]]}
    rotations = axis_angle_to_matrix(stack["poses"].reshape(-1, _NUM_JOINTS, 3))
    global_rotation = axis_angle_to_matrix(stack["Rh"])  # (N, 3, 3)
    rotations[:, 0] = global_rotation @ rotations[:, 0]
    rest_t = torch.as_tensor(rest)
    # world = Rh X + Th and X's root sits at the frame's own tpose root; FK puts it at rest[0] + t.
    transl = (global_rotation @ stack["tpose_joints"][:, 0, :, None])[..., 0] + stack["Th"] - rest_t[0]
    posed = forward_kinematics(rotations, rest_t, SMPL_PARENTS, transl)[..., :3, 3]
    expected = (global_rotation[:, None] @ stack["joints"][..., None])[..., 0] + stack["Th"][:, None]
    error = (posed - expected).norm(dim=-1)  # (N, J)
    worst = int(error.max(dim=1).values.argmax())
    if float(error[worst].max()) > JOINT_TOLERANCE_M:
        joint = SMPL_JOINT_NAMES[int(error[worst].argmax())]
        raise InputError(
            f"{path}: frame '{frames[worst]}': SMPL's kinematic tree posed by 'poses', 'Rh', 'Th' and "
            f"'tpose_joints' puts joint '{joint}' {float(error[worst].max()):.3f} m from R(Rh) joints + Th "
            f"(tolerance {JOINT_TOLERANCE_M} m); expected HumanNeRF's convention world = R(Rh) X_smpl(poses) + Th"
        )
    return {
        "parents": np.array(SMPL_PARENTS, dtype=np.int64),
        "rest_joints": rest,
        "rotvecs": matrix_to_axis_angle(rotations).numpy(),
        "transl": transl.numpy(),
        "joint_names": np.array(SMPL_JOINT_NAMES, dtype=np.str_),
    }


def _mesh_infos(path: Path) -> tuple[list[str], dict[str, dict[str, np.ndarray]]]:
    """Sorted frame names and each frame's checked arrays (float64)."""
    raw = _dict_of_dicts(path, load_array_pickle(path))
    frames = sorted(raw)
    shapes = {
        "Rh": [(3,), (1, 3)], "Th": [(3,), (1, 3)], "poses": [(_NUM_JOINTS * 3,), (1, _NUM_JOINTS * 3)],
        "joints": [(_NUM_JOINTS, 3)], "tpose_joints": [(_NUM_JOINTS, 3)],
    }
    mesh = {}
    for frame in frames:
        mesh[frame] = {
            key: _frame_array(path, frame, raw[frame], key, *allowed).reshape(allowed[0])
            for key, allowed in shapes.items()
        }
    return frames, mesh


def _image_size(path: Path) -> tuple[int, int]:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"{path}: not a readable image (PNG/JPEG expected)")
    return int(image.shape[0]), int(image.shape[1])


def _frame_files(root: Path, folder: str, frames: list[str]) -> dict[str, Path]:
    files = {}
    for frame in frames:
        matches = [root / folder / f"{frame}{ext}" for ext in (".png", ".jpg", ".jpeg")]
        found = next((p for p in matches if p.is_file()), None)
        if found is None:
            raise InputError(f"{root / folder}: no file for frame '{frame}' (expected {frame}.png)")
        files[frame] = found
    return files


def humannerf_splits(frames: list[str]) -> dict[str, list[str]]:
    """The last TEST_FRACTION of the frames test (later, unseen poses), the rest train; every
    frame trains when there are fewer than 5."""
    n_test = int(round(TEST_FRACTION * len(frames))) if len(frames) >= 5 else 0
    return {"train": frames[: len(frames) - n_test], "test": frames[len(frames) - n_test :]}


def read_humannerf(root: Path) -> CaptureV1:
    """Read a HumanNeRF subject directory as a capture with body model 'skeleton' (SMPL's tree).

    Raises:
        InputError: a missing file, a pickle of another structure, a key or shape that is wrong
            (naming the file, the frame and the key), or joints that disagree with the poses (a
            different convention).
    """
    root = Path(root)
    mesh_path, camera_path = root / MESH_INFOS, root / CAMERAS
    for path in (mesh_path, camera_path):
        if not path.is_file():
            raise InputError(f"{path}: missing; a HumanNeRF subject has {CAMERAS} and {MESH_INFOS}")
    frames, mesh = _mesh_infos(mesh_path)
    K, w2c, dist = _cameras(camera_path, frames)
    rest = _rest_joints(root, np.stack([mesh[f]["tpose_joints"] for f in frames]))
    poses = _skeleton_poses(mesh_path, rest, mesh, frames)

    images = _frame_files(root, "images", frames)
    masks = _frame_files(root, "masks", frames)
    height, width = _image_size(images[frames[0]])
    sources = [camera_path, mesh_path] + ([root / CANONICAL_JOINTS] if (root / CANONICAL_JOINTS).is_file() else [])
    return assemble_capture(CaptureParts(
        root=root, source_format="humannerf", body_model="skeleton", frames=frames,
        splits=humannerf_splits(frames), K=K, w2c=w2c, height=height, width=width, poses=poses,
        image_files=images, mask_files=masks, source_files=sources,
        subject={"skeleton": "smpl", "source": "HumanNeRF / ZJU-MoCap"}, dist=dist,
    ))
