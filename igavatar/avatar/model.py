"""A model artifact (written by `igavatar train`) loaded back into a posable avatar.

    model = load_model(Path("run/model"), device="cpu")
    model.avatar, model.canonical_grid, model.subject.parents, model.body_model
    frames = model.pose(local_rotations, root_translation)       # PosedFrames
    posed = model.posed(frames.bone_transforms[0], frames.pose_condition[0])
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from igavatar.artifacts.manifest import read_artifact
from igavatar.avatar.facts import ManifestFacts
from igavatar.errors import ArtifactError
from igavatar.avatar.subject import SUBJECT_FILE, SubjectArrays
from igavatar.body.skeleton import Skeleton
from igavatar.capture.posed_subject import PosedFrames, pose_frames
from igavatar.capture.scans import existing
from igavatar.model.avatar import Avatar
from igavatar.model.posed import PosedAvatar
from igavatar.render.occupancy import OccupancyGrid
from igavatar.training.checkpoint import load_state
from igavatar.training.config import TrainConfig, config_from_json

#: The shape prior's mesh when the model was trained from one of its own (the masks' visual hull that
#: `train --refine-poses` voted on its fitted poses, stages.train_prior); its grid is in subject.npz.
MODEL_PRIOR_FILE = "prior.ply"


def build_avatar(config: TrainConfig, subject: SubjectArrays, pose_dim: int) -> Avatar:
    """A fresh avatar for a subject: its canonical box, skinning grid and root-finding seeds."""
    return Avatar(
        config.avatar,
        canonical_box=torch.from_numpy(subject.canonical_box).float(),
        skinning_grid=torch.from_numpy(subject.skinning_grid).float(),
        grid_box_min=torch.from_numpy(subject.grid_box_min).float(),
        grid_box_max=torch.from_numpy(subject.grid_box_max).float(),
        pose_dim=pose_dim,
        init_bones=tuple(int(i) for i in subject.init_bones),
        parents=tuple(int(i) for i in subject.parents),
    )


@dataclass(frozen=True, eq=False)
class ModelManifest(ManifestFacts):
    """A model artifact's manifest, read without loading the network (for checks before the load)."""

    path: Path
    manifest: dict

    @property
    def canonical_box(self) -> list[list[float]]:
        """(2, 3) canonical box, meters."""
        return self.manifest["data"]["canonical_box"]

    @property
    def recorded_dataset(self) -> Path:
        """The dataset path recorded at training (relative to where `train` ran)."""
        return Path(self.data["dataset"])

    def trained_dataset(self) -> Path | None:
        """The dataset it was trained on, if it is still there: the recorded path, else the path of
        that name beside the model (a run directory moved as a whole, or a relative path recorded
        where `train` ran)."""
        return existing(self.recorded_dataset, self.path)


def read_model_manifest(path: Path, check_hashes: bool = True) -> ModelManifest:
    """Read and check a model artifact's manifest (kind, version, schema and, by default, file hashes)."""
    return ModelManifest(Path(path), read_artifact(Path(path), expected="model", check_hashes=check_hashes))


@dataclass(frozen=True, eq=False)
class ModelArtifact(ModelManifest):
    """A trained avatar with everything needed to pose and render it.

    Attributes:
        path: the model artifact directory; manifest: its manifest (ModelManifest's reads).
        config: the TrainConfig it was trained with.
        avatar: the Avatar in eval mode, on the requested device.
        canonical_grid: its canonical occupancy grid.
        subject: its subject.npz (skeleton, canonical pose, skinning grid).
    """

    config: TrainConfig
    avatar: Avatar
    canonical_grid: OccupancyGrid
    subject: SubjectArrays

    @property
    def phenotype(self) -> dict | None:
        """The Anny phenotype the subject was fitted with (None for other body models)."""
        return self.data.get("subject", {}).get("phenotype")

    @property
    def joint_names(self) -> list[str]:
        return list(self.subject.joint_names)

    @property
    def skeleton(self) -> Skeleton:
        return self.subject.skeleton

    @property
    def device(self) -> torch.device:
        return self.avatar.canonical_box.device

    def pose(self, local_rotations: torch.Tensor, root_translation: torch.Tensor) -> PosedFrames:
        """Bone transforms and pose conditioning of local rotations (N, J, 3, 3) relative to the rest pose."""
        return pose_frames(
            self.subject.parents, torch.from_numpy(self.subject.rest_joints).float(),
            torch.from_numpy(self.subject.canonical_rotations).float(), local_rotations.float(),
            root_translation.float(),
        )

    def posed(self, bone_transforms: torch.Tensor, pose_condition: torch.Tensor, nonrigid: bool = True) -> PosedAvatar:
        """The avatar in one frame: (J, 4, 4) canonical -> world transforms, (pose_dim,) conditioning;
        `nonrigid` False poses by skinning alone (PosedAvatar.nonrigid)."""
        return PosedAvatar.of(self.avatar, torch.as_tensor(bone_transforms).float(),
                              torch.as_tensor(pose_condition).float(), nonrigid)


def _load_weights(module: torch.nn.Module, weights: dict, key: str, path: Path) -> None:
    """module.load_state_dict(weights[key]); ArtifactError naming the file and the tensors that do
    not fit the model its manifest describes (an edited file, re-hashed), instead of a traceback."""
    if not isinstance(weights.get(key), dict):
        raise ArtifactError(f"{path}: the {key} weights are missing; re-run `igavatar train`")
    try:
        module.load_state_dict(weights[key])
    except (RuntimeError, KeyError) as error:
        detail = "; ".join(line.strip() for line in str(error).splitlines()[1:4]) or str(error)
        raise ArtifactError(f"{path}: the {key} weights do not fit the model its manifest describes ({detail}); "
                            "re-run `igavatar train`") from None


def load_model(path: Path, device: torch.device | str = "cpu") -> ModelArtifact:
    """Read and check a model artifact, rebuild its Avatar and occupancy grid."""
    path = Path(path)
    manifest = read_artifact(path, expected="model")
    config = config_from_json(manifest["config"])
    subject = SubjectArrays.read(path / SUBJECT_FILE)
    avatar = build_avatar(config, subject, manifest["data"]["pose_dim"])
    weights = load_state(path / "weights.npz")
    box = avatar.canonical_box
    grid = OccupancyGrid(box[0], box[1], resolution=config.occupancy_resolution)
    for module, key in ((avatar, "avatar"), (grid, "canonical_grid")):
        _load_weights(module, weights, key, path / "weights.npz")
    avatar.eval()
    return ModelArtifact(path, manifest, config, avatar.to(device), grid.to(device), subject)
