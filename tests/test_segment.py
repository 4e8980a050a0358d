"""GrabCut segmentation seeded by a projected body: rasterising, seeding, cutting.

The end-to-end check (a synthetic capture without masks, preprocessed, against its true masks) is
in tests/test_preprocess.py.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from igavatar.capture.segment import (
    PosedBody,
    estimate_mask,
    grabcut_mask,
    mesh_silhouette,
    seed_labels,
    skeleton_silhouette,
)
from igavatar.errors import InputError

SIZE = 96
K = np.array([[100.0, 0, SIZE / 2], [0, 100.0, SIZE / 2], [0, 0, 1]])
W2C = np.eye(4)
W2C[2, 3] = 3.0  # the world origin 3 m in front of the camera


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def noisy_scene(subject: np.ndarray, seed: int = 0) -> np.ndarray:
    """(SIZE, SIZE, 3) uint8: a reddish textured subject on a bluish textured background."""
    rng = np.random.default_rng(seed)
    background = np.clip(rng.normal([60, 90, 150], 25, (SIZE, SIZE, 3)), 0, 255)
    foreground = np.clip(rng.normal([170, 70, 50], 25, (SIZE, SIZE, 3)), 0, 255)
    return np.where(subject[..., None], foreground, background).astype(np.uint8)


def test_mesh_silhouette_fills_overlapping_triangles():
    """A square (two triangles) plus a triangle over it: overlaps add up, never cancel out."""
    vertices = np.array([[-0.3, -0.3, 0], [0.3, -0.3, 0], [0.3, 0.3, 0], [-0.3, 0.3, 0]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 1, 3]])
    silhouette = mesh_silhouette(vertices, faces, K, W2C, (SIZE, SIZE))
    # 0.6 m at 3 m with f = 100 px spans 20 px: a 20 x 20 (+-1 px edge) square at the center.
    assert 19 * 19 <= silhouette.sum() <= 21 * 21
    assert silhouette[SIZE // 2, SIZE // 2] and silhouette[SIZE // 2 - 8, SIZE // 2 - 8]
    assert not silhouette[5, 5]


def test_skeleton_silhouette_follows_the_bones():
    joints = np.array([[0.0, 0.0, 0.0], [0.0, -0.6, 0.0], [0.5, 0.0, 0.0]])
    silhouette = skeleton_silhouette(joints, np.array([-1, 0, 0]), K, W2C, (SIZE, SIZE), radius_m=0.06)
    assert silhouette[SIZE // 2, SIZE // 2] and silhouette[SIZE // 2 - 18, SIZE // 2]  # up the image (y down)
    assert silhouette[SIZE // 2, SIZE // 2 + 15] and not silhouette[SIZE // 2 + 15, SIZE // 2 + 15]


def test_grabcut_recovers_the_subject_from_a_misaligned_prior():
    truth = np.zeros((SIZE, SIZE), np.uint8)
    cv2.ellipse(truth, (48, 30), (10, 12), 0, 0, 360, 1, -1)  # head
    cv2.rectangle(truth, (34, 40), (62, 85), 1, -1)  # body
    truth = truth > 0
    # The prior: the subject shrunk by 3 px and shifted by 2 px (a body model under clothes, a
    # slightly wrong pose); it alone reaches only a modest IoU.
    prior = np.roll(cv2.erode(truth.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0, (2, 2), axis=(0, 1))
    sure = cv2.erode(prior.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    mask = grabcut_mask(noisy_scene(truth), seed_labels(prior, sure, band_px=8))
    assert iou(prior, truth) < 0.8
    assert iou(mask, truth) > 0.95, iou(mask, truth)


def test_grabcut_drops_islands_that_do_not_touch_the_sure_subject():
    truth = np.zeros((SIZE, SIZE), bool)
    truth[30:70, 40:56] = True
    image_subject = truth.copy()
    image_subject[5:9, 5:9] = True  # a subject-colored blob far from the body
    probable = truth.copy()
    probable[5:9, 5:9] = True  # even if seeded probable, it is not connected to the sure core
    sure = np.zeros_like(truth)
    sure[40:60, 44:52] = True
    mask = grabcut_mask(noisy_scene(image_subject), seed_labels(probable, sure, band_px=6))
    assert not mask[5:9, 5:9].any() and iou(mask, truth) > 0.9


def test_estimate_mask_from_a_skeleton_without_template():
    """Bones seed capsules of 8 cm; the subject is 6 cm thick: GrabCut finds its real edge."""
    joints = np.array([[0.0, 0.1, 0.0], [0.0, -0.6, 0.0], [0.45, 0.05, 0.0], [-0.45, 0.05, 0.0], [0.0, 0.4, 0.0]])
    parents = np.array([-1, 0, 0, 0, 0])
    truth = skeleton_silhouette(joints, parents, K, W2C, (SIZE, SIZE), radius_m=0.06)
    mask = estimate_mask(noisy_scene(truth, seed=1), K, W2C, PosedBody(joints=joints, parents=parents))
    prior = skeleton_silhouette(joints, parents, K, W2C, (SIZE, SIZE), radius_m=0.08)
    assert iou(mask, truth) > 0.9 and iou(mask, truth) > iou(prior, truth) + 0.1, (iou(mask, truth), iou(prior, truth))


def test_estimate_mask_refuses_what_it_cannot_use():
    rgb = np.zeros((SIZE, SIZE, 3), np.uint8)
    with pytest.raises(InputError, match="neither a template mesh nor a skeleton"):
        estimate_mask(rgb, K, W2C, PosedBody())
    with pytest.raises(InputError, match=r"image has shape \(96, 96\) and dtype float64, expected \(H, W, 3\) uint8"):
        estimate_mask(np.zeros((SIZE, SIZE)), K, W2C, PosedBody(joints=np.zeros((1, 3)), parents=np.array([-1])))
    # A body behind the camera seeds nothing: an empty mask (preprocess reports the frame).
    behind = PosedBody(joints=np.array([[0.0, 0.0, -5.0]]), parents=np.array([-1]))
    assert not estimate_mask(rgb, K, W2C, behind).any()
