"""Image metrics (PSNR, SSIM) on [0, 1] RGB and the side-by-side PNGs of an evaluation report.

    metrics = evaluate_image(rgb_pred, rgb_gt, mask_gt)        # (H, W, 3) floats in [0, 1], (H, W) bool
    cv2.imwrite("f000.png", cv2.cvtColor(side_by_side(rgb_gt, rgb_pred), cv2.COLOR_RGB2BGR))

Conventions (EVAL.md): images are RGB float arrays in [0, 1], composited by the caller on the
protocol's background (white), and both metrics use ``data_range=1``. The released InstantGeoAvatar
code computes SSIM on [-1, 1] images with data_range 1, which inflates its constants' relative
weight; that defect is deliberately not reproduced. "full" means the whole image, "mask_bbox" the
same metric on the crop to the ground-truth mask's bounding box.

SSIM is Wang et al. (2004): 11x11 Gaussian window (sigma 1.5, truncated at 3.5 sigma), K1 = 0.01,
K2 = 0.03, population (co)variances, computed per channel and averaged. Borders follow
scikit-image: filters reflect at the edge and the (win_size - 1) // 2 pixel rim is cropped before
averaging, so ``ssim`` agrees with ``skimage.metrics.structural_similarity(..., channel_axis=-1,
data_range=1, gaussian_weights=True, sigma=1.5, use_sample_covariance=False)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from scipy.ndimage import correlate1d

from igavatar.errors import InputError

__all__ = [
    "ImageInputError",
    "ImageMetrics",
    "psnr",
    "ssim",
    "ssim_map",
    "mask_bbox",
    "crop_to_mask_bbox",
    "error_map",
    "side_by_side",
    "evaluate_image",
]

SSIM_SIGMA = 1.5
SSIM_TRUNCATE = 3.5
SSIM_RADIUS = int(SSIM_TRUNCATE * SSIM_SIGMA + 0.5)  # 5 -> an 11 x 11 window, as scipy.ndimage rounds it
SSIM_K1 = 0.01
SSIM_K2 = 0.03


class ImageInputError(InputError, ValueError):
    """An image or mask given to a metric has the wrong shape, dtype or content."""


def _rgb_pair(pred: Any, target: Any) -> tuple[np.ndarray, np.ndarray]:
    """Validate two (H, W, 3) finite float images of equal shape; returns float64 copies."""
    arrays = []
    for name, image in (("pred", pred), ("target", target)):
        array = np.asarray(image)
        if array.ndim != 3 or array.shape[2] != 3:
            raise ImageInputError(f"{name}: shape {array.shape}, expected (H, W, 3) RGB")
        if not np.issubdtype(array.dtype, np.floating):
            raise ImageInputError(f"{name}: dtype {array.dtype}, expected float RGB in [0, 1] (divide uint8 by 255)")
        if not np.all(np.isfinite(array)):
            raise ImageInputError(f"{name}: contains NaN or inf")
        arrays.append(array.astype(np.float64))
    if arrays[0].shape != arrays[1].shape:
        raise ImageInputError(f"pred shape {arrays[0].shape} differs from target shape {arrays[1].shape}")
    return arrays[0], arrays[1]


def _bool_mask(mask: Any, shape: tuple[int, int]) -> np.ndarray:
    """Validate an (H, W) mask matching ``shape``; nonzero means inside."""
    mask = np.asarray(mask)
    if mask.shape != shape:
        raise ImageInputError(f"mask: shape {mask.shape}, expected {shape} like the image")
    return mask.astype(bool)


def psnr(pred: Any, target: Any, mask: Any = None, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB, ``10 log10(data_range^2 / MSE)``.

    Args:
        pred, target: (H, W, 3) float RGB in [0, 1]. mask: optional (H, W) bool; when given the MSE
            is over the masked pixels only (all three channels). data_range: 1 for [0, 1] images.
    Returns:
        PSNR in dB; ``inf`` when the images are identical.
    """
    pred, target = _rgb_pair(pred, target)
    squared = (pred - target) ** 2
    if mask is not None:
        inside = _bool_mask(mask, pred.shape[:2])
        if not inside.any():
            raise ImageInputError("psnr: mask is empty, there is no pixel to compare")
        squared = squared[inside]
    mse = float(np.mean(squared))
    return float("inf") if mse == 0.0 else float(10.0 * np.log10(data_range**2 / mse))


