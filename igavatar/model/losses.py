"""Training losses of InstantGeoAvatar (paper Eq. 7 and 9); the Table 5 ablation's finite-difference
regularizers are in igavatar.model.fd_losses.

    terms = {"rgb": rgb_loss(out.rgb, rgb_gt), "smooth": smooth_loss_along_ray(out.gradient, out.valid)}
    loss = total_loss(terms, LossWeights())   # out: igavatar.render.volume.RenderOutput

Pure functions of tensors: no model, renderer or deformer imports. Per-sample inputs use the
renderer's padded layout: ``gradients (R, S, 3)`` with ``valid (R, S)``; only valid samples count.

Choices (see each docstring): ``rgb_loss`` defaults to MSE, as the released InstantGeoAvatar code
(the paper only says "photometric loss"; InstantAvatar used Huber with delta 0.1, available as
``kind="huber"``). ``alpha_loss`` defaults to L1 as the paper states (the release uses MSE).
``eikonal_loss`` averages over valid samples only (the release also averages the dummy gradients
of empty slots). ``smooth_loss_along_ray`` is Eq. 9 with the literal ``1 / N_s^i`` normalizer.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = [
    "LossWeights",
    "alpha_loss",
    "eikonal_loss",
    "linear_warmup",
    "rgb_loss",
    "smooth_loss_along_ray",
    "smooth_loss_neighbour_rays",
    "total_loss",
]

_NORMAL_EPS = 1e-12


@dataclass(frozen=True)
class LossWeights:
    """Weights of the loss terms; defaults are the paper's (Eq. 7 and Sec. 4)."""

    rgb: float = 10.0
    """lambda_rgb, photometric term."""
    alpha: float = 0.1
    """lambda_alpha, L1 between rendered opacity and the mask."""
    eikonal: float = 0.1
    """lambda_Eik with analytic gradients (the release uses 0.01; the paper 0.1)."""
    smooth: float = 1.0
    """lambda_smooth, along-ray normal smoothness (paper: good anywhere in [0.5, 1.5])."""
    fd_eikonal: float = 0.1
    """Ablation: eikonal on finite-difference gradients (Neuralangelo), replacing ``eikonal``."""
    curvature: float = 5e-4
    """Ablation: Neuralangelo curvature term; scale it by :func:`linear_warmup` during warm-up."""
    body_inside: float = 0.0
    """Hinge keeping the SDF at points inside the naked template (confirmed by the masks) no larger
    than the template's, plus a slack (igavatar.training.body_prior); 0 = off."""
    free_space: float = 0.0
    """Hinge keeping the SDF at canonical points that the masks' visual hull rules out at least
    as large as their distance to the hull (igavatar.training.visual_hull); 0 = off."""


def total_loss(terms: Mapping[str, Tensor], weights: LossWeights) -> Tensor:
    """Weighted sum ``sum_k weights.k * terms[k]``; every key must be a LossWeights field.

    Args:
        terms: name -> scalar tensor.
        weights: the weights.

    Returns:
        Scalar tensor.
    """
    names = {f.name for f in fields(LossWeights)}
    unknown = sorted(set(terms) - names)
    if unknown:
        raise ValueError(f"total_loss: unknown terms {unknown}; known: {sorted(names)}")
    if not terms:
        raise ValueError("total_loss: no terms given")
    return sum(getattr(weights, name) * value for name, value in terms.items())  # type: ignore[return-value]


def rgb_loss(
    rgb_pred: Tensor,
    rgb_target: Tensor,
    kind: Literal["mse", "l1", "huber"] = "mse",
    huber_delta: float = 0.1,
) -> Tensor:
    """Photometric loss on composited color.

    Args:
        rgb_pred, rgb_target: (R, 3) (or any equal shapes) in [0, 1]; the target must be
            composited on the same background as the prediction.
        kind: "mse" (released InstantGeoAvatar, default), "l1", or "huber" (InstantAvatar, delta 0.1).
        huber_delta: Huber transition point.

    Returns:
        Scalar mean over all elements.
    """
    if rgb_pred.shape != rgb_target.shape:
        raise ValueError(f"rgb_loss: prediction {tuple(rgb_pred.shape)} vs target {tuple(rgb_target.shape)}")
    if kind == "mse":
        return F.mse_loss(rgb_pred, rgb_target)
    if kind == "l1":
        return F.l1_loss(rgb_pred, rgb_target)
    if kind == "huber":
        return F.huber_loss(rgb_pred, rgb_target, delta=huber_delta)
    raise ValueError(f"rgb_loss: kind must be 'mse', 'l1' or 'huber', got {kind!r}")


