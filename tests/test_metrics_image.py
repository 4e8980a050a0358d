"""Image metrics against scikit-image, plus mask boxes and report panels.

    .venv/bin/python -m pytest tests/test_metrics_image.py -q
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from igavatar.errors import InputError
from igavatar.metrics.image import (
    ImageInputError,
    crop_to_mask_bbox,
    error_map,
    evaluate_image,
    mask_bbox,
    psnr,
    side_by_side,
    ssim,
)


def skimage_ssim(pred: np.ndarray, target: np.ndarray) -> float:
    return structural_similarity(
        pred, target, channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5,
        use_sample_covariance=False,
    )


def smooth_image(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A natural-ish image: blurred noise plus a gradient, in [0, 1]."""
    image = cv2.GaussianBlur(rng.random((height, width, 3)), (0, 0), 3.0)
    image = image + np.linspace(0, 0.5, width)[None, :, None]
    return (image - image.min()) / (image.max() - image.min())


@pytest.mark.parametrize("shape", [(11, 11), (32, 47), (64, 40)])
@pytest.mark.parametrize("noise", [0.02, 0.2])
def test_ssim_matches_skimage(shape, noise):
    rng = np.random.default_rng(hash((shape, noise)) % 2**32)
    target = smooth_image(rng, *shape)
    pred = np.clip(target + rng.normal(scale=noise, size=target.shape), 0, 1)
    assert ssim(pred, target) == pytest.approx(skimage_ssim(pred, target), abs=1e-6)


def test_ssim_matches_skimage_on_unrelated_and_float32_images():
    rng = np.random.default_rng(0)
    a = rng.random((24, 30, 3)).astype(np.float32)
    b = rng.random((24, 30, 3)).astype(np.float32)
    reference = skimage_ssim(a.astype(np.float64), b.astype(np.float64))
    assert ssim(a, b) == pytest.approx(reference, abs=1e-6)
    assert abs(ssim(a, b)) < 0.2  # unrelated noise is nearly uncorrelated


def test_ssim_identity_and_symmetry():
    rng = np.random.default_rng(1)
    a = smooth_image(rng, 20, 20)
    b = np.clip(a + 0.1 * rng.normal(size=a.shape), 0, 1)
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    assert ssim(a, b) == pytest.approx(ssim(b, a), abs=1e-12)
    assert ssim(a, b) < 0.95


def test_ssim_data_range_matters():
    # The released code's [-1, 1] images with data_range=1 are a different number: guard the units.
    rng = np.random.default_rng(2)
    a = smooth_image(rng, 20, 20)
    b = np.clip(a + 0.1 * rng.normal(size=a.shape), 0, 1)
    wrong = structural_similarity(
        2 * a - 1, 2 * b - 1, channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5,
        use_sample_covariance=False,
    )
    assert abs(ssim(a, b) - wrong) > 1e-3


def test_psnr_matches_skimage_and_closed_form():
    rng = np.random.default_rng(3)
    target = rng.random((16, 20, 3))
    pred = np.clip(target + rng.normal(scale=0.05, size=target.shape), 0, 1)
    assert psnr(pred, target) == pytest.approx(peak_signal_noise_ratio(target, pred, data_range=1.0), abs=1e-10)
    # A constant offset of 0.1 gives MSE 0.01 -> exactly 20 dB.
    assert psnr(np.full((4, 4, 3), 0.6), np.full((4, 4, 3), 0.5)) == pytest.approx(20.0, abs=1e-9)
    assert psnr(target, target) == float("inf")


def test_psnr_with_mask_uses_only_masked_pixels():
    target = np.zeros((8, 8, 3))
    pred = np.zeros((8, 8, 3))
    pred[:4] = 0.1  # error only in the top half
    mask = np.zeros((8, 8), bool)
    mask[:4, :] = True
    assert psnr(pred, target, mask=mask) == pytest.approx(20.0)
    assert psnr(pred, target, mask=~mask) == float("inf")
    assert psnr(pred, target) == pytest.approx(10 * np.log10(1 / 0.005))


