"""Import an X-Humans subject (DATA.md section 1b) as an SMPL capture v1 with ground-truth scans.

    if detect_xhumans(root): capture = read_xhumans(root)     # a validated CaptureV1, capture.scans

Layout (per subject, e.g. 00036/):
    gender.txt, mean_shape_smpl.npy (10,)
    {train,test}/TakeN/render/image/color_000011.png       RGB renders, 800x1200 (W x H)
    {train,test}/TakeN/render/depth/depth_000011.tiff      float depth; the subject where it is
                                                           nearer than the far plane (mask)
    {train,test}/TakeN/render/cameras.npz                  intrinsic (3,3), extrinsic (M,4,4) w2c,
                                                           row i for the i-th image in sorted order
    {train,test}/TakeN/SMPL/mesh-f00011_smpl.pkl           global_orient (3,), body_pose (69,),
                                                           transl (3,), betas (10,) (ignored)
    {train,test}/TakeN/meshes_pkl/mesh-f00011.pkl          the scan: vertices (V,3), faces (F,3), ...
Image color_<n> pairs with depth_<n>, the SMPL file and the scan of frame number n.

What is imported by default: the first training take (lowest take number) for the train split,
the way the paper trains on one to two takes (150-300 frames), and every test take for the test
split; every frame of those takes. Frames are named '<split>-<take>-<n:06d>'. The body shape is
mean_shape_smpl.npy (the per-frame betas of the SMPL files are fits of the same body and are
ignored). The per-frame scans become `capture.scans`, which `igavatar eval` reads (see
`read_xhumans_scan`). The SMPL fits are gendered (gender.txt, recorded in the capture's subject);
pass the matching SMPL model file to preprocess for the closest body.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from igavatar.capture.arrays import array_of, read_npy, read_npz
from igavatar.capture.assemble import CaptureParts, assemble_capture
from igavatar.capture.capture_v1 import CAPTURE_FILE, CaptureV1
from igavatar.capture.pickles import load_array_pickle
from igavatar.errors import InputError

NAME = "xhumans"
_TAKE = re.compile(r"^Take(\d+)$")
_COLOR = re.compile(r"^color_(\d+)$")


def detect_xhumans(root: Path) -> bool:
    """mean_shape_smpl.npy and a train/ or test/ folder, and no capture.json."""
    return (
        not (root / CAPTURE_FILE).is_file()
        and (root / "mean_shape_smpl.npy").is_file()
        and ((root / "train").is_dir() or (root / "test").is_dir())
    )


def _takes(root: Path, split: str) -> list[Path]:
    """TakeN folders of `split`, by take number."""
    folder = root / split
    if not folder.is_dir():
        return []
    takes = [p for p in folder.iterdir() if p.is_dir() and _TAKE.match(p.name)]
    return sorted(takes, key=lambda p: int(_TAKE.match(p.name).group(1)))


def _params_of(path: Path) -> dict[str, np.ndarray]:
    """global_orient (3,), body_pose (69,), transl (3,) of one SMPL parameter pickle."""
    params = load_array_pickle(path)
    if not isinstance(params, dict):
        raise InputError(
            f"{path}: holds a {type(params).__name__}, expected a dict with global_orient, body_pose, transl "
            "(an X-Humans SMPL/mesh-f*_smpl.pkl)"
        )
    return {
        "global_orient": array_of(path, params, "global_orient", (3,), (1, 3)).reshape(3),
        "body_pose": array_of(path, params, "body_pose", (69,), (1, 69)).reshape(69),
        "transl": array_of(path, params, "transl", (3,), (1, 3)).reshape(3),
    }


def read_xhumans_scan(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64 meters and faces (F, 3) int64 of an X-Humans meshes_pkl/mesh-f*.pkl."""
    mesh = load_array_pickle(path)
    if not isinstance(mesh, dict):
        raise InputError(f"{path}: holds a {type(mesh).__name__}, expected a dict with vertices and faces (a scan)")
    vertices = array_of(path, mesh, "vertices", (None, 3))
    faces = array_of(path, mesh, "faces", (None, 3))
    if not np.all(faces == np.round(faces)):
        raise InputError(f"{path}: key 'faces' holds non-integer vertex indices")
    faces = faces.astype(np.int64)
    if faces.min() < 0 or faces.max() >= vertices.shape[0]:
        raise InputError(f"{path}: key 'faces' indexes vertices outside [0, {vertices.shape[0] - 1}]")
    return vertices, faces


@dataclass
class _Take:
    """The frames of one take, in image order."""

    names: list[str]
    K: np.ndarray  # (3, 3)
    w2c: np.ndarray  # (M, 4, 4)
    images: list[Path]
    depths: list[Path]
    params: list[dict[str, np.ndarray]]
    param_files: list[Path]
    scans: list[Path | None]
    size_hw: tuple[int, int]
    camera_file: Path


