"""The facts a dataset and a model artifact both record in their manifest's data."""

from __future__ import annotations


class ManifestFacts:
    """Typed reads of `self.manifest["data"]` shared by DatasetArtifact and ModelArtifact."""

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
