"""Adam for training and shape initialization: PyTorch's fused kernel on the fast path.

    optimizer = adam([{"params": table, "lr": 1e-2}, {"params": mlps, "lr": 1e-3}], betas=(0.9, 0.99), eps=1e-15)

``torch.optim.Adam`` on CPU defaults to its per-tensor loop: for the 1.2 M x 2 hash table that is
a dozen full passes over 10 MB with a temporary per op (about 8 ms a step on 2 cores, measured).
``fused=True`` does the whole update in one pass per tensor (under 1 ms). Same update rule, same
state dict; results agree to float32 rounding (tested). ``IGAVATAR_KERNELS=0`` keeps the loop
implementation, the reference, like every other fast path.

``SparseAdam`` is the rule tiny-cuda-nn applies to a hash table (Instant-NGP, and the paper's code
through it): an entry whose gradient is exactly zero this step is left alone, its moments and its
step count included. Dense Adam with Instant-NGP's eps = 1e-15 keeps moving such an entry: one
gradient, however small, gives it about ``lr * sign(g) * 0.9**k / 0.995**k`` on each of the next
~20 steps (m / sqrt(v) does not depend on the gradient's size), about ten full-lr steps in all,
with nothing to pull it back where no ray reaches. Measured: that drift opened the canonical ankle
of a benchmark subject (SDF -22 mm -> +20 mm on the bone's axis over the ten steps after one
gradient reached it; tests/benchmarks/results/sparse-adam.md).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import torch

from igavatar.kernels import kernels_enabled, load_kernel

__all__ = ["SparseAdam", "adam"]

_FUSED_DEVICES = ("cpu", "cuda")


def _parameters(params: Iterable) -> list[torch.Tensor]:
    params = list(params)
    if params and isinstance(params[0], dict):
        return [p for group in params for p in group["params"]]
    return params


def adam(params: Iterable, **options) -> torch.optim.Adam:
    """``torch.optim.Adam(params, **options)``, fused where the fast path is on and it applies.

    Fused applies to parameters all on one CPU or CUDA device.
    """
    params = list(params)
    tensors = _parameters(params)
    devices = {p.device for p in tensors}
    fused = kernels_enabled() and len(devices) == 1 and next(iter(devices)).type in _FUSED_DEVICES
    return torch.optim.Adam(params, fused=fused or None, **options)


class SparseAdam(torch.optim.Optimizer):
    """Adam that updates only the entries with a non-zero gradient (tiny-cuda-nn's hash-table rule).

    Per entry: on a step where its gradient g != 0,
        n += 1;  m = b1 m + (1 - b1) g;  v = b2 v + (1 - b2) g^2
        x -= lr * sqrt(1 - b2^n) / (1 - b1^n) * m / (sqrt(v) + eps)
    and on a step where g == 0 nothing of it changes. The bias correction uses the entry's own
    count n, so an entry first reached late starts like a fresh Adam. When every entry has a
    gradient on every step this is torch's Adam (up to where eps enters; tested).

    Args:
        params: tensors or parameter groups (any shape; the rule is elementwise).
        lr, betas, eps: as torch.optim.Adam.
    """

    def __init__(self, params: Iterable, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.99), eps: float = 1e-15):
        super().__init__(params, {"lr": lr, "betas": betas, "eps": eps})
        self._corrections: dict[tuple[float, float], torch.Tensor] = {}   # the kernel's bias-correction tables

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            for param in group["params"]:
                if param.grad is None:
                    continue
                if param.grad.is_sparse:
                    raise RuntimeError("SparseAdam takes dense gradients with zeros where an entry was not reached")
                state = self.state[param]
                if not state:
                    state["exp_avg"] = torch.zeros_like(param, memory_format=torch.contiguous_format)
                    state["exp_avg_sq"] = torch.zeros_like(param, memory_format=torch.contiguous_format)
                    state["steps"] = torch.zeros_like(param, dtype=torch.int32, memory_format=torch.contiguous_format)
                elif state["steps"].dtype != torch.int32:
                    # Optimizer.load_state_dict casts every state tensor but "step" to the parameter's dtype.
                    state["steps"] = state["steps"].to(torch.int32).contiguous()
                # Asked for only by a CPU tensor (a CUDA run never builds it); None when disabled or unbuildable.
                kernel = load_kernel("sparseadam") if _kernel_applies(param) else None
                if kernel is not None:
                    self._kernel_step(kernel, param, state, group)
                else:
                    _reference_step(param, state, group)
        return loss

    def _kernel_step(self, kernel, param: torch.Tensor, state: dict, group: dict) -> None:
        beta1, beta2 = group["betas"]
        table = self._corrections.get((beta1, beta2))
        if table is None:
            table = self._corrections[(beta1, beta2)] = _bias_corrections(beta1, beta2)
        kernel.step(param.detach().view(-1).numpy(), param.grad.detach().contiguous().view(-1).numpy(),
                    state["exp_avg"].view(-1).numpy(), state["exp_avg_sq"].view(-1).numpy(),
                    state["steps"].view(-1).numpy(), table.numpy(), float(group["lr"]), float(beta1), float(beta2),
                    float(group["eps"]))


def _kernel_applies(param: torch.Tensor) -> bool:
    return param.device.type == "cpu" and param.dtype == torch.float32 and param.is_contiguous()


def _bias_corrections(beta1: float, beta2: float) -> torch.Tensor:
    """(K,) float32: sqrt(1 - b2^n) / (1 - b1^n) for n < K; the last entry (1.0 in float32) stands
    for every larger n. K is where 1 - b2^n and 1 - b1^n both round to 1 in float32."""
    slowest = max(beta1, beta2)
    size = min(int(math.ceil(17.0 / max(1e-6, 1.0 - slowest))) + 2, 20_000_000)
    n = torch.arange(size, dtype=torch.float64).clamp_min(1)
    return (torch.sqrt(1 - beta2**n) / (1 - beta1**n)).to(torch.float32)


def _reference_step(param: torch.Tensor, state: dict, group: dict) -> None:
    """The rule in plain PyTorch on the reached entries only (the kernel's reference)."""
    beta1, beta2 = group["betas"]
    grad = param.grad.reshape(-1)
    reached = torch.nonzero(grad).squeeze(1)                      # (K,) flat indices
    g = grad[reached]
    exp_avg, exp_avg_sq, steps = (state[key].view(-1) for key in ("exp_avg", "exp_avg_sq", "steps"))
    m = exp_avg[reached].mul_(beta1).add_(g, alpha=1 - beta1)
    v = exp_avg_sq[reached].mul_(beta2).addcmul_(g, g, value=1 - beta2)
    n = steps[reached] + 1
    exp_avg[reached], exp_avg_sq[reached], steps[reached] = m, v, n
    n = n.to(torch.float64)
    rate = (group["lr"] * torch.sqrt(1 - beta2**n) / (1 - beta1**n)).to(m.dtype)
    update = -rate * m / (v.sqrt() + group["eps"])
    if param.is_contiguous():
        param.view(-1).index_add_(0, reached, update)
    else:
        param.copy_(param.reshape(-1).index_add(0, reached, update).view_as(param))
