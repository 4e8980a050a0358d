"""Import the InstantAvatar / PeopleSnapshot layout (DATA.md section 1a) as an SMPL capture v1.

    if detect_peoplesnapshot(root): capture = read_peoplesnapshot(root)     # a validated CaptureV1

Layout (as InstantAvatar's preprocessing writes it):
    images/image_0000.png ...          RGB, undistorted
    masks/mask_0000.npy ...            {0,1}  (custom-video variant: masks/*.png, 0/255; or no masks)
    cameras.npz                        intrinsic (3,3), extrinsic (4,4) w2c, height, width
    poses.npz                          betas (10,)|(1,10), thetas (N,72) [or global_orient (N,3) +
                                       body_pose (N,69)], transl (N,3); N = every image
                                       (custom-video variant: poses_optimized.npz)
    poses/anim_nerf_{train,test}.npz   betas (1,10), global_orient (n,3), body_pose (n,69), transl (n,3)

Frames and splits. Images and masks pair by sorted order (as InstantAvatar reads them), and frame
i is the i-th image. For the four subjects of the Anim-NeRF benchmark (ANIM_NERF_SPLITS, matched
by the directory name) the splits are its frame ranges (first, last inclusive, step); a split's
poses come from its poses/anim_nerf_<split>.npz when that file exists (poses refined by Anim-NeRF,
one row per frame of the range) and from poses.npz otherwise. Other directories get the default
split: the first two thirds of the images for training, the rest for testing, every
DEFAULT_STEP-th frame of each, with poses from poses.npz (a poses/ folder of split files is then
an error, since which frames its rows belong to is unknown). Anim-NeRF's one-frame 'val' split is
not imported (it repeats the first test frame). The body shape is the betas of the train split's
pose file.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from igavatar.capture.arrays import array_of, read_npz, scalar_of
from igavatar.capture.assemble import CaptureParts, assemble_capture
from igavatar.capture.capture_v1 import CAPTURE_FILE, CaptureV1
from igavatar.errors import InputError

NAME = "peoplesnapshot"

#: Anim-NeRF frame ranges (first, last inclusive, step) of the PeopleSnapshot benchmark subjects,
#: as InstantAvatar's configs give them.
ANIM_NERF_SPLITS: dict[str, dict[str, tuple[int, int, int]]] = {
    "male-3-casual": {"train": (0, 455, 4), "test": (456, 675, 4)},
    "female-3-casual": {"train": (0, 445, 4), "test": (446, 647, 4)},
    "female-4-casual": {"train": (0, 335, 4), "test": (335, 523, 4)},
    "male-4-casual": {"train": (0, 659, 6), "test": (660, 872, 6)},
}
#: Every DEFAULT_STEP-th frame is used by the default split (the benchmark's usual step).
DEFAULT_STEP = 4
#: Share of the images (from the start) that the default split trains on.
DEFAULT_TRAIN_SHARE = 2 / 3
_SPLIT_NAMES = ("train", "test")
_TRAILING_NUMBER = re.compile(r"(\d+)$")


def detect_peoplesnapshot(root: Path) -> bool:
    """images/ + cameras.npz + poses.npz or poses_optimized.npz, and no capture.json."""
    return (
        not (root / CAPTURE_FILE).is_file()
        and (root / "images").is_dir()
        and (root / "cameras.npz").is_file()
        and ((root / "poses.npz").is_file() or (root / "poses_optimized.npz").is_file())
    )


def _frame_number(path: Path) -> int | None:
    match = _TRAILING_NUMBER.search(path.stem)
    return int(match.group(1)) if match else None


def _images_and_masks(root: Path) -> tuple[list[Path], list[Path]]:
    """Sorted images and their masks (.npy preferred, else .png; empty list when there are none)."""
    images = sorted((root / "images").glob("*.png"))
    if not images:
        raise InputError(f"{root / 'images'}: no .png images")
    masks: list[Path] = []
    mask_dir = root / "masks"
    if mask_dir.is_dir():
        masks = sorted(mask_dir.glob("*.npy")) or sorted(mask_dir.glob("*.png"))
    if masks and len(masks) != len(images):
        raise InputError(
            f"{mask_dir}: {len(masks)} masks for {len(images)} images; give one mask per image "
            "(they pair by sorted order), or none to have them estimated"
        )
    for image, mask in zip(images, masks):
        numbers = _frame_number(image), _frame_number(mask)
        if None not in numbers and numbers[0] != numbers[1]:
            raise InputError(
                f"{mask}: pairs with {image.name} by sorted order but is numbered {numbers[1]}, not {numbers[0]}; "
                "a mask is missing or extra"
            )
    return images, masks


def _camera(root: Path) -> tuple[np.ndarray, np.ndarray, int, int]:
    path = root / "cameras.npz"
    data = read_npz(path)
    if "intrinsic" not in data and {"K", "w2c"} <= set(data):
        raise InputError(
            f"{path}: holds capture v1 cameras (K, w2c), not PeopleSnapshot ones (intrinsic, extrinsic); "
            f"{root / CAPTURE_FILE} is missing: restore it to read {root} as a capture v1"
        )
    K = array_of(path, data, "intrinsic", (3, 3))
    w2c = array_of(path, data, "extrinsic", (4, 4), (3, 4))
    if w2c.shape == (3, 4):
        w2c = np.vstack((w2c, [0.0, 0.0, 0.0, 1.0]))
    height, width = scalar_of(path, data, "height"), scalar_of(path, data, "width")
    if height < 1 or width < 1 or height != int(height) or width != int(width):
        raise InputError(f"{path}: height/width are {height}x{width}, expected positive integers")
    return K, w2c, int(height), int(width)


def _smpl_rows(path: Path, data: dict, n_rows: int | None) -> dict[str, np.ndarray]:
    """betas (10,), global_orient (n,3), body_pose (n,69), transl (n,3) of one pose file.

    Accepts `thetas (n, 72)` in place of global_orient + body_pose (InstantAvatar's poses.npz).
    """
    betas = array_of(path, data, "betas", (10,), (1, 10), (None, 10))
    if betas.ndim == 2 and betas.shape[0] > 1 and not np.allclose(betas, betas[:1], atol=1e-6):
        raise InputError(f"{path}: key 'betas' has shape {betas.shape} with different rows; expected one body shape")
    if "thetas" in data:
        thetas = array_of(path, data, "thetas", (None, 72))
        orient, body = thetas[:, :3], thetas[:, 3:]
    else:
        orient = array_of(path, data, "global_orient", (None, 3))
        body = array_of(path, data, "body_pose", (orient.shape[0], 69))
    transl = array_of(path, data, "transl", (orient.shape[0], 3))
    if n_rows is not None and orient.shape[0] != n_rows:
        key = "thetas" if "thetas" in data else "global_orient"
        raise InputError(f"{path}: key '{key}' has {orient.shape[0]} rows, expected {n_rows} (one per frame)")
    return {"betas": betas.reshape(-1, 10)[0], "global_orient": orient, "body_pose": body, "transl": transl}


def _split_indices(root: Path, n_images: int, has_split_files: bool) -> tuple[dict[str, list[int]], str]:
    """Image indices per split, and where they come from ('anim-nerf' or 'default')."""
    ranges = ANIM_NERF_SPLITS.get(root.name)
    if ranges is None:
        if has_split_files:
            raise InputError(
                f"{root / 'poses'}: Anim-NeRF split files, but '{root.name}' is not a subject with known frame "
                f"ranges ({', '.join(ANIM_NERF_SPLITS)}), so their rows cannot be matched to images; name the "
                "directory after its PeopleSnapshot subject, or move poses/ away to use poses.npz with the "
                "default split"
            )
        if n_images < 2:
            raise InputError(f"{root / 'images'}: {n_images} image; the default split needs at least 2 (train and test)")
        cut = min(max(1, round(n_images * DEFAULT_TRAIN_SHARE)), n_images - 1)
        return {"train": list(range(0, cut, DEFAULT_STEP)), "test": list(range(cut, n_images, DEFAULT_STEP))}, "default"
    indices = {}
    for split, (first, last, step) in ranges.items():
        if last >= n_images:
            raise InputError(
                f"{root / 'images'}: {n_images} images, but the Anim-NeRF {split} split of {root.name} runs to "
                f"frame {last}; the subject's images are incomplete"
            )
        indices[split] = list(range(first, last + 1, step))
    return indices, "anim-nerf"


def read_peoplesnapshot(root: Path) -> CaptureV1:
    """Read a PeopleSnapshot / InstantAvatar subject directory (see the module docstring)."""
    root = Path(root)
    images, masks = _images_and_masks(root)
    K, w2c, height, width = _camera(root)
    all_poses_path = root / "poses.npz"
    if not all_poses_path.is_file():
        all_poses_path = root / "poses_optimized.npz"
    split_paths = {s: root / "poses" / f"anim_nerf_{s}.npz" for s in _SPLIT_NAMES}
    split_paths = {s: p for s, p in split_paths.items() if p.is_file()}
    indices, split_source = _split_indices(root, len(images), bool(split_paths))

    all_poses = _smpl_rows(all_poses_path, read_npz(all_poses_path), len(images))
    frames_index = sorted(set(indices["train"]) | set(indices["test"]))
    position = {image_index: row for row, image_index in enumerate(frames_index)}
    poses = {key: all_poses[key][frames_index].copy() for key in ("global_orient", "body_pose", "transl")}
    betas, betas_from = all_poses["betas"], all_poses_path
    sources = [root / "cameras.npz", all_poses_path]
    for split in _SPLIT_NAMES:
        if split not in split_paths:
            continue
        path = split_paths[split]
        refined = _smpl_rows(path, read_npz(path), len(indices[split]))
        rows = [position[i] for i in indices[split]]
        for key in poses:
            poses[key][rows] = refined[key]
        if split == "train":
            betas, betas_from = refined["betas"], path
        sources.append(path)

    frames = [images[i].stem for i in frames_index]
    if len(set(frames)) != len(frames):
        raise InputError(f"{root / 'images'}: image names are not unique after dropping the extension")
    gender = next((g for g in ("female", "male") if root.name.startswith(g)), None)
    subject = {"name": root.name, "split_source": split_source, "betas_from": str(betas_from.relative_to(root))}
    if gender is not None:
        subject["gender"] = gender
    return assemble_capture(CaptureParts(
        root=root, source_format=NAME, body_model="smpl", frames=frames,
        splits={split: [images[i].stem for i in indices[split]] for split in _SPLIT_NAMES},
        K=np.broadcast_to(K, (len(frames), 3, 3)).copy(), w2c=np.broadcast_to(w2c, (len(frames), 4, 4)).copy(),
        height=height, width=width, poses={"betas": betas, **poses},
        image_files={images[i].stem: images[i] for i in frames_index},
        mask_files={images[i].stem: masks[i] for i in frames_index} if masks else {},
        source_files=sources, subject=subject,
    ))
