"""Fused SDF MLP with its analytic gradient: one autograd node instead of ~40 small torch ops.

    feature, grad_sdf = sdf_head_with_gradient(mlp_input, jacobian, grad_scale, first, last, beta, threshold)
    # mlp_input (P, D = 3 + C), jacobian (P, C, 3)  ->  feature (P, F), grad_sdf (P, 3)

The fast path of :meth:`igavatar.model.fields.SDFField.forward_with_gradient` for the paper's SDF
network (one Softplus hidden layer, no positional encoding). With ``z = W1 x + b1``,
``a = softplus_beta(z)``, ``s = softplus'(z)`` and ``u = s * W2[0]``:

    feature  = W2 a + b2                                        (P, F); sdf = feature[:, 0]
    gin      = W1^T u                                           (P, D): d sdf / d mlp_input
    grad_sdf = gin[:, :3] k[:3] + sum_c gin[:, 3 + c] k[3 + c] J[:, c, :]     (P, 3)

where ``k = grad_scale`` (1 / input scale for the point, the level weights for the hash features)
and ``J`` the hash grid's spatial Jacobian. The reference computes the same with torch ops and
autograd; here the matrix products of the forward and backward run on oneDNN and the weight
gradients on the ``wgrad`` kernel (:mod:`igavatar.model.linear`, rows padded to cached shapes)
and everything between them in
``igavatar/kernels/csrc/sdfhead.cpp``: one pass per element-wise stage, the Jacobian contraction
and its backward without materialising (P, C, 3) outer products in torch. The backward is exact
(``once_differentiable``, like every first-order loss here): gradients to the MLP input, the
Jacobian (hence the hash table and the points, through the grid's own backward) and the four
parameters; tests compare all of them with the reference to float32 tolerance.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.autograd.function import once_differentiable

from igavatar.kernels import kernels_enabled, load_kernel
from igavatar.model.linear import (
    onednn_linear_available, onednn_product, padded_rows, weight_gradients, zero_pad_rows,
)

__all__ = ["sdf_head_applies", "sdf_head_forward", "sdf_head_with_gradient"]


def _numpy(tensor: torch.Tensor):
    """A zero-copy numpy view of a contiguous float32 CPU tensor (no autograd history is read)."""
    return tensor.detach().numpy()


def sdf_head_applies(mlp_input: torch.Tensor, layers: nn.ModuleList) -> bool:
    """Whether the fused path can run: kernels on, one hidden layer, float32 CPU input and weights,
    oneDNN usable and the element-wise kernel built (building it on first call)."""
    return (
        kernels_enabled()
        and len(layers) == 2
        and mlp_input.dim() == 2
        and mlp_input.shape[0] > 0
        and mlp_input.device.type == "cpu"
        and mlp_input.dtype == torch.float32
        and all(p.dtype == torch.float32 and p.device.type == "cpu" for p in layers.parameters())
        and onednn_linear_available()
        and load_kernel("sdfhead") is not None
    )


class _SDFHead(torch.autograd.Function):
    @staticmethod
    def forward(ctx, mlp_input, jacobian, w1, b1, w2, b2, grad_scale, beta: float, threshold: float):
        kernel = load_kernel("sdfhead")
        points = mlp_input.shape[0]
        rows = padded_rows(points)  # oneDNN compiles one kernel per shape: keep a few dozen
        x = zero_pad_rows(mlp_input.detach().contiguous(), rows)
        w1, b1, w2, b2 = (t.detach().contiguous() for t in (w1, b1, w2, b2))
        jacobian = jacobian.detach().contiguous()
        grad_scale = grad_scale.detach().contiguous()
        z = onednn_product(x, w1, b1, False)  # (R, H)
        a, u = torch.empty_like(z), torch.empty_like(z)
        kernel.activation_forward(_numpy(z), _numpy(w2[0]), beta, threshold, _numpy(a), _numpy(u))
        feature = onednn_product(a, w2, b2, False)  # (R, F)
        gin = onednn_product(u, w1.t().contiguous(), None, False)  # (R, D) = u W1
        grad_sdf = z.new_empty((points, 3))
        kernel.gradient_forward(_numpy(gin), _numpy(jacobian), _numpy(grad_scale), _numpy(grad_sdf))
        ctx.save_for_backward(x, z, a, u, gin, jacobian, w1, w2, grad_scale)
        ctx.beta, ctx.threshold = beta, threshold
        return feature[:points], grad_sdf

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_feature, grad_grad_sdf):
        kernel = load_kernel("sdfhead")
        x, z, a, u, gin, jacobian, w1, w2, grad_scale = ctx.saved_tensors
        rows, hidden = z.shape
        points = jacobian.shape[0]
        w1_t = w1.t().contiguous()  # (D, H)
        need_input, need_jacobian = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        # autograd materialises a missing output gradient as zeros, so None is rare: zeros then too.
        grad_u, grad_jacobian, grad_w1_from_gin = None, None, None
        if grad_grad_sdf is not None:
            q = z.new_empty((rows, x.shape[1]))  # d loss / d gin, zero on the padding rows
            grad_jacobian = jacobian.new_empty(jacobian.shape if need_jacobian else (0,) + jacobian.shape[1:])
            kernel.gradient_backward(
                _numpy(grad_grad_sdf.contiguous()), _numpy(gin), _numpy(jacobian), _numpy(grad_scale),
                _numpy(q), _numpy(grad_jacobian),
            )
            grad_u = onednn_product(q, w1, None, False)  # (R, H) = q W1^T
            # gin = u W1 is a layer with weight W1^T: its weight gradient q^T u is (D, H).
            grad_w1_from_gin = weight_gradients(q, u, w1_t, False)[0].t()
            if not need_jacobian:
                grad_jacobian = None
        grad_a, grad_w2, grad_b2 = None, None, None
        if grad_feature is not None:
            grad_feature = zero_pad_rows(grad_feature.contiguous(), rows)
            grad_a = onednn_product(grad_feature, w2.t().contiguous(), None, False)  # (R, H) = gf W2
            grad_w2, grad_b2 = weight_gradients(grad_feature, a, w2, True)
        grad_a = torch.zeros_like(z) if grad_a is None else grad_a
        grad_u = torch.zeros_like(z) if grad_u is None else grad_u
        grad_z, grad_w0 = torch.empty_like(z), z.new_empty(hidden)
        kernel.activation_backward(
            _numpy(z), _numpy(grad_a), _numpy(grad_u), _numpy(w2[0]), ctx.beta, ctx.threshold,
            _numpy(grad_z), _numpy(grad_w0),
        )
        if grad_w2 is None:
            grad_w2, grad_b2 = torch.zeros_like(w2), w2.new_zeros(w2.shape[0])
        grad_w2[0] += grad_w0  # u = s * W2[0]
        grad_w1, grad_b1 = weight_gradients(grad_z, x, w1, True)
        if grad_w1_from_gin is not None:
            grad_w1 = grad_w1 + grad_w1_from_gin
        grad_input = onednn_product(grad_z, w1_t, None, False)[:points] if need_input else None
        return grad_input, grad_jacobian, grad_w1, grad_b1, grad_w2, grad_b2, None, None, None


def sdf_head_with_gradient(
    mlp_input: torch.Tensor,
    jacobian: torch.Tensor,
    grad_scale: torch.Tensor,
    first: nn.Linear,
    last: nn.Linear,
    beta: float,
    threshold: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The SDF MLP and the closed-form gradient of its first output wrt the point (see module doc).

    Args:
        mlp_input: (P, D) with D = 3 + C: the centerd, scaled point, then the C hash features.
        jacobian: (P, C, 3) d hash features / d point.
        grad_scale: (D,) k: d mlp_input[:, :3] / d point per axis, then the level weight of each feature.
        first: Linear D -> H (Softplus after it); last: Linear H -> F.
        beta, threshold: of F.softplus.
    Returns:
        feature (P, F) and grad_sdf (P, 3), differentiable (once) wrt mlp_input, jacobian and the
        layers' parameters. Call only where :func:`sdf_head_applies` holds.
    """
    return _SDFHead.apply(
        mlp_input, jacobian, first.weight, first.bias, last.weight, last.bias, grad_scale, float(beta), float(threshold)
    )


@torch.no_grad()
def sdf_head_forward(
    mlp_input: torch.Tensor, first: nn.Linear, last: nn.Linear, beta: float, threshold: float
) -> torch.Tensor:
    """feature (P, F) = W2 softplus_beta(W1 mlp_input + b1) + b2, without gradients (queries, meshing).

    The same products on oneDNN and the Softplus in one kernel pass; call only where
    :func:`sdf_head_applies` holds and no gradient is wanted.
    """
    points = mlp_input.shape[0]
    rows = padded_rows(points)
    x = zero_pad_rows(mlp_input.contiguous(), rows)
    z = onednn_product(x, first.weight.contiguous(), first.bias.contiguous(), False)
    a = torch.empty_like(z)
    load_kernel("sdfhead").softplus(_numpy(z), float(beta), float(threshold), _numpy(a))
    return onednn_product(a, last.weight.contiguous(), last.bias.contiguous(), False)[:points]