def alpha_loss(opacity: Tensor, mask: Tensor, kind: Literal["l1", "mse"] = "l1") -> Tensor:
    """Mask loss between rendered opacity and the foreground mask.

    Args:
        opacity: (R,) accumulated weights in [0, 1].
        mask: (R,) target in [0, 1] (bool accepted).
        kind: "l1" (paper, default) or "mse" (released code).

    Returns:
        Scalar mean.
    """
    if opacity.shape != mask.shape:
        raise ValueError(f"alpha_loss: opacity {tuple(opacity.shape)} vs mask {tuple(mask.shape)}")
    mask = mask.to(opacity.dtype)
    if kind == "l1":
        return F.l1_loss(opacity, mask)
    if kind == "mse":
        return F.mse_loss(opacity, mask)
    raise ValueError(f"alpha_loss: kind must be 'l1' or 'mse', got {kind!r}")


def eikonal_loss(gradients: Tensor, valid: Tensor | None = None) -> Tensor:
    """Eikonal term ``mean (|grad d| - 1)^2`` over valid samples only.

    Args:
        gradients: (M, 3) SDF gradients of valid samples, or (..., 3) together with ``valid``.
        valid: None, or (...) bool selecting the samples that count (e.g. RenderOutput.valid).

    Returns:
        Scalar; 0 when there are no samples.
    """
    if gradients.shape[-1] != 3:
        raise ValueError(f"eikonal_loss: gradients have shape {tuple(gradients.shape)}, expected (..., 3)")
    if valid is not None:
        if valid.shape != gradients.shape[:-1]:
            raise ValueError(
                f"eikonal_loss: valid {tuple(valid.shape)} does not match gradients {tuple(gradients.shape)}"
            )
        gradients = gradients[valid]
    gradients = gradients.reshape(-1, 3)
    if gradients.shape[0] == 0:
        return gradients.sum() * 0.0
    return ((torch.linalg.vector_norm(gradients, dim=-1) - 1.0) ** 2).mean()


def _pair_term(n_a: Tensor, n_b: Tensor) -> Tensor:
    """Eq. 9 summand for unit normals at the two ends of an interval: (...) from (..., 3) pairs."""
    n_mid = 0.5 * (n_a + n_b)
    return torch.linalg.vector_norm(n_mid - n_a, dim=-1) + torch.linalg.vector_norm(n_mid - n_b, dim=-1)


def smooth_loss_along_ray(
    gradients: Tensor,
    valid: Tensor,
    normalization: Literal["samples", "pairs", "released"] = "samples",
    pairs: Literal["valid", "adjacent", "monotone"] = "valid",
    t_starts: Tensor | None = None,
    t_ends: Tensor | None = None,
    positions: Tensor | None = None,
    sdf: Tensor | None = None,
    band: float | None = None,
) -> Tensor:
    """Paper Eq. 9: normals at consecutive valid samples of each ray should agree.

    ``n_hat_j = g_j / |g_j|``, ``n_bar_j = (n_hat_j + n_hat_{j+1}) / 2`` and each pair adds
    ``|n_bar_j - n_hat_j| + |n_bar_j - n_hat_{j+1}|`` (which equals ``|n_hat_{j+1} - n_hat_j|``).
    Pairs are consecutive in the ray's order of *valid* samples: two valid samples separated by
    invalid slots (skipped empty space) form a pair, exactly as in a packed sample layout, so the
    result is the same before and after :func:`igavatar.render.sampler.compact_samples`.

    ``pairs="adjacent"`` keeps only pairs whose intervals touch (``t_starts`` of the later sample
    equals ``t_ends`` of the earlier one): a ray that leaves one surface (a forearm), crosses
    skipped empty space and enters another (the torso) then does not pull the normals of the two
    surfaces together. Eq. 9 does not say which; the literal reading is ``"valid"``.

    Normalization: per ray, the pair sum is divided by ``N_s^i`` = its number of valid samples,
    as Eq. 9 writes (``normalization="pairs"`` divides by ``N_s^i - 1`` instead, a true mean per
    pair). The result is the mean over rays with at least two valid samples; rays with fewer have
    no pair and are not counted, so the value does not depend on how many rays miss the body.
    ``normalization="released"`` is the scale of the authors' code: each summand squared
    (``|n_bar - n_hat|^2``, i.e. ``|n_hat_{j+1} - n_hat_j|^2 / 2`` per pair) and the sum divided by
    every pair slot of every ray (R x (S - 1)), empty ones included; two to three orders of
    magnitude weaker than Eq. 9, and its gradient fades as neighbouring normals align.

    Args:
        gradients: (R, S, 3) SDF gradients (or normals; only directions matter).
        valid: (R, S) bool.
        normalization: "samples" (Eq. 9, default) or "pairs".
        pairs: "valid" (consecutive valid samples, default) or "adjacent" (touching intervals only).
        t_starts, t_ends: (R, S) sample intervals along the ray; required for ``pairs="adjacent"``.
        positions: (R, S, 3) sample positions in the gradients' frame; required for
            ``pairs="monotone"``.
        sdf, band: (R, S) SDF values and meters: only samples with ``|sdf| < band`` take part, as
            if the others were invalid: the surface's normals are smoothed, not those of the
            distance field in empty space (under a crotch, whose smoothing fills the crease).
            None: every valid sample.

    Returns:
        Scalar; 0 when no ray has a pair.
    """
    _check_smooth_inputs(gradients, valid, normalization, pairs, t_starts, t_ends, positions, sdf, band)
    valid = valid.bool()
    if band is not None:
        valid = valid & (sdf.detach().abs() < band)
    n_hat = F.normalize(gradients, dim=-1, eps=_NORMAL_EPS)
    pack, num_valid = _packer(valid)
    n_packed = pack(n_hat)
    s = valid.shape[1]
    valid_packed = torch.arange(s, device=valid.device)[None, :] < num_valid[:, None]
    pair_valid = valid_packed[:, :-1] & valid_packed[:, 1:]  # (R, S-1)
    if pairs == "adjacent":
        pair_valid = pair_valid & _touching(pack(t_starts.detach()), pack(t_ends.detach()))
    elif pairs == "monotone":
        pair_valid = pair_valid & _one_way(n_packed.detach(), pack(positions.detach()))
    if normalization == "released":
        return _released_form(n_packed, pair_valid)
    return _eq9_form(gradients, n_packed, pair_valid, num_valid, per_sample=normalization == "samples")


