"""The canonical-shape section of an eval report: gathers the dataset's template, skeleton and (for a
synthetic capture) the true clothed surface, and asks `igavatar.metrics.canonical` about the
predicted canonical mesh: is every limb there, is the gap between the legs empty, how close is it
to the truth.

    section, image = canonical_section(read_dataset(dataset_dir), capture_dir, (v, f), n_iou=200_000)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
import trimesh

from igavatar.body.motions import semantic_joint_map
from igavatar.metrics.canonical import (
    REST_SURFACE_FILE,
    canonical_from_rest,
    canonical_shape_report,
    leg_gap_points,
    limb_labels,
    rest_to_canonical_transforms,
)
from igavatar.avatar.dataset import PRIOR_FILE, DatasetArtifact
from igavatar.avatar.subject import SubjectArrays
from igavatar.metrics.report import canonical_views_image
from igavatar.skinning.grid import sample_grid

#: Body models whose joints have semantic names (limbs can be told apart).
NAMED_SKELETONS = ("anny", "smpl")


def canonical_truth(capture_dir: Path | None, subject: SubjectArrays) -> tuple[np.ndarray, np.ndarray] | None:
    """The true clothed surface in the dataset's canonical pose, when the capture has it."""
    path = None if capture_dir is None else Path(capture_dir) / REST_SURFACE_FILE
    if path is None or not path.is_file():
        return None
    with np.load(path) as rest:
        if int(rest["weights_index"].max()) >= subject.n_joints:
            return None  # the capture's skeleton is not the one the truth is skinned to (a lone root)
        transforms = rest_to_canonical_transforms(subject.rest_joints, subject.parents, subject.canonical_rotations)
        vertices = canonical_from_rest(rest["vertices"], rest["weights_index"], rest["weights_value"], transforms)
        return vertices, np.asarray(rest["faces"], np.int64)


def _mesh_arrays(path: Path) -> tuple[np.ndarray, np.ndarray]:
    mesh = trimesh.load(path, process=False)
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)


def canonical_section(
    dataset: DatasetArtifact,
    capture_dir: Path | None,
    pred: tuple[np.ndarray, np.ndarray],
    n_iou: int = 200_000,
    seed: int = 0,
    trained_prior: Path | None = None,
) -> tuple[dict[str, Any] | None, np.ndarray | None]:
    """The report's `canonical` section and its front/side picture; (None, None) without a template.

    `trained_prior`: the mesh of the prior the model was trained from when it is not the dataset's
    (the masks' hull that `train --refine-poses` voted on its fitted poses); the picture shows it.

    The limb check needs the template's vertices grouped by body part, so it runs for body models
    with named joints (Anny, SMPL) and for a bare skeleton of such a kind with a body fitted to it
    (its template is then that fit, not the subject's own body); any other bare skeleton gets the
    comparison with the truth only.
    """
    prior_path = dataset.path / PRIOR_FILE
    if not prior_path.is_file():
        return None, None
    prior_v, prior_f = _mesh_arrays(prior_path)
    # The naked template the limb check needs.
    body_path = dataset.body_template_path
    naked = body_path.is_file()
    template_v, template_f = _mesh_arrays(body_path) if naked and body_path != prior_path else (prior_v, prior_f)
    subject = dataset.subject
    truth = canonical_truth(capture_dir, subject)
    # A bare skeleton of a named kind has a template when a body was fitted to it (igavatar.capture.body_fit).
    kind = dataset.body_model if dataset.body_model in NAMED_SKELETONS else dataset.data.get("subject", {}).get("skeleton_kind")
    kind = kind if kind in NAMED_SKELETONS else None
    joint_names = list(subject.joint_names)
    labels = np.full(len(template_v), -1, np.int64)
    gap = None
    if kind is not None and naked:
        weights = sample_grid(torch.from_numpy(subject.skinning_grid).float(), torch.from_numpy(subject.grid_box_min).float(),
                              torch.from_numpy(subject.grid_box_max).float(), torch.from_numpy(template_v).float())
        joint_map = dict(semantic_joint_map(kind))
        labels = limb_labels(subject.parents, joint_names, joint_map, weights.argmax(dim=1).numpy())
        index = {part: joint_names.index(name) for part, name in joint_map.items() if name in joint_names}
        if all(part in index for part in ("left_thigh", "right_thigh", "left_shin", "right_shin")):
            gap = leg_gap_points(subject.canonical_joints.astype(np.float64), index)
    section = canonical_shape_report(pred, (template_v, template_f), labels, gap, truth, n_iou=n_iou, seed=seed)
    section["frame"] = "canonical (the avatar's rest space, meters in, units as in the posed metrics)"
    section["truth"] = "ground_truth/clothed_rest.npz of the capture, posed into the canonical pose" if truth else "not available"
    rows = [("prediction", pred[0], pred[1])]
    if truth is not None:
        rows.append(("truth (clothed)", truth[0], truth[1]))
    prior = dataset.shape_prior
    if trained_prior is not None and trained_prior.is_file():
        rows.append(("shape prior (visual hull, voted on the fitted poses)", *_mesh_arrays(trained_prior)))
    else:
        rows.append(({"template": "template (naked)"}.get(prior, f"shape prior ({prior.replace('_', ' ')})"), prior_v, prior_f))
    return section, canonical_views_image(rows)
