"""A dataset artifact (written by `igavatar preprocess`) read into typed records.

    dataset = read_dataset(Path("run/dataset"))          # manifest checked, hashes verified
    dataset.body_model, dataset.image_size, dataset.splits, dataset.subject.parents
    frames = dataset.frames()                            # DatasetFrames, all frames
    data = training_data(dataset)                        # TrainingData (CPU tensors) for the trainer
    test = frames.select(frames.test_indices)
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np
import torch

from igavatar.artifacts.manifest import read_artifact
from igavatar.artifacts.npz import read_npz
from igavatar.avatar.facts import ManifestFacts
from igavatar.avatar.subject import SUBJECT_FILE, SubjectArrays
from igavatar.capture.images import resize_image, resize_mask
from igavatar.errors import ArtifactError, InputError
from igavatar.training.data import TrainingData

FRAMES_FILE = "frames.npz"
#: The shape prior's mesh (the naked template, a visual hull or capsules; manifest "shape_prior").
PRIOR_FILE = "template.ply"
#: The naked template beside a prior that is not it (`preprocess --shape-prior visual-hull`).
BODY_TEMPLATE_FILE = "body_template.ply"
#: The naked template's skinning weights, `weights` (V, J), when the capture has a body model: `train
#: --refine-poses` votes the shape prior again on the poses it fitted (igavatar.training.prior_vote).
BODY_WEIGHTS_FILE = "body_weights.npz"


@dataclass(frozen=True, eq=False)
class DatasetFrames:
    """frames.npz: N frames of J joints, pose conditioning of size pose_dim (float32 unless stated).

    Attributes:
        names: N frame names (images/<name>.png, masks/<name>.png).
        K: (N, 3, 3) intrinsics at the dataset's resolution; w2c: (N, 4, 4) world -> camera.
        bone_transforms: (N, J, 4, 4) canonical -> posed world.
        pose_condition: (N, pose_dim) conditioning of the non-rigid offset.
        posed_boxes: (N, 2, 3) world boxes that bound the posed subject.
        posed_joints: (N, J, 3) world joints.
        is_train, is_test: (N,) bool splits.
    """

    names: tuple[str, ...]
    K: np.ndarray
    w2c: np.ndarray
    bone_transforms: np.ndarray
    pose_condition: np.ndarray
    posed_boxes: np.ndarray
    posed_joints: np.ndarray
    is_train: np.ndarray
    is_test: np.ndarray

    @property
    def n_frames(self) -> int:
        return len(self.names)

    @property
    def train_indices(self) -> list[int]:
        return np.flatnonzero(self.is_train).tolist()

    @property
    def test_indices(self) -> list[int]:
        return np.flatnonzero(self.is_test).tolist()

    def select(self, indices: list[int]) -> DatasetFrames:
        """The frames at `indices`, in that order."""
        index = np.asarray(indices, np.int64)
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        values = {key: (tuple(value[i] for i in indices) if key == "names" else value[index]) for key, value in values.items()}
        return DatasetFrames(**values)


#: frames.npz's arrays and their shapes (N frames, J joints, pose_dim P).
_FRAME_SHAPES = {"frame_names": ("N",), "K": ("N", 3, 3), "w2c": ("N", 4, 4), "bone_transforms": ("N", "J", 4, 4),
                 "pose_condition": ("N", "P"), "posed_boxes": ("N", 2, 3), "posed_joints": ("N", "J", 3),
                 "is_train": ("N",), "is_test": ("N",)}


@dataclass(frozen=True, eq=False)
class DatasetArtifact(ManifestFacts):
    """A checked dataset artifact: its directory, manifest and subject; frames read on demand."""

    path: Path
    manifest: dict

    @property
    def image_size(self) -> tuple[int, int]:
        """(H, W) of the dataset's images."""
        height, width = (int(v) for v in self.data["image_size"])
        return height, width

    @property
    def splits(self) -> dict[str, list[str]]:
        return self.data["splits"]

    @property
    def shape_prior(self) -> str:
        return str(self.data.get("shape_prior", "template"))

    @property
    def body_template_path(self) -> Path:
        """Where the body model's naked template is: the prior itself, or written beside a prior
        that is not it (the file is absent for a capture without a body model)."""
        return self.path / (PRIOR_FILE if self.shape_prior == "template" else BODY_TEMPLATE_FILE)

    @cached_property
    def subject(self) -> SubjectArrays:
        return SubjectArrays.read(self.path / SUBJECT_FILE)

    def body_weights(self, n_vertices: int) -> np.ndarray | None:
        """(V, J) float32 skinning weights of the naked template of `n_vertices` vertices, or None for
        a dataset without them (no body model, or made before preprocess wrote them)."""
        path = self.path / BODY_WEIGHTS_FILE
        if not path.is_file():
            return None
        arrays = read_npz(path, {"weights": ("V", "J")}, "the body's skinning weights",
                          sizes={"V": n_vertices, "J": self.subject.n_joints})
        return arrays["weights"].astype(np.float32)

    def image_path(self, name: str) -> Path:
        return self.path / "images" / f"{name}.png"

    def mask_path(self, name: str) -> Path:
        return self.path / "masks" / f"{name}.png"

    def image_and_mask(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Frame `name` at the dataset's size: RGB (H, W, 3) uint8 and mask (H, W) bool."""
        image = cv2.imread(str(self.image_path(name)), cv2.IMREAD_COLOR)
        mask = cv2.imread(str(self.mask_path(name)), cv2.IMREAD_GRAYSCALE)
        if image is None or mask is None:
            missing = self.image_path(name) if image is None else self.mask_path(name)
            raise ArtifactError(f"{missing}: unreadable; re-run `igavatar preprocess`")
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB), mask > 127

    def image_on_white(self, name: str, size_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Frame `name` composited on white and resized: RGB (h, w, 3) float64 in [0, 1], mask (h, w) bool."""
        image, inside = self.image_and_mask(name)
        rgb = np.where(inside[..., None], image, 255).astype(np.uint8)
        # Composite first, then area-resample, so that edge pixels blend with white as a render does.
        return resize_image(rgb, size_hw).astype(np.float64) / 255.0, resize_mask(inside, size_hw)

    def frames(self) -> DatasetFrames:
        """Every frame of frames.npz; ArtifactError naming the file and missing keys."""
        path = self.path / FRAMES_FILE
        arrays = read_npz(path, _FRAME_SHAPES, "the frames", sizes={"J": self.subject.n_joints, "P": self.pose_dim})
        names = tuple(str(n) for n in arrays.pop("frame_names"))
        return DatasetFrames(names=names, **arrays)


def training_data(dataset: DatasetArtifact) -> TrainingData:
    """Every frame of a dataset artifact as CPU tensors (images (N, H, W, 3) uint8, masks (N, H, W) bool)."""
    frames = dataset.frames()
    images, masks = [], []
    for name in frames.names:
        image, mask = dataset.image_and_mask(name)
        images.append(image)
        masks.append(mask)
    if not frames.train_indices:
        raise InputError(f"{dataset.path}: the dataset has no training frames (splits.train is empty)")
    return TrainingData(
        frame_names=list(frames.names),
        images=torch.from_numpy(np.stack(images)),
        masks=torch.from_numpy(np.stack(masks)),
        K=torch.from_numpy(frames.K).float(),
        w2c=torch.from_numpy(frames.w2c).float(),
        bone_transforms=torch.from_numpy(frames.bone_transforms).float(),
        pose_condition=torch.from_numpy(frames.pose_condition).float(),
        posed_boxes=torch.from_numpy(frames.posed_boxes).float(),
        train_indices=torch.tensor(frames.train_indices, dtype=torch.long),
    )


def read_dataset(path: Path, check_hashes: bool = True) -> DatasetArtifact:
    """Read and check a dataset artifact's manifest (and by default its files' hashes)."""
    path = Path(path)
    return DatasetArtifact(path, read_artifact(path, expected="dataset", check_hashes=check_hashes))
