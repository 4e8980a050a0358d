"""The facts a dataset and a model artifact both record in their manifest's data."""

from __future__ import annotations

import numpy as np

from igavatar.body.bones import skeleton_kind
from igavatar.body.motions import SKELETON_KINDS, body_to_world


class ManifestFacts:
    """Typed reads of `self.manifest["data"]` shared by DatasetArtifact and ModelArtifact, and the
    world axes of their subject (both have `subject`, a SubjectArrays)."""

    manifest: dict

    @property
    def data(self) -> dict:
        return self.manifest["data"]

    @property
    def body_model(self) -> str:
        """'anny', 'smpl' or 'skeleton'."""
        return str(self.data["body_model"])

    @property
    def pose_dim(self) -> int:
        """The size of a frame's pose conditioning."""
        return int(self.data["pose_dim"])

    @property
    def recorded_joint_names(self) -> list[str]:
        return list(self.data["joint_names"])

    @property
    def axes_kind(self) -> str:
        """The skeleton kind whose world axes the capture uses: the body model's; for a bare skeleton
        its kind (Anny's bones come in Anny's +Z-up world); SMPL's for a skeleton of unknown kind."""
        if self.body_model in SKELETON_KINDS:
            return self.body_model
        return skeleton_kind(self.subject.skeleton) or "smpl"

    @property
    def body_axes(self) -> np.ndarray:
        """(3, 3) columns: the body's left, up and forward directions in world (see axes_kind)."""
        return body_to_world(self.axes_kind)