def _gaussian_window_1d() -> np.ndarray:
    """The normalized 1-D Gaussian taps (2 r + 1,) of the SSIM window (separable)."""
    x = np.arange(-SSIM_RADIUS, SSIM_RADIUS + 1, dtype=np.float64)
    taps = np.exp(-0.5 * (x / SSIM_SIGMA) ** 2)
    return taps / taps.sum()


def _gaussian_blur(images: np.ndarray) -> np.ndarray:
    """Separable 11x11 Gaussian over axes 0 and 1 of (H, W, C); 'reflect' borders as skimage."""
    taps = _gaussian_window_1d()
    return correlate1d(correlate1d(images, taps, axis=0, mode="reflect"), taps, axis=1, mode="reflect")


def ssim_map(pred: Any, target: Any, data_range: float = 1.0) -> np.ndarray:
    """Per-pixel, per-channel SSIM map (H, W, 3) before border cropping and averaging.

    Args:
        pred, target: (H, W, 3) float RGB in [0, 1], H and W >= 11. data_range: 1 for [0, 1].
    """
    pred, target = _rgb_pair(pred, target)
    win = 2 * SSIM_RADIUS + 1
    if min(pred.shape[:2]) < win:
        raise ImageInputError(f"ssim: image is {pred.shape[0]}x{pred.shape[1]}, both sides must be >= {win}")
    c1 = (SSIM_K1 * data_range) ** 2
    c2 = (SSIM_K2 * data_range) ** 2
    # One blur pass over the five stacked moments instead of five calls.
    moments = _gaussian_blur(
        np.concatenate([pred, target, pred * pred, target * target, pred * target], axis=2)
    )
    mu_x, mu_y, e_xx, e_yy, e_xy = np.split(moments, 5, axis=2)
    # Population (co)variances: E[xy] - E[x]E[y] under the normalized window (Wang et al.).
    var_x = e_xx - mu_x * mu_x
    var_y = e_yy - mu_y * mu_y
    cov_xy = e_xy - mu_x * mu_y
    numerator = (2 * mu_x * mu_y + c1) * (2 * cov_xy + c2)
    denominator = (mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2)
    return numerator / denominator


def ssim(pred: Any, target: Any, data_range: float = 1.0) -> float:
    """Mean SSIM (Wang et al. 2004) over channels and interior pixels; see the module docstring.

    Args:
        pred, target: (H, W, 3) float RGB in [0, 1], H and W >= 11. data_range: 1 for [0, 1].
    Returns:
        SSIM in [-1, 1] (1 for identical images).
    """
    full = ssim_map(pred, target, data_range)
    # skimage averages only where the window lies fully inside the image.
    r = SSIM_RADIUS
    return float(full[r:-r, r:-r].mean())


def mask_bbox(mask: Any, pad: int = 0) -> tuple[int, int, int, int]:
    """Bounding box of a mask's True pixels, half-open, padded and clipped to the image.

    Args:
        mask: (H, W) bool (nonzero = inside). pad: pixels added on every side.
    Returns:
        ``(y0, y1, x0, x1)`` with ``image[y0:y1, x0:x1]`` the crop.
    """
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ImageInputError(f"mask: shape {mask.shape}, expected (H, W)")
    if pad < 0:
        raise ImageInputError(f"mask_bbox: pad={pad}, expected >= 0")
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    if len(rows) == 0:
        raise ImageInputError("mask_bbox: mask is empty, it has no bounding box")
    height, width = mask.shape
    return (
        max(int(rows[0]) - pad, 0), min(int(rows[-1]) + 1 + pad, height),
        max(int(cols[0]) - pad, 0), min(int(cols[-1]) + 1 + pad, width),
    )


def crop_to_mask_bbox(mask: Any, *images: Any, pad: int = 0) -> tuple[np.ndarray, ...]:
    """Crop every image (H, W, ...) to ``mask_bbox(mask, pad)``; returns the crops in order."""
    y0, y1, x0, x1 = mask_bbox(mask, pad)
    crops = []
    for i, image in enumerate(images):
        image = np.asarray(image)
        if image.shape[:2] != np.shape(mask):
            raise ImageInputError(f"crop_to_mask_bbox: image {i} has shape {image.shape}, mask {np.shape(mask)}")
        crops.append(image[y0:y1, x0:x1])
    return tuple(crops)