def _check_smooth_inputs(gradients: Tensor, valid: Tensor, normalization: str, pairs: str, t_starts: Tensor | None,
                         t_ends: Tensor | None, positions: Tensor | None, sdf: Tensor | None, band: float | None) -> None:
    """ValueError unless smooth_loss_along_ray's inputs fit together (the tensors its modes need)."""
    if gradients.ndim != 3 or gradients.shape[-1] != 3 or valid.shape != gradients.shape[:2]:
        raise ValueError(
            f"smooth_loss_along_ray: gradients {tuple(gradients.shape)} and valid "
            f"{tuple(valid.shape)} must be (R, S, 3) and (R, S)"
        )
    if normalization not in ("samples", "pairs", "released"):
        raise ValueError(
            f"smooth_loss_along_ray: normalization must be 'samples', 'pairs' or 'released', got {normalization!r}"
        )
    if pairs not in ("valid", "adjacent", "monotone"):
        raise ValueError(f"smooth_loss_along_ray: pairs must be 'valid', 'adjacent' or 'monotone', got {pairs!r}")
    if pairs == "adjacent" and (
        t_starts is None or t_ends is None or t_starts.shape != valid.shape or t_ends.shape != valid.shape
    ):
        raise ValueError(
            "smooth_loss_along_ray: pairs='adjacent' needs t_starts and t_ends of shape "
            f"{tuple(valid.shape)}"
        )
    if pairs == "monotone" and (positions is None or positions.shape != gradients.shape):
        raise ValueError(
            f"smooth_loss_along_ray: pairs='monotone' needs positions of shape {tuple(gradients.shape)}"
        )
    if band is not None and (sdf is None or sdf.shape != valid.shape):
        raise ValueError(f"smooth_loss_along_ray: band needs sdf of shape {tuple(valid.shape)}")


def _packer(valid: Tensor) -> tuple[Callable[[Tensor], Tensor], Tensor]:
    """A function packing each ray's valid samples to the front in order, and the count (R,) of them.

    Slot = number of valid samples before it; invalid ones go to a spare last column and are cut,
    so consecutive valid samples are adjacent whatever gaps separated them.
    """
    r, s = valid.shape
    dest = torch.where(valid, torch.cumsum(valid, dim=1) - 1, s)

    def pack(values: Tensor) -> Tensor:
        """(R, S, ...) per-slot values -> the same values of the valid samples, packed to the front."""
        index = dest.reshape(r, s, *([1] * (values.ndim - 2))).expand_as(values)
        return values.new_zeros((r, s + 1, *values.shape[2:])).scatter(1, index, values)[:, :s]

    return pack, valid.sum(dim=1)


def _touching(starts: Tensor, ends: Tensor) -> Tensor:
    """(R, S-1) whether consecutive packed intervals touch.

    Touching intervals share a boundary up to rounding; a skipped bin leaves a gap of one whole
    interval, so a tolerance of a hundredth of the interval separates the two.
    """
    tolerance = 1e-2 * (ends - starts)[:, :-1].abs()
    return (starts[:, 1:] - ends[:, :-1]).abs() <= tolerance


