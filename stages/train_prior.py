"""`train --refine-poses`: the dataset's shape prior voted again on the poses fitted to the masks.

    vote = revote_prior(config, dataset, data, refiner, silhouette, work)   # None: the dataset's prior
    subject, data = vote.subject, vote.with_boxes(data)                      # the hull's grid and boxes
    mesh = vote.mesh_path                                                    # the shape initialization's

`preprocess` voted between the naked template and the masks' visual hull on the capture's poses
(igavatar.training.prior_vote says why that vote fails on poses that are off). When it kept the
template by that rule, and the poses have since been fitted to the masks, the rule is asked again;
where the hull wins, the run trains on it: its skinning grid, canonical box and posed boxes replace
the dataset's in the model (subject.npz), and the SDF starts from its mesh (written in the work
folder, so that a resumed run finds the same shape initialization).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from igavatar.avatar.dataset import DatasetArtifact
from igavatar.avatar.model import MODEL_PRIOR_FILE
from igavatar.avatar.subject import SubjectArrays
from igavatar.capture.shape_prior import PriorBody, WeightBlur
from igavatar.training.config import TrainConfig
from igavatar.training.data import TrainingData
from igavatar.training.pose_refine import PoseRefiner
from igavatar.training.pose_silhouette import SilhouetteFit, corrected_data
from igavatar.training.prior_vote import vote_prior
from stages.progress import ProgressSink

#: The hull voted on the fitted poses, in the work folder while training and in the model after.
REVOTED_PRIOR_FILE = MODEL_PRIOR_FILE


@dataclass(frozen=True)
class RevotedPrior:
    """The outcome of the vote on the fitted poses.

    Attributes:
        report: for the model's manifest (igavatar.training.prior_vote.PriorVote.report, or why
            the vote could not run).
        subject: the dataset's subject arrays with the hull's skinning grid and boxes, or None
            when the dataset's prior stays.
        posed_boxes: (N, 2, 3) the hull's padded world boxes per frame, or None.
        mesh_path: the hull's mesh, or None.
    """

    report: dict
    subject: SubjectArrays | None = None
    posed_boxes: torch.Tensor | None = None
    mesh_path: Path | None = None

    def with_boxes(self, data: TrainingData) -> TrainingData:
        """`data` with the hull's posed boxes (unchanged when the dataset's prior stays)."""
        return data if self.posed_boxes is None else dataclasses.replace(data, posed_boxes=self.posed_boxes)


def _dataset_blur(dataset: DatasetArtifact) -> WeightBlur:
    """The weight blur preprocess used (its manifest config: an int, or a text for the defaults)."""
    config = dataset.manifest.get("config", {})
    passes = config.get("weight_smoothing")
    return WeightBlur(passes if isinstance(passes, int) else None, config.get("weight_spread"))


def _body(dataset: DatasetArtifact, transforms: torch.Tensor) -> PriorBody | None:
    """The dataset's naked template posed by `transforms` (N, J, 4, 4); None without its weights."""
    import trimesh

    mesh = trimesh.load(dataset.body_template_path, process=False)
    weights = dataset.body_weights(len(mesh.vertices))
    if weights is None:
        return None
    subject = dataset.subject
    return PriorBody(subject.skeleton, torch.from_numpy(subject.canonical_joints).float(), transforms.float(),
                     torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32), torch.from_numpy(weights),
                     torch.as_tensor(np.asarray(mesh.faces), dtype=torch.int64))


def revote_prior(config: TrainConfig, dataset: DatasetArtifact, data: TrainingData, refiner: PoseRefiner | None,
                 silhouette: SilhouetteFit | None, work: Path, progress: ProgressSink) -> RevotedPrior | None:
    """Vote again when the poses were fitted to the masks and preprocess's rule kept the template
    (module docstring); None when there is nothing to vote on. The refiner holds the fit's corrections."""
    if refiner is None or silhouette is None or not config.pose_prior_vote:
        return None
    if dataset.shape_prior != "template" or "loose_clothing" not in dataset.data:
        return None  # already the hull, or a prior the user chose (--shape-prior template)
    transforms = corrected_data(data, refiner).bone_transforms
    body = _body(dataset, transforms)
    if body is None:
        return RevotedPrior({"prior": "template", "skipped": "the dataset has no body_weights.npz (made before "
                             "igavatar wrote them): `igavatar preprocess --force` remakes it"})
    progress.status("voting the shape prior again on the fitted poses")
    resolution = tuple(int(n) for n in dataset.subject.skinning_grid.shape[1:])
    vote = vote_prior(body, data, resolution, _dataset_blur(dataset))
    report = {"before": dataset.data["loose_clothing"], **vote.report}
    if vote.prior is None:
        return RevotedPrior(report)
    prior = vote.prior
    mesh_path = work / REVOTED_PRIOR_FILE
    import trimesh

    trimesh.Trimesh(prior.vertices.numpy(), prior.faces.numpy(), process=False).export(mesh_path)
    subject = dataclasses.replace(
        dataset.subject, skinning_grid=prior.skinning_grid.numpy().astype(np.float32),
        grid_box_min=prior.box_min.numpy().astype(np.float32), grid_box_max=prior.box_max.numpy().astype(np.float32),
        canonical_box=prior.canonical_box().numpy().astype(np.float32))
    return RevotedPrior(report, subject, prior.posed_boxes.float(), mesh_path)
