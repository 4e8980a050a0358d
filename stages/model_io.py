"""Load a model artifact back into an Avatar (for export, animate and eval).

    model = load_model(Path("igavatar-run/model"), device="cpu")
    model.avatar, model.canonical_grid, model.subject["parents"], model.manifest["data"]
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from igavatar.artifacts.manifest import read_artifact
from igavatar.capture.subject import PosedFrames, pose_frames
from igavatar.model.avatar import Avatar
from igavatar.render.occupancy import OccupancyGrid
from igavatar.training.checkpoint import load_state
from igavatar.training.config import TrainConfig, config_from_json


@dataclass(frozen=True)
class LoadedModel:
    """A trained avatar with everything needed to pose and render it.

    Attributes:
        path: the model artifact directory; manifest: its manifest.
        config: the TrainConfig it was trained with.
        avatar: the Avatar in eval mode, on the requested device.
        canonical_grid: its canonical occupancy grid.
        subject: arrays of subject.npz (parents, rest_joints, canonical_rotations, joint_names, ...).
    """

    path: Path
    manifest: dict
    config: TrainConfig
    avatar: Avatar
    canonical_grid: OccupancyGrid
    subject: dict

    @property
    def joint_names(self) -> list[str]:
        return [str(n) for n in self.subject["joint_names"]]

    def pose(self, local_rotations: torch.Tensor, root_translation: torch.Tensor) -> PosedFrames:
        """Bone transforms and pose conditioning of local rotations (N, J, 3, 3) relative to the rest pose."""
        return pose_frames(
            self.subject["parents"], torch.from_numpy(self.subject["rest_joints"]).float(),
            torch.from_numpy(self.subject["canonical_rotations"]).float(), local_rotations.float(),
            root_translation.float(),
        )


def load_model(path: Path, device: torch.device | str = "cpu") -> LoadedModel:
    """Read and check a model artifact, rebuild its Avatar and occupancy grid."""
    from stages.train import build_avatar

    path = Path(path)
    manifest = read_artifact(path, expected="model")
    config = config_from_json(manifest["config"])
    subject = dict(np.load(path / "subject.npz"))
    avatar = build_avatar(config, subject, manifest["data"]["pose_dim"])
    weights = load_state(path / "weights.npz")
    avatar.load_state_dict(weights["avatar"])
    box = avatar.canonical_box
    grid = OccupancyGrid(box[0], box[1], resolution=config.occupancy_resolution)
    grid.load_state_dict(weights["canonical_grid"])
    avatar.eval()
    return LoadedModel(path, manifest, config, avatar.to(device), grid.to(device), subject)