def _one_way(normals: Tensor, positions: Tensor) -> Tensor:
    """(R, S-1) whether the SDF runs one way between consecutive packed samples: its slope along the
    chord has one sign at both ends (the unit normals have the gradients' signs, so they serve)."""
    chord = positions.diff(dim=1)  # (R, S-1, 3)
    slope_a = (normals[:, :-1] * chord).sum(dim=-1)
    slope_b = (normals[:, 1:] * chord).sum(dim=-1)
    return slope_a * slope_b > 0


def _released_form(n_packed: Tensor, pair_valid: Tensor) -> Tensor:
    """The authors' code's scale: squared summands, summed over pairs, divided by every pair slot."""
    r, s = n_packed.shape[:2]
    n_a, n_b = n_packed[:, :-1], n_packed[:, 1:]
    n_mid = 0.5 * (n_a + n_b)
    term = (n_mid - n_a).square().sum(dim=-1) + (n_mid - n_b).square().sum(dim=-1)
    return torch.where(pair_valid, term, torch.zeros_like(term)).sum() / max(1, r * (s - 1))


def _eq9_form(gradients: Tensor, n_packed: Tensor, pair_valid: Tensor, num_valid: Tensor, per_sample: bool) -> Tensor:
    """Eq. 9: per ray, the pair sum over its valid samples (or pairs); the mean over rays with a pair."""
    term = _pair_term(n_packed[:, :-1], n_packed[:, 1:])
    per_ray_sum = torch.where(pair_valid, term, torch.zeros_like(term)).sum(dim=1)
    has_pair = num_valid >= 2
    if not bool(has_pair.any()):
        return gradients.sum() * 0.0
    denom = num_valid if per_sample else num_valid - 1
    return (per_ray_sum[has_pair] / denom[has_pair].to(per_ray_sum.dtype)).mean()


def smooth_loss_neighbour_rays(
    gradients: Tensor, valid: Tensor, include_vertical: bool = False
) -> Tensor:
    """Screen-space variant (released code): same sample slot on neighbouring pixels of a patch.

    Pairs are (pixel (y, x), pixel (y, x + 1)) at the same slot s, and with
    ``include_vertical`` also (y, x) with (y + 1, x); both samples must be valid. Pairs never cross
    a patch row or a patch boundary (the release's flattened layout paired the last pixel of a
    row with the first of the next, and across patches). Each pair adds the Eq. 9 summand; the
    result is the mean over valid pairs (the release divided by all slots). Use the uncompacted
    sample layout: only then does slot s mean about the same depth on neighbouring rays.

    Args:
        gradients: (..., Hp, Wp, S, 3) per-sample gradients of patches of rays.
        valid: (..., Hp, Wp, S) bool.
        include_vertical: also pair vertically adjacent pixels.

    Returns:
        Scalar; 0 when there is no valid pair.
    """
    if gradients.ndim < 4 or gradients.shape[-1] != 3 or valid.shape != gradients.shape[:-1]:
        raise ValueError(
            f"smooth_loss_neighbour_rays: gradients {tuple(gradients.shape)} and valid "
            f"{tuple(valid.shape)} must be (..., Hp, Wp, S, 3) and (..., Hp, Wp, S)"
        )
    valid = valid.bool()
    n_hat = F.normalize(gradients, dim=-1, eps=_NORMAL_EPS)
    total = gradients.new_zeros(())
    count = 0
    # (normal a, normal b, both valid) for each neighbour direction; slicing stays inside a patch.
    pairs = [(n_hat[..., :, :-1, :, :], n_hat[..., :, 1:, :, :], valid[..., :, :-1, :] & valid[..., :, 1:, :])]
    if include_vertical:
        pairs.append(
            (n_hat[..., :-1, :, :, :], n_hat[..., 1:, :, :, :], valid[..., :-1, :, :] & valid[..., 1:, :, :])
        )
    for n_a, n_b, pair_valid in pairs:
        term = _pair_term(n_a, n_b)
        total = total + torch.where(pair_valid, term, torch.zeros_like(term)).sum()
        count += int(pair_valid.sum())
    if count == 0:
        return gradients.sum() * 0.0
    return total / count


def linear_warmup(step: int, warmup_steps: int) -> float:
    """Weight factor rising linearly from 0 at step 0 to 1 at ``warmup_steps`` (then 1)."""
    if warmup_steps <= 0:
        return 1.0
    return min(1.0, max(0.0, step / warmup_steps))
