"""The finite-difference regularizers of the paper's Table 5 ablation: eikonal and curvature terms
from central differences of an SDF callable (as Neuralangelo's, no analytic gradient needed).

    fd_eik, curvature = finite_difference_terms(sdf_fn, x, eps=0.002)   # one set of 6 neighbours

Pure functions of tensors and an SDF callable: no model, renderer or deformer imports.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from igavatar.model.losses import eikonal_loss

__all__ = ["SdfFn", "curvature_loss", "finite_difference_eikonal", "finite_difference_gradient",
           "finite_difference_sdf", "finite_difference_terms"]

SdfFn = Callable[[Tensor], Tensor]
"""x (P, 3) -> signed distance (P,), positive outside."""


def finite_difference_sdf(sdf_fn: SdfFn, x: Tensor, eps: float) -> tuple[Tensor, Tensor]:
    """SDF at the 6 axis neighbours ``x +- eps e_k``, in one batched call of ``sdf_fn``.

    Args:
        sdf_fn: x (P, 3) -> (P,).
        x: (M, 3) points (canonical space for the avatar).
        eps: step in the units of x.

    Returns:
        sdf_plus (M, 3) with column k = d(x + eps e_k), sdf_minus (M, 3) with d(x - eps e_k).
    """
    if x.ndim != 2 or x.shape[-1] != 3:
        raise ValueError(f"finite_difference_sdf: x has shape {tuple(x.shape)}, expected (M, 3)")
    if eps <= 0:
        raise ValueError(f"finite_difference_sdf: eps must be > 0, got {eps}")
    m = x.shape[0]
    offsets = torch.eye(3, device=x.device, dtype=x.dtype) * eps  # (3, 3), row k = eps e_k
    points = torch.cat([x[:, None, :] + offsets, x[:, None, :] - offsets], dim=1)  # (M, 6, 3)
    values = sdf_fn(points.reshape(-1, 3))
    if values.shape != (6 * m,):
        raise ValueError(f"finite_difference_sdf: sdf_fn returned {tuple(values.shape)}, expected ({6 * m},)")
    values = values.reshape(m, 6)
    return values[:, :3], values[:, 3:]


def finite_difference_gradient(sdf_fn: SdfFn, x: Tensor, eps: float) -> Tensor:
    """Central-difference SDF gradient (Neuralangelo's numerical gradient), (M, 3) from x (M, 3)."""
    plus, minus = finite_difference_sdf(sdf_fn, x, eps)
    return (plus - minus) / (2.0 * eps)


def finite_difference_eikonal(sdf_fn: SdfFn, x: Tensor, eps: float) -> Tensor:
    """Eikonal term on numerical gradients (6 extra SDF evaluations per point).

    Args:
        sdf_fn: x (P, 3) -> (P,).
        x: (M, 3) valid sample points (canonical space).
        eps: finite-difference step (Neuralangelo ties it to the finest active hash level).

    Returns:
        Scalar ``mean (|grad_fd d| - 1)^2``; 0 for M = 0.
    """
    if x.shape[0] == 0:
        return x.sum() * 0.0
    return eikonal_loss(finite_difference_gradient(sdf_fn, x, eps))


def curvature_loss(sdf_fn: SdfFn, x: Tensor, eps: float, sdf_at_x: Tensor | None = None) -> Tensor:
    """Neuralangelo curvature term: mean |Laplacian d| by central differences of step eps.

    ``lap(x) = sum_k (d(x + eps e_k) + d(x - eps e_k) - 2 d(x)) / eps^2``. Paper weight ~5e-4 with
    a linear warm-up (:func:`linear_warmup`).

    Args:
        sdf_fn: x (P, 3) -> (P,).
        x: (M, 3) points.
        eps: finite-difference step.
        sdf_at_x: (M,) d(x) if already computed (saves one evaluation per point).

    Returns:
        Scalar; 0 for M = 0.
    """
    return finite_difference_terms(sdf_fn, x, eps, sdf_at_x)[1]


def finite_difference_terms(
    sdf_fn: SdfFn, x: Tensor, eps: float, sdf_at_x: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Numerical eikonal and curvature terms from one shared set of 6 neighbour evaluations.

    Args:
        sdf_fn, x, eps, sdf_at_x: as in :func:`curvature_loss`.

    Returns:
        (eikonal, curvature) scalars.
    """
    if x.shape[0] == 0:
        zero = x.sum() * 0.0
        return zero, zero
    plus, minus = finite_difference_sdf(sdf_fn, x, eps)
    if sdf_at_x is None:
        sdf_at_x = sdf_fn(x)
    if sdf_at_x.shape != (x.shape[0],):
        raise ValueError(
            f"finite_difference_terms: sdf_at_x has shape {tuple(sdf_at_x.shape)}, expected ({x.shape[0]},)"
        )
    gradient = (plus - minus) / (2.0 * eps)
    laplacian = (plus + minus - 2.0 * sdf_at_x[:, None]).sum(dim=-1) / eps**2
    return eikonal_loss(gradient), laplacian.abs().mean()
