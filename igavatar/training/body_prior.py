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

A fit that is too heavy everywhere by a centimetre or two passes that vote (a centimetre is about a
pixel at 256 px) and the bound would inflate the subject by the excess less the slack. The
confirmed points also measure it: their `spill`, the mean share of the views seeing a point in
which it falls outside the undilated mask, is 0.011-0.015 for the benchmark's fitted templates and
0.060 / 0.108 for a template grown by 1 / 2 cm (256 px: a pixel is 1.1 cm wide at the subject). Above
MAX_SPILL the template is not used. A fitted template's own spill grows as pixels coarsen (the
silhouette's edge pixels), so the check is made only where a pixel covers at most
SPILL_CHECK_MAX_PIXEL_M at the subject; with coarser masks a centimetre cannot be seen and the
template is trusted as the masks' vote leaves it (tests/benchmarks/results/body-prior.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import trimesh

from igavatar.capture.ghost_limbs import SkinFn
from igavatar.capture.visual_hull import MaskViews, free_points, vote_masks
from igavatar.geometry.mesh_ops import nearest_sample_distance
from igavatar.geometry.projection import project_points

__all__ = [
    "MAX_SPILL", "SPILL_CHECK_MAX_PIXEL_M", "BodyInsidePoints", "body_inside_loss", "body_inside_points", "sample_inside_template",
]

#: Largest `BodyInsidePoints.spill` of a template the body-inside term trusts: between the benchmark's
#: fitted templates (at most 0.015) and a template 1 cm too heavy (0.060); 5 mm too heavy gives 0.034.
MAX_SPILL = 0.035
#: The spill is checked only when a mask pixel covers at most this many meters at the subject (the
#: benchmark: 1.1 cm; the tests: 1.2 cm in a 128 px view of a 1.2 m box, 2.5 cm at 64 px).
SPILL_CHECK_MAX_PIXEL_M = 0.015


@dataclass(frozen=True)
class BodyInsidePoints:
    """Canonical points inside the naked template that the masks confirm.

    Attributes:
        points: (P, 3) float32 canonical positions.
        template_sdf: (P,) float32 the template's signed distance there (< 0, meters).
        sampled: how many points were drawn inside the template before the masks' vote.
        spill: mean over the kept points of the share of the views seeing a point in which it
            falls outside the undilated mask (0 for a template inside the silhouettes; nan when
            no point is kept).
        pixel_m: median over the views of a mask pixel's width at the kept points' centroid
            (meters; nan when no point is kept).
    """

    points: torch.Tensor
    template_sdf: torch.Tensor
    sampled: int
    spill: float = float("nan")
    pixel_m: float = float("nan")

    @property
    def spill_checked(self) -> bool:
        """Whether the masks are fine enough for the spill to tell a fit too heavy by a centimetre."""
        return bool(self.pixel_m <= SPILL_CHECK_MAX_PIXEL_M)

    def trusted(self, max_spill: float = MAX_SPILL) -> bool:
        """Whether the term should use these points: some are kept and, where the masks can tell,
        the template spills past them no more than `max_spill` (1: never refused)."""
        return len(self.points) > 0 and (not self.spill_checked or self.spill <= max_spill)


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
    distance = nearest_sample_distance(dense, points)
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
        max(2, 10 %) of the views that see it (`free_points`, the visual hull's rule); its spill
        is measured on the kept points with the masks as they are.
    """
    points, sdf = sample_inside_template(vertices, faces, n_points, depth_m, seed)
    points_t = torch.tensor(points, dtype=torch.float32)
    votes = vote_masks(points_t, skin, views, mask_dilation_px)
    confirmed = ~free_points(votes.seen, votes.inside)
    kept = points_t[confirmed]
    spill = pixel_m = float("nan")
    if len(kept):
        exact = vote_masks(kept, skin, views, mask_dilation_px=0)
        outside = (exact.seen - exact.inside).float() / exact.seen.clamp_min(1).float()
        spill = float(outside.mean())
        pixel_m = _pixel_size_m(kept.mean(dim=0, keepdim=True), skin, views)
    return BodyInsidePoints(kept, torch.tensor(sdf, dtype=torch.float32)[confirmed], len(points), spill, pixel_m)


def _pixel_size_m(x_canonical: torch.Tensor, skin: SkinFn, views: MaskViews) -> float:
    """Median over the views of the width (meters) a pixel covers at a canonical point's depth."""
    widths = []
    for K, w2c, frame in zip(views.K, views.w2c, views.frames):
        K = np.asarray(K, np.float64)
        _, depth = project_points(K, np.asarray(w2c, np.float64), skin(int(frame), x_canonical).double().cpu().numpy())
        if depth[0] > 0:
            widths.append(float(depth[0]) / K[0, 0])
    return float(np.median(widths)) if widths else float("nan")


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