def test_mask_bbox_and_crop():
    mask = np.zeros((10, 12), bool)
    mask[3:6, 4:9] = True
    assert mask_bbox(mask) == (3, 6, 4, 9)
    assert mask_bbox(mask, pad=2) == (1, 8, 2, 11)
    assert mask_bbox(mask, pad=10) == (0, 10, 0, 12)  # clipped to the image
    image = np.arange(10 * 12 * 3, dtype=float).reshape(10, 12, 3)
    (crop_image, crop_mask) = crop_to_mask_bbox(mask, image, mask)
    np.testing.assert_array_equal(crop_image, image[3:6, 4:9])
    assert crop_mask.all()
    with pytest.raises(ImageInputError, match="empty"):
        mask_bbox(np.zeros((4, 4), bool))


def test_evaluate_image_full_and_bbox_variants():
    rng = np.random.default_rng(4)
    target = np.ones((40, 50, 3))  # white background
    pred = target.copy()
    mask = np.zeros((40, 50), bool)
    mask[10:30, 15:35] = True
    target[mask] = rng.random((mask.sum(), 3))
    pred[mask] = np.clip(target[mask] + rng.normal(scale=0.05, size=(mask.sum(), 3)), 0, 1)
    metrics = evaluate_image(pred, target, mask)
    assert metrics.psnr_full_db == pytest.approx(psnr(pred, target))
    crop_pred, crop_target = pred[10:30, 15:35], target[10:30, 15:35]
    assert metrics.psnr_mask_bbox_db == pytest.approx(psnr(crop_pred, crop_target))
    assert metrics.ssim_mask_bbox == pytest.approx(skimage_ssim(crop_pred, crop_target), abs=1e-6)
    # The white background inflates the full-image numbers relative to the box.
    assert metrics.psnr_full_db > metrics.psnr_mask_bbox_db
    assert metrics.ssim_full > metrics.ssim_mask_bbox
    assert set(metrics.to_dict()) == {"description", "full_image", "mask_bbox"}
    # A box thinner than the SSIM window is grown to 11 px rather than failing.
    thin = np.zeros((40, 50), bool)
    thin[20, 5:45] = True
    assert np.isfinite(evaluate_image(pred, target, thin).ssim_mask_bbox)


def test_error_map_and_side_by_side():
    gt = np.zeros((6, 5, 3))
    pred = gt.copy()
    pred[2, 3] = [0.4, 0.2, 0.0]
    err = error_map(pred, gt)
    assert err.shape == (6, 5) and err[2, 3] == pytest.approx(0.2) and err.sum() == pytest.approx(0.2)
    panel = side_by_side(gt, pred, error_vmax=0.2)
    assert panel.shape == (6, 15, 3) and panel.dtype == np.uint8
    np.testing.assert_array_equal(panel[:, :5], 0)
    assert tuple(panel[2, 5 + 3]) == (102, 51, 0)  # 0.4 * 255, 0.2 * 255

    def jet(value: int) -> np.ndarray:
        bgr = cv2.applyColorMap(np.array([[value]], np.uint8), cv2.COLORMAP_JET)
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)[0, 0]

    np.testing.assert_array_equal(panel[0, 10], jet(0))  # zero error
    np.testing.assert_array_equal(panel[2, 13], jet(255))  # error at vmax: top of the map
    assert panel[2, 13, 0] > panel[2, 13, 2]  # RGB order: red dominates where the error is largest


def test_bad_inputs_name_the_problem():
    with pytest.raises(ImageInputError, match=r"pred: shape \(4, 4\)"):
        psnr(np.zeros((4, 4)), np.zeros((4, 4)))
    with pytest.raises(ImageInputError, match="uint8"):
        psnr(np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(ImageInputError, match=">= 11"):
        ssim(np.zeros((8, 20, 3)), np.zeros((8, 20, 3)))
    with pytest.raises(InputError, match="differs"):
        ssim(np.zeros((12, 12, 3)), np.zeros((12, 13, 3)))
