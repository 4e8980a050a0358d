"""The naked body inside the clothes: an upper bound on the SDF inside the body model's template.

    prior = body_inside_points(vertices, faces, skin, views)      # points inside the template
    loss = body_inside_loss(sdf_field(prior.points), prior.template_sdf, slack=0.005)

Clothes, hair and skin lie on or outside the naked body, so the clothed subject contains the body
model's template (when the template is fitted to the subject). For a point inside the template
the true SDF is then at most the template's: ``sdf(x) <= sdf_template(x)``. The hinge keeps that
bound, loosened by `slack`, and nothing else: it never pulls clothing in, only stops the surface
from retreating inside the body. It matters where the images cannot: fingers and toes are a pixel
wide at 256-512 px, and a trained field lets them recede into a mitten (measured in
tests/benchmarks/results/body-prior.md).

A template that does not fit (a body-model fit off by some centimetres, a hand in the wrong pose)
would make the bound wrong. Only points that the masks confirm are kept: pushed into every voting
training frame by forward skinning, a point must fall inside the (dilated) mask in all but a few
views (the visual hull's vote, igavatar.capture.visual_hull), so a limb of the template that lies
outside the subject's silhouettes is left out instead of being forced into the shape.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from igavatar.capture.ghost_limbs import SkinFn
from igavatar.capture.visual_hull import MaskViews, free_points, vote_masks

__all__ = ["BodyInsidePoints", "body_inside_loss", "body_inside_points", "sample_inside_template"]


@dataclass(frozen=True)
class BodyInsidePoints:
    """Canonical points inside the naked template that the masks confirm.

    Attributes:
        points: (P, 3) float32 canonical positions.
        template_sdf: (P,) float32 the template's signed distance there (< 0, meters).
        sampled: how many points were drawn inside the template before the masks' vote.
    """

    points: torch.Tensor
    template_sdf: torch.Tensor
    sampled: int


def sample_inside_template(
    vertices: np.ndarray, faces: np.ndarray, n_points: int = 120_000, depth_m: float = 0.012, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Points just inside the template and their exact signed distance.

    Surface points drawn uniformly by area and moved inwards along the face normal by U(0, depth)
    cover thin parts (fingers, toes) in proportion to their area, where points drawn in the volume
    would all but miss them. Points that leave the body (through a finger thinner than the step)
    or sit on the surface are dropped.

    Args:
        vertices (V, 3), faces (F, 3): the canonical template (its largest component is used).
        n_points: surface points drawn.
        depth_m: largest inward step in meters.
        seed: RNG seed.
    Returns:
        points (P, 3) float64 and sdf (P,) float64 < 0, P <= n_points.
    """
    parts = trimesh.Trimesh(vertices, faces, process=False).split(only_watertight=False)
    mesh = max(parts, key=lambda m: len(m.faces)) if len(parts) else trimesh.Trimesh(vertices, faces, process=False)
    rng = np.random.default_rng(seed)
    surface, face = trimesh.sample.sample_surface(mesh, n_points, seed=seed)
    points = surface - mesh.face_normals[face] * rng.uniform(0.0, depth_m, (n_points, 1))
    # The distance to a dense surface sample (the same estimate as the shape initialization's).
    dense, _ = trimesh.sample.sample_surface(mesh, 4 * n_points, seed=seed + 1)
    distance, _ = cKDTree(dense).query(points, workers=-1)
    keep = mesh.contains(points) & (distance > 5e-4)
    return points[keep], -distance[keep]


def body_inside_points(
    vertices: np.ndarray,
    faces: np.ndarray,
    skin: SkinFn,
    views: MaskViews,
    n_points: int = 120_000,
    depth_m: float = 0.012,
    mask_dilation_px: int = 2,
    seed: int = 0,
) -> BodyInsidePoints:
    """Sample points inside the template and keep those the masks confirm.

    Args:
        vertices, faces: the naked template in canonical space.
        skin: forward skinning of canonical points into a view's frame (world space).
        views: the voting masks and cameras.
        n_points, depth_m, seed: see `sample_inside_template`.
        mask_dilation_px: masks are dilated first (pose, camera and mask errors of a pixel or two).
    Returns:
        BodyInsidePoints (CPU); a point is kept unless it falls outside the masks in at least
        max(2, 10 %) of the views that see it (`free_points`, the visual hull's rule).
    """
    points, sdf = sample_inside_template(vertices, faces, n_points, depth_m, seed)
    points_t = torch.tensor(points, dtype=torch.float32)
    votes = vote_masks(points_t, skin, views, mask_dilation_px)
    confirmed = ~free_points(votes.seen, votes.inside)
    return BodyInsidePoints(points_t[confirmed], torch.tensor(sdf, dtype=torch.float32)[confirmed], len(points))


def body_inside_loss(sdf: torch.Tensor, template_sdf: torch.Tensor, slack: float) -> torch.Tensor:
    """Mean of relu(sdf - template_sdf - slack): the field may not be further outside than the body.

    Args:
        sdf: (P,) predicted signed distance at points inside the template.
        template_sdf: (P,) the template's signed distance there (< 0).
        slack: meters of tolerance (the rendered silhouette sits ~3 beta outside the zero level, so
            a trained zero level lies a few millimetres inside the true surface; and fits are not exact).
    Returns:
        scalar tensor.
    """
    if sdf.shape != template_sdf.shape:
        raise ValueError(f"body_inside_loss: sdf {tuple(sdf.shape)} vs template_sdf {tuple(template_sdf.shape)}")
    return torch.relu(sdf - template_sdf - slack).mean()
