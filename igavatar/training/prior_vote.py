"""The shape prior voted again on the training poses as the fit to the masks corrected them.

    body = PriorBody(skeleton, canonical_joints, fitted_transforms, template, weights, faces)
    vote = vote_prior(body, data, (64, 16, 64), WeightBlur(None, 1.0))
    vote.report    # {"views": 53, "loose": 0.031, "spill": 0.004, "prior": "visual_hull", "seconds": ...}
    vote.prior     # the masks' visual hull (igavatar.capture.shape_prior.ShapePrior), or None

`preprocess --shape-prior auto` chooses between the naked template and the masks' visual hull on
the capture's poses (igavatar.capture.loose_clothing): the hull only where the masks reach far past
the posed template and the template barely spills past them. Poses that are off spill, so a dress
on noisy poses gets the template, and the avatar grows two trouser legs out of it (5 degrees of
noise: CD-L1 11.2 mm against 3.8 with the exact poses, tests/benchmarks/results/pose-noise.md).
After `train --refine-poses` has fitted the poses to the masks (igavatar.training.pose_silhouette)
the same rule is asked again on the fitted poses, and where the hull now wins it is built from the
same masks posed by those poses, as preprocess builds it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from igavatar.capture.shape_prior import (
    MAX_HULL_VIEWS, MIN_HULL_VIEWS, PriorBody, ShapePrior, WeightBlur, hull_prior, posed_template_fit,
)
from igavatar.capture.visual_hull import spread_views
from igavatar.training.data import TrainingData


@dataclass(frozen=True)
class PriorVote:
    """The vote's outcome.

    Attributes:
        prior: the masks' visual hull posed by the body's transforms, or None (the template stays).
        report: JSON-able: views, loose, spill (igavatar.capture.loose_clothing.TemplateFit),
            prior ("visual_hull" | "template"), seconds.
    """

    prior: ShapePrior | None
    report: dict


def vote_prior(body: PriorBody, data: TrainingData, resolution: tuple[int, int, int], blur: WeightBlur) -> PriorVote:
    """Preprocess's loose-clothing vote and hull (igavatar.capture.shape_prior) on `body`'s poses.

    Args:
        body: the subject with a template; its bone_transforms (N, J, 4, 4) are every frame's poses
            (the training frames' as fitted), indexed as `data`'s frames.
        data: the frames' masks and cameras; its training frames vote (at most MAX_HULL_VIEWS).
        resolution: (D, H, W) of the skinning grid; blur: as preprocess smoothed the weights.
    """
    started = time.perf_counter()
    views = spread_views(data.train_indices.tolist(), MAX_HULL_VIEWS)
    if len(views) < MIN_HULL_VIEWS:
        return PriorVote(None, {"views": len(views), "prior": "template", "seconds": time.perf_counter() - started})
    masks = {i: data.masks[i].numpy() for i in views}
    K, w2c = data.K.double().numpy(), data.w2c.double().numpy()
    fit = posed_template_fit(body, views, masks, K, w2c)
    prior = hull_prior(body, views, masks, K, w2c, resolution, blur) if fit.hull_is_better else None
    report = {"views": len(views), "loose": fit.loose, "spill": fit.spill,
              "prior": "template" if prior is None else "visual_hull", "seconds": time.perf_counter() - started}
    return PriorVote(prior, report)
