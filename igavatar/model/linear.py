"""Fully connected layers on oneDNN's float32 matrix products, behind the plain `F.linear` reference.

    h = linear(pad_rows(x), layer.weight, layer.bias, relu=True)   # relu(x W^T + b): (P', in) -> (P', out)
    out = linear(h, last.weight, last.bias)[: x.shape[0]]              # drop the padding rows

Why: torch's CPU `F.linear`/`mm` call MKL's sgemm, which on this project's reference machine (an
AMD EPYC with AVX-512) runs far below the chip's float32 peak: a (17k, 39) x (39, 128) product takes
5.2 ms where oneDNN, also inside torch, takes 0.5 ms; (17k, 128) x (128, 128) 3.8 ms against 1.9 ms
(tests/benchmarks/bench_speed.py measures it in a training step). Both are float32 products, so
the results agree to float32 rounding (tests/test_linear.py), and the ReLU is fused into the
product's output pass.

The fast path runs the forward product and the input gradient on oneDNN (``torch.ops.mkldnn.
_linear_pointwise``, the op torch's own compiler emits for CPU linear layers) and the weight and
bias gradients on the ``wgrad`` kernel (``igavatar/kernels/csrc/wgrad.cpp``: ``grad^T x`` read
straight from the two row-major (P, .) arrays, 1.7-4x faster than oneDNN's inner-product backward,
which first copies both into its own layout; one copy per ISA, sized to its registers, chosen on
the CPU's features). Layers with neither side a multiple of 16, or
without the kernel built, use that oneDNN backward (``aten::mkldnn_linear_backward_weights``).
It is used when
`kernels_enabled()`, for 2-D float32 CPU inputs, and when this torch build has the op; otherwise,
and always with ``IGAVATAR_KERNELS=0``, the layer is plain `F.linear` (+ `relu`). The fast path is
differentiable once (like every first-order training loss here); a double backward raises.
"""

from __future__ import annotations

import logging
import threading

import torch
import torch.nn.functional as F
from torch.autograd.function import once_differentiable

from igavatar.kernels import kernels_enabled, load_kernel

__all__ = [
    "linear", "linear_reference", "onednn_linear_available", "onednn_product", "onednn_weight_gradients",
    "pad_rows", "padded_rows", "weight_gradients", "weight_gradients_reference", "zero_pad_rows",
]

_LOG = logging.getLogger(__name__)
_LOCK = threading.Lock()
_AVAILABLE: bool | None = None


def linear_reference(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, relu: bool = False) -> torch.Tensor:
    """``F.linear(x, weight, bias)`` then `relu` if asked: x (P, in), weight (out, in), bias (out,)."""
    y = F.linear(x, weight, bias)
    return torch.relu(y) if relu else y


def onednn_product(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, relu: bool) -> torch.Tensor:
    """x (P, in) @ weight (out, in)^T + bias (out,), ReLU fused when `relu`; contiguous float32."""
    return torch.ops.mkldnn._linear_pointwise(x, weight, bias, "relu" if relu else "none", [], "")


