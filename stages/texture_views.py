"""`export --texture-from images`: the training frames as views to fuse into the texture.

    paint = image_painter(model, dataset_path, max_views=0, progress=progress)
    textured = textured_mesh(vertices, faces, color_fn, target_faces, size, paint=paint)

Only the dataset's *training* frames are used, never its test frames, so that held-out images
stay held out. Each frame poses the atlas mesh as export poses its meshes (forward skinning and
the non-rigid offset; the model's refined poses where `train --refine-poses` made them), and its
image and mask are read at the dataset's size, one frame at a time.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from igavatar.avatar.dataset import read_dataset
from igavatar.avatar.model import ModelArtifact
from igavatar.avatar.poses import read_poses
from igavatar.avatar.surfaces import surface_colors
from igavatar.errors import InputError
from igavatar.mesh.texture_fusion import FusionSettings, ProjectedView, fuse_texture
from igavatar.mesh.textured_mesh import Painter
from stages.progress import ProgressSink


def _training_indices(is_train: np.ndarray, max_views: int) -> list[int]:
    train = np.flatnonzero(is_train)
    if max_views and train.size > max_views:
        train = train[np.round(np.linspace(0, train.size - 1, max_views)).astype(np.int64)]
    return train.tolist()


def training_views(model: ModelArtifact, dataset_path: Path, atlas_vertices: np.ndarray, max_views: int,
                   progress: ProgressSink) -> Iterator[ProjectedView]:
    """The training frames as views, lazily: a frame is posed and its image read when its turn comes."""
    dataset = read_dataset(dataset_path)
    frames = dataset.frames()
    indices = _training_indices(frames.is_train, max_views)
    if not indices:
        raise InputError(f"--texture-from images: the dataset {dataset_path} has no training frames")
    poses = read_poses(model, dataset_path, lambda n, where: indices, option="--dataset")

    def views() -> Iterator[ProjectedView]:
        with progress.task("texture from images", total=len(indices)) as advance:
            for slot, index in enumerate(indices):
                with torch.no_grad():
                    posed = model.posed(poses.bone_transforms[slot].to(model.device), poses.pose_condition[slot].to(model.device))
                    x_posed = posed.pose_vertices(atlas_vertices)
                image, mask = dataset.image_and_mask(frames.names[index])
                yield ProjectedView(x_posed, frames.K[index], frames.w2c[index], image, mask)
                advance(1)

    return views()


def image_painter(model: ModelArtifact, dataset_path: Path, max_views: int, progress: ProgressSink,
                  record: dict) -> Painter:
    """A textured_mesh painter fusing the training images; the color field fills what no view sees.
    `record` receives the fusion's facts (views, seen fraction) for the manifest."""

    def paint(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
        views = training_views(model, dataset_path, vertices, max_views, progress)
        image, covered, stats = fuse_texture(vertices, faces, uv, size, views,
                                             fallback_fn=lambda x: surface_colors(model.avatar, x), settings=FusionSettings())
        record.update(stats, dataset=str(dataset_path))
        return image, covered

    return paint