def error_map(pred: Any, target: Any) -> np.ndarray:
    """Per-pixel mean absolute RGB error (H, W) in [0, 1] for [0, 1] images."""
    pred, target = _rgb_pair(pred, target)
    return np.abs(pred - target).mean(axis=2)


def side_by_side(gt: Any, pred: Any, error_vmax: float = 0.25) -> np.ndarray:
    """Report panel ``gt | pred | error`` as one RGB uint8 image (H, 3 W, 3).

    Args:
        gt, pred: (H, W, 3) float RGB in [0, 1].
        error_vmax: mean absolute error shown at the top of the color map (OpenCV JET: blue = 0,
            red >= error_vmax). Fixed rather than per-image so that panels compare across frames.
    Returns:
        RGB uint8; convert with ``cv2.COLOR_RGB2BGR`` before ``cv2.imwrite``.
    """
    if not error_vmax > 0:
        raise ImageInputError(f"side_by_side: error_vmax={error_vmax}, expected > 0")
    err = error_map(pred, gt)
    to_uint8 = lambda x: np.round(np.clip(x, 0.0, 1.0) * 255.0).astype(np.uint8)  # noqa: E731
    err_bgr = cv2.applyColorMap(to_uint8(err / error_vmax), cv2.COLORMAP_JET)
    err_rgb = cv2.cvtColor(err_bgr, cv2.COLOR_BGR2RGB)
    panels = [to_uint8(np.asarray(gt, np.float64)), to_uint8(np.asarray(pred, np.float64)), err_rgb]
    return np.concatenate(panels, axis=1)


@dataclass(frozen=True)
class ImageMetrics:
    """PSNR (dB) and SSIM of one frame on [0, 1] RGB, data_range 1, full image and mask bbox."""

    psnr_full_db: float
    ssim_full: float
    psnr_mask_bbox_db: float
    ssim_mask_bbox: float
    bbox_pad: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict saying what each number is computed on."""
        return {
            "description": (
                "PSNR/SSIM on [0, 1] RGB, data_range=1, background composited by the caller; SSIM Wang "
                "et al. (11x11 Gaussian, sigma 1.5, population covariance, skimage borders)"
            ),
            "full_image": {"psnr_db": self.psnr_full_db, "ssim": self.ssim_full},
            "mask_bbox": {
                "psnr_db": self.psnr_mask_bbox_db, "ssim": self.ssim_mask_bbox,
                "note": f"crop to the ground-truth mask's bounding box padded by {self.bbox_pad} px",
            },
        }


def evaluate_image(pred: Any, target: Any, mask: Any, pad: int = 0) -> ImageMetrics:
    """PSNR and SSIM on the full image and inside the mask's bounding box.

    Args:
        pred, target: (H, W, 3) float RGB in [0, 1], same background. mask: (H, W) ground-truth mask.
        pad: pixels added around the box (the box is grown to 11 px per side where the image allows,
            because SSIM needs a full window).
    """
    pred_a, target_a = _rgb_pair(pred, target)
    mask_a = _bool_mask(mask, pred_a.shape[:2])
    y0, y1, x0, x1 = mask_bbox(mask_a, pad)
    y0, y1 = _grow(y0, y1, 2 * SSIM_RADIUS + 1, pred_a.shape[0])
    x0, x1 = _grow(x0, x1, 2 * SSIM_RADIUS + 1, pred_a.shape[1])
    pred_c, target_c = pred_a[y0:y1, x0:x1], target_a[y0:y1, x0:x1]
    return ImageMetrics(
        psnr_full_db=psnr(pred_a, target_a), ssim_full=ssim(pred_a, target_a),
        psnr_mask_bbox_db=psnr(pred_c, target_c), ssim_mask_bbox=ssim(pred_c, target_c), bbox_pad=int(pad),
    )


def _grow(lo: int, hi: int, minimum: int, size: int) -> tuple[int, int]:
    """Widen the half-open interval [lo, hi) to at least ``minimum`` inside [0, size)."""
    missing = minimum - (hi - lo)
    if missing <= 0:
        return lo, hi
    lo = max(lo - (missing + 1) // 2, 0)
    hi = min(lo + minimum, size)
    return max(hi - minimum, 0), hi
