"""subject.npz, shared by the dataset and model artifacts: the skeleton and the canonical space.

    subject = SubjectArrays.read(Path("run/dataset/subject.npz"))
    subject.skeleton, subject.parents (J,), subject.skinning_grid (J, D, H, W)
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from igavatar.artifacts.npz import read_npz
from igavatar.body.skeleton import Skeleton

SUBJECT_FILE = "subject.npz"
#: Every array of subject.npz and its shape (J joints, B seed bones, a D x H x W grid).
_SHAPES = {"parents": ("J",), "rest_joints": ("J", 3), "canonical_joints": ("J", 3), "canonical_rotations": ("J", 3, 3),
           "joint_names": ("J",), "init_bones": ("B",), "skinning_grid": ("J", "D", "H", "W"),
           "grid_box_min": (3,), "grid_box_max": (3,), "canonical_box": (2, 3)}


@dataclass(frozen=True, eq=False)
class SubjectArrays:
    """The arrays of subject.npz (J joints, a (D, H, W) skinning grid, lengths in meters).

    Attributes:
        parents: (J,) int64, -1 at the root; rest_joints: (J, 3) rest-pose joints;
        canonical_joints: (J, 3) joints in the canonical (star) pose;
        canonical_rotations: (J, 3, 3) local rotations of the canonical pose;
        joint_names: J names; init_bones: (B,) bones that seed root finding;
        skinning_grid: (J, D, H, W) canonical skinning weights over grid_box_min/max (3,) each;
        canonical_box: (2, 3) box of the canonical SDF.
    """

    parents: np.ndarray
    rest_joints: np.ndarray
    canonical_joints: np.ndarray
    canonical_rotations: np.ndarray
    joint_names: tuple[str, ...]
    init_bones: np.ndarray
    skinning_grid: np.ndarray
    grid_box_min: np.ndarray
    grid_box_max: np.ndarray
    canonical_box: np.ndarray

    @classmethod
    def read(cls, path: Path) -> SubjectArrays:
        """Read subject.npz; ArtifactError naming the file and the missing keys."""
        arrays: dict = read_npz(Path(path), _SHAPES, "the subject arrays")
        arrays["joint_names"] = tuple(str(n) for n in arrays["joint_names"])
        return cls(**arrays)

    def write(self, path: Path) -> None:
        """subject.npz at `path` (the layout `read` reads)."""
        arrays = {name: getattr(self, name) for name in _SHAPES}
        arrays["joint_names"] = np.array(self.joint_names, dtype=np.str_)
        np.savez_compressed(path, **arrays)

    @property
    def skeleton(self) -> Skeleton:
        return Skeleton(self.parents, self.rest_joints, self.joint_names)

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    def same_skeleton(self, other: SubjectArrays) -> bool:
        """Whether `other` has the same joints (names, order) and tree."""
        return self.joint_names == other.joint_names and np.array_equal(self.parents, other.parents)