def _read_take(take: Path, split: str) -> _Take:
    render = take / "render"
    image_dir = render / "image"
    numbered = []
    for path in image_dir.glob("color_*.png") if image_dir.is_dir() else []:
        match = _COLOR.match(path.stem)
        if match:
            numbered.append((int(match.group(1)), path))
    if not numbered:
        raise InputError(f"{image_dir}: no color_XXXXXX.png renders")
    numbered.sort()
    camera_file = render / "cameras.npz"
    cameras = read_npz(camera_file)
    K = array_of(camera_file, cameras, "intrinsic", (3, 3))
    w2c = array_of(camera_file, cameras, "extrinsic", (None, 4, 4), (None, 3, 4))
    if w2c.shape[1] == 3:
        w2c = np.concatenate((w2c, np.broadcast_to([0.0, 0.0, 0.0, 1.0], (w2c.shape[0], 1, 4))), axis=1)
    if w2c.shape[0] != len(numbered):
        raise InputError(
            f"{camera_file}: key 'extrinsic' has shape {(w2c.shape[0], 4, 4)}, expected ({len(numbered)}, 4, 4): "
            f"one camera per render in {image_dir}"
        )
    first = cv2.imread(str(numbered[0][1]), cv2.IMREAD_UNCHANGED)
    if first is None:
        raise InputError(f"{numbered[0][1]}: not a readable image")
    depths, params, param_files, scans = [], [], [], []
    for number, _ in numbered:
        depths.append(render / "depth" / f"depth_{number:06d}.tiff")
        param_files.append(take / "SMPL" / f"mesh-f{number:05d}_smpl.pkl")
        params.append(_params_of(param_files[-1]))
        scan = take / "meshes_pkl" / f"mesh-f{number:05d}.pkl"
        scans.append(scan if scan.is_file() else None)
    return _Take(
        names=[f"{split}-{take.name}-{number:06d}" for number, _ in numbered],
        K=K, w2c=w2c, images=[path for _, path in numbered], depths=depths, params=params, param_files=param_files, scans=scans,
        size_hw=first.shape[:2], camera_file=camera_file,
    )


def read_xhumans(root: Path) -> CaptureV1:
    """Read an X-Humans subject (see the module docstring for what is imported)."""
    root = Path(root)
    train_takes, test_takes = _takes(root, "train"), _takes(root, "test")
    if not train_takes:
        raise InputError(f"{root / 'train'}: no TakeN folders; X-Humans subjects train on their train/ takes")
    shape_path = root / "mean_shape_smpl.npy"
    betas = array_of(shape_path, {"mean_shape": read_npy(shape_path)}, "mean_shape", (10,), (1, 10)).reshape(10)
    gender_path = root / "gender.txt"
    gender = gender_path.read_text(encoding="utf-8", errors="replace").strip() if gender_path.is_file() else None

    chosen = [("train", train_takes[0])] + [("test", take) for take in test_takes]
    takes = [_read_take(take, split) for split, take in chosen]
    size_hw = takes[0].size_hw
    for take, (_, folder) in zip(takes[1:], chosen[1:]):
        if take.size_hw != size_hw:
            raise InputError(
                f"{folder / 'render' / 'image'}: renders are {take.size_hw[1]}x{take.size_hw[0]}, but "
                f"{chosen[0][1].name}'s are {size_hw[1]}x{size_hw[0]}; a capture has one image size"
            )
    depth_present = [path.is_file() for take in takes for path in take.depths]
    if any(depth_present) and not all(depth_present):
        missing = next(p for take in takes for p in take.depths if not p.is_file())
        raise InputError(f"{missing}: missing; the masks come from the depth renders, which must cover every frame or none")

    frames = [name for take in takes for name in take.names]
    splits = {"train": takes[0].names, "test": [name for take in takes[1:] for name in take.names]}
    if not splits["test"]:
        del splits["test"]
    params = [p for take in takes for p in take.params]
    poses = {key: np.stack([p[key] for p in params]) for key in ("global_orient", "body_pose", "transl")}
    subject = {"name": root.name, "takes": {split: [] for split in splits}}
    for split, folder in chosen:
        subject["takes"][split].append(folder.name)
    if gender:
        subject["gender"] = gender
    sources = [shape_path] + ([gender_path] if gender else []) + [take.camera_file for take in takes]
    sources += [path for take in takes for path in take.param_files]
    return assemble_capture(CaptureParts(
        root=root, source_format=NAME, body_model="smpl", frames=frames, splits=splits,
        K=np.concatenate([np.broadcast_to(t.K, (len(t.names), 3, 3)) for t in takes]),
        w2c=np.concatenate([t.w2c for t in takes]), height=size_hw[0], width=size_hw[1],
        poses={"betas": betas, **poses},
        image_files={n: p for t in takes for n, p in zip(t.names, t.images)},
        mask_files={n: p for t in takes for n, p in zip(t.names, t.depths)} if all(depth_present) else {},
        source_files=sources,
        scans={n: s for t in takes for n, s in zip(t.names, t.scans) if s is not None},
        subject=subject,
    ))
