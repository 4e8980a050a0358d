"""Does the subject wear something the naked body model cannot grow into? Masks against the posed template.

    fit = template_fit(masks, bodies, K, w2c, distance_m=LOOSE_DISTANCE_M)   # means over the views
    use_hull = fit.hull_is_better          # loose >= LOOSE_SHARE and loose >= LOOSE_OVER_SPILL x spill

A naked template is a good shape prior for tight clothes and a bad one for a dress: training grows
the surface from the prior, and a skirt between two template legs comes out as two trouser legs.
The masks say which case a capture is: the share of subject pixels lying more than a few
centimeters outside the posed template's silhouette. On the three synthetic subjects (256 px, all
60 training views), the share at 2 / 3 / 4 / 5 cm: tight shirt and trousers on a heavy body
0.057 / 0.012 / 0.0013 / 0; a tight striped shirt 0.023 / 0.003 / 0.0004 / 0; a flared dress
0.055 / 0.037 / 0.026 / 0.012. Clothes sit 2-3 cm off the body; a skirt much farther.

Poses that are off look the same from the mask's side: an arm posed 10 cm away from where the
person holds it leaves mask pixels far from the template. They differ on the template's side: a
misplaced limb also lies on background, where loose clothes only ever cover more (the `spill`).
Misregistration alone is nearly symmetric (a clothed mask a little larger than the naked body:
loose 1.8-2.6x the spill under 2.5-5 degrees of noise a joint on the tight striped shirt), loose
clothes add to one side only (the flared dress: loose 0.023, spill 0). The visual hull is the
wrong prior for poses that are off too: it is what every view's mask keeps, and a limb that each
frame puts somewhere else is carved away (5 degrees of pose noise left an armless blob,
tests/benchmarks/results/pose-noise.md). So the hull replaces the template only where the masks
reach past it much more than it spills past them.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from igavatar.geometry.projection import project_points

#: Subject pixels farther than this (meters, at the body's depth) outside the posed template's
#: silhouette count as clothing or hair the template does not reach.
LOOSE_DISTANCE_M = 0.04
#: The mean share of such pixels from which the masks' visual hull is the better shape prior.
LOOSE_SHARE = 0.01
#: The loose share must be at least this many times the spill for the clothes, not the poses, to
#: explain it. Measured at LOOSE_DISTANCE_M (loose / spill): 2.5 and 5 degrees of noise on a tight
#: shirt 0.014 / 0.0055 and 0.065 / 0.037; ZJU-MoCap 377 on its own poses 0.042 / 0.0079 and from
#: the video path 0.024 / 0.0006; the dress 0.023 / 0.
LOOSE_OVER_SPILL = 4.0


@dataclass(frozen=True)
class TemplateFit:
    """How the posed template and the masks disagree, as means over the views.

    Attributes:
        loose: share of the masks' pixels farther than the distance outside the template's silhouette.
        spill: share of the template silhouette's pixels farther than the distance outside the mask.
    """

    loose: float
    spill: float

    @property
    def hull_is_better(self) -> bool:
        """Loose clothes (the masks reach past the template) on poses that hold (it barely spills past them)."""
        return self.loose >= LOOSE_SHARE and self.loose >= LOOSE_OVER_SPILL * self.spill


def template_silhouette(vertices_world: np.ndarray, faces: np.ndarray, K: np.ndarray, w2c: np.ndarray,
                        size_hw: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: pixels the posed mesh covers (its triangles filled, 1/8 px precision).

    Args:
        vertices_world: (V, 3) posed vertices; faces: (F, 3); K: (3, 3); w2c: (4, 4).
    """
    uv, _ = project_points(K, w2c, vertices_world)
    keep = np.all(np.isfinite(uv[faces]).reshape(len(faces), -1), axis=1)
    polygons = np.round(uv[faces[keep]] * 8).astype(np.int32)  # (F', 3, 2), 3 fractional bits
    silhouette = np.zeros(size_hw, np.uint8)
    cv2.fillPoly(silhouette, list(polygons), 1, lineType=cv2.LINE_8, shift=3)
    return silhouette.astype(bool)


def outside_share(mask: np.ndarray, silhouette: np.ndarray, distance_px: float) -> float:
    """Share of the mask's pixels farther than `distance_px` from the silhouette (0 for an empty mask)."""
    if not mask.any():
        return 0.0
    distance = cv2.distanceTransform((~silhouette).astype(np.uint8), cv2.DIST_L2, 5)
    return float((mask & (distance > distance_px)).sum() / mask.sum())


def template_fit(
    masks: list[np.ndarray],
    bodies: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    K: np.ndarray,
    w2c: np.ndarray,
    distance_m: float = LOOSE_DISTANCE_M,
) -> TemplateFit:
    """Means over the views of the masks' pixels `distance_m` outside the posed template, and back.

    Args:
        masks: V (H, W) bool subject masks at the dataset's size.
        bodies: V tuples (posed vertices (N, 3), faces (F, 3), root position (3,)) in world space;
            the root's depth converts meters to pixels.
        K: (V, 3, 3) intrinsics at the masks' size; w2c: (V, 4, 4).
    Returns:
        TemplateFit with both shares in [0, 1]; 0 when there are no views.
    """
    loose, spill = [], []
    for mask, (vertices, faces, root), k, pose in zip(masks, bodies, K, w2c):
        _, depth = project_points(k, pose, np.asarray(root, np.float64)[None])
        if not depth[0] > 1e-6:
            continue
        silhouette = template_silhouette(vertices, faces, k, pose, mask.shape)
        distance_px = distance_m * float(k[0, 0]) / float(depth[0])
        loose.append(outside_share(mask, silhouette, distance_px))
        spill.append(outside_share(silhouette, mask, distance_px))
    return TemplateFit(float(np.mean(loose)) if loose else 0.0, float(np.mean(spill)) if spill else 0.0)