def onednn_weight_gradients(
    grad: torch.Tensor, x: torch.Tensor, weight: torch.Tensor, with_bias: bool
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """grad (P, out)^T x (P, in) and grad summed over rows, by oneDNN's inner-product backward
    (its long reduction over P is ~1.2-1.6x faster than `mm` here); dense (out, in), (out,) or None."""
    grad_weight, grad_bias = torch.ops.aten.mkldnn_linear_backward_weights(
        grad.to_mkldnn(), x.to_mkldnn(), weight, with_bias
    )
    return grad_weight, grad_bias if with_bias else None


def weight_gradients_reference(
    grad: torch.Tensor, x: torch.Tensor, with_bias: bool
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``grad.t() @ x`` (out, in) and ``grad.sum(0)`` (out,) or None: what the fast paths compute."""
    return grad.t() @ x, grad.sum(0) if with_bias else None


def weight_gradients(
    grad: torch.Tensor, x: torch.Tensor, weight: torch.Tensor, with_bias: bool
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """A layer's weight and bias gradients from its output gradient and input.

    Args:
        grad: (P, out) gradient of the layer's output; x: (P, in) its input; float32 CPU.
        weight: (out, in), only read by the oneDNN fallback (its primitive wants the shape).
        with_bias: also return the bias gradient.
    Returns:
        grad_weight (out, in) = grad^T x and grad_bias (out,) = grad summed over rows (or None);
        on the ``wgrad`` kernel when ``in`` or ``out`` is a multiple of 16, else on oneDNN.
    """
    kernel = load_kernel("wgrad")
    out_dim, in_dim = grad.shape[1], x.shape[1]
    if kernel is None or (in_dim % 16 and out_dim % 16):
        return onednn_weight_gradients(grad, x, weight, with_bias)
    grad, x = grad.detach().contiguous(), x.detach().contiguous()
    empty = grad.new_empty(0)
    grad_bias = grad.new_empty(out_dim) if with_bias else empty
    if in_dim % 16 == 0:  # vectors along `in`: grad^T x directly
        grad_weight = grad.new_empty((out_dim, in_dim))
        kernel.outer_sum(grad.numpy(), x.numpy(), grad_weight.numpy(), grad_bias.numpy(), empty.numpy())
    else:  # vectors along `out`: (x^T grad)^T, a small (in, out) transpose
        grad_weight_t = grad.new_empty((in_dim, out_dim))
        kernel.outer_sum(x.numpy(), grad.numpy(), grad_weight_t.numpy(), empty.numpy(), grad_bias.numpy())
        grad_weight = grad_weight_t.t().contiguous()
    return grad_weight, grad_bias if with_bias else None


def onednn_linear_available() -> bool:
    """Whether this torch build runs oneDNN's linear op correctly (checked once on a tiny product)."""
    global _AVAILABLE
    if _AVAILABLE is not None:
        return _AVAILABLE
    with _LOCK:
        if _AVAILABLE is None:
            try:
                generator = torch.Generator().manual_seed(0)
                x = torch.randn(5, 7, generator=generator)
                weight = torch.randn(3, 7, generator=generator)
                bias = torch.randn(3, generator=generator)
                grad = torch.randn(5, 3, generator=generator)
                grad_weight, grad_bias = onednn_weight_gradients(grad, x, weight, True)
                ok = (
                    torch.backends.mkldnn.is_available()
                    and torch.allclose(onednn_product(x, weight, bias, True), linear_reference(x, weight, bias, True), atol=1e-5)
                    and torch.allclose(grad_weight, grad.t() @ x, atol=1e-5)
                    and torch.allclose(grad_bias, grad.sum(0), atol=1e-5)
                )
                reason = "its result differs from F.linear"
            except Exception as error:  # noqa: BLE001 - any failure means "use F.linear"
                ok, reason = False, " ".join(str(error).split())[:200]
            if not ok:
                _LOG.warning("igavatar: oneDNN linear layers unavailable (%s); using F.linear", reason)
            _AVAILABLE = bool(ok)
    return _AVAILABLE


class _OneDnnLinear(torch.autograd.Function):
    """relu?(x W^T + b) with oneDNN forward and input gradient, :func:`weight_gradients` for W and b."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, relu: bool) -> torch.Tensor:
        x = x.contiguous()
        weight = weight.contiguous()
        y = onednn_product(x, weight, None if bias is None else bias.contiguous(), relu)
        # The ReLU's mask is read back from its output, as torch's own relu backward does.
        ctx.save_for_backward(x, weight, y if relu else None)
        ctx.relu = relu
        ctx.has_bias = bias is not None
        return y

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_y: torch.Tensor):
        x, weight, y = ctx.saved_tensors
        grad = grad_y.contiguous()
        if ctx.relu:
            grad = torch.ops.aten.threshold_backward(grad, y, 0)
        grad_x = grad_weight = grad_bias = None
        if ctx.needs_input_grad[0]:
            grad_x = onednn_product(grad, weight.t().contiguous(), None, False)
        if ctx.needs_input_grad[1]:
            grad_weight, grad_bias = weight_gradients(grad, x, weight, ctx.has_bias)
        elif ctx.has_bias and ctx.needs_input_grad[2]:
            grad_bias = grad.sum(0)
        return grad_x, grad_weight, grad_bias if ctx.needs_input_grad[2] else None, None


def _fast_path_applies(x: torch.Tensor) -> bool:
    return (
        kernels_enabled()
        and x.dim() == 2
        and x.shape[0] > 0
        and x.device.type == "cpu"
        and x.dtype == torch.float32
        and onednn_linear_available()
    )


def padded_rows(rows: int) -> int:
    """`rows` rounded up to its bucket: a multiple of max(256, 2^(floor(log2 rows) - 4)), i.e. at
    most ~6 % more rows, and about 16 distinct sizes per doubling of the row count."""
    step = max(256, 1 << max(0, rows.bit_length() - 5))
    return -(-rows // step) * step


def pad_rows(x: torch.Tensor) -> torch.Tensor:
    """x (P, C) with zero rows appended up to :func:`padded_rows` when the fast path applies, else x.

    oneDNN compiles one kernel per matrix shape (about 8 ms each on 2 cores) and caches it; the
    number of samples in a training step changes every step, so an MLP run on its exact row count
    would compile on every call. Padding the MLP's *input* once, running every layer on the padded
    rows and slicing the output (``out[:P]``) keeps a few dozen shapes in the cache. The padded
    rows receive zero output gradient, so they add nothing to any parameter's gradient.
    """
    if not _fast_path_applies(x):
        return x
    return zero_pad_rows(x, padded_rows(x.shape[0]))


def zero_pad_rows(x: torch.Tensor, rows: int) -> torch.Tensor:
    """x (P, C) with zero rows appended up to (rows, C); x itself when P >= rows."""
    extra = rows - x.shape[0]
    return torch.cat((x, x.new_zeros((extra, x.shape[1])))) if extra > 0 else x


def linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None, relu: bool = False) -> torch.Tensor:
    """A fully connected layer, ``relu(x W^T + b)`` when `relu`, else ``x W^T + b``.

    Args:
        x: (P, in). weight: (out, in). bias: (out,) or None. relu: fuse a ReLU on the output.
    Returns:
        (P, out), on oneDNN when the fast path applies (see the module docstring), else
        :func:`linear_reference`.
    """
    if _fast_path_applies(x) and weight.dtype == torch.float32 and (bias is None or bias.dtype == torch.float32):
        return _OneDnnLinear.apply(x, weight, bias, relu)
    return linear_reference(x, weight, bias, relu)
