"""The fused Adam of the fast path against torch's reference loop, the resume flags, and SparseAdam
(tiny-cuda-nn's hash-table rule) against torch's Adam, with its C++ kernel against its reference."""

from __future__ import annotations

import pytest
import torch

from igavatar import kernels
from igavatar.training.optim import SparseAdam, adam
from tests.conftest import built_kernel


def _run(fused_on: bool, steps: int = 6) -> list[torch.Tensor]:
    """Two groups (a hash-table-like tensor and an MLP weight), fixed gradients per step."""
    generator = torch.Generator().manual_seed(0)
    table = torch.randn(5000, 2, generator=generator).requires_grad_()
    weight = torch.randn(64, 27, generator=generator).requires_grad_()
    kernels.set_kernels_enabled(fused_on)
    try:
        optimizer = adam([{"params": [table], "lr": 1e-2}, {"params": [weight], "lr": 1e-3}], betas=(0.9, 0.99), eps=1e-15)
    finally:
        kernels.set_kernels_enabled(None)
    assert bool(optimizer.param_groups[0]["fused"]) is fused_on
    for _ in range(steps):
        table.grad = torch.randn(table.shape, generator=generator)
        weight.grad = torch.randn(weight.shape, generator=generator) * 1e-3
        optimizer.step()
    state = optimizer.state[table]
    return [table.detach(), weight.detach(), state["exp_avg"], state["exp_avg_sq"]]


def test_fused_adam_matches_the_reference_loop():
    reference, fused = _run(False), _run(True)
    start = torch.randn(5000, 2, generator=torch.Generator().manual_seed(0))
    assert not torch.equal(reference[0], start), "the optimizer did not move the parameters"
    for ref, fast in zip(reference, fused):
        torch.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-7)


def test_resumed_trainer_keeps_its_own_optimizer_implementation(small_run, kernels_on):
    from tests.test_train import _trainer

    fast = _trainer(small_run / "dataset", steps=2)
    fast.train_step()
    assert all(group["fused"] for group in fast.optimizer.param_groups)
    state = fast.state_dict()
    kernels.set_kernels_enabled(False)
    reference = _trainer(small_run / "dataset", steps=2)
    reference.load_state_dict(state)
    assert not any(group["fused"] for group in reference.optimizer.param_groups)
    reference.train_step()  # steps with the loop implementation from the fused run's moments
    assert reference.step == 2


def _sparse_run(kernels_enabled: bool, grads: list[torch.Tensor], eps: float = 1e-15) -> tuple[torch.Tensor, dict]:
    table = torch.randn(grads[0].shape, generator=torch.Generator().manual_seed(1)).requires_grad_()
    kernels.set_kernels_enabled(kernels_enabled)
    try:
        optimizer = SparseAdam([table], lr=1e-2, betas=(0.9, 0.99), eps=eps)
        for grad in grads:
            table.grad = grad.clone()
            optimizer.step()
    finally:
        kernels.set_kernels_enabled(None)
    return table.detach(), optimizer.state[table]


def _masked_grads(steps: int, shape=(3000, 2), reached: float = 0.3) -> list[torch.Tensor]:
    generator = torch.Generator().manual_seed(2)
    rows = [torch.rand(shape[0], 1, generator=generator) < reached for _ in range(steps)]
    return [torch.randn(shape, generator=generator) * row for row in rows]


@pytest.mark.parametrize("kernels_enabled", [False, True])
def test_sparse_adam_is_torch_adam_when_every_entry_has_a_gradient(kernels_enabled):
    if kernels_enabled:
        built_kernel("sparseadam")
    generator = torch.Generator().manual_seed(3)
    grads = [torch.randn(500, 2, generator=generator) for _ in range(12)]
    sparse, state = _sparse_run(kernels_enabled, grads)
    table = torch.randn(500, 2, generator=torch.Generator().manual_seed(1)).requires_grad_()
    dense = torch.optim.Adam([table], lr=1e-2, betas=(0.9, 0.99), eps=1e-15)
    for grad in grads:
        table.grad = grad.clone()
        dense.step()
    torch.testing.assert_close(sparse, table.detach(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(state["exp_avg_sq"], dense.state[table]["exp_avg_sq"])
    assert bool((state["steps"] == 12).all())


@pytest.mark.parametrize("kernels_enabled", [False, True])
def test_sparse_adam_leaves_unreached_entries_alone_where_dense_adam_drifts(kernels_enabled):
    if kernels_enabled:
        built_kernel("sparseadam")
    # Entry 0 gets one tiny gradient at step 1 and none after; entry 1 none at all.
    grads = [torch.zeros(4, 2) for _ in range(10)]
    grads[0][0] = 1e-6
    grads[0][2:] = 1.0
    start = torch.randn(4, 2, generator=torch.Generator().manual_seed(1))
    sparse, state = _sparse_run(kernels_enabled, grads)
    # First step: a fresh Adam step of lr * sign(g) for the reached entries, whatever |g| ...
    torch.testing.assert_close(sparse[0] - start[0], torch.full((2,), -1e-2), rtol=1e-4, atol=0)
    # ... and then nothing: neither the never-reached entry nor the once-reached one moves again.
    assert torch.equal(sparse[1], start[1])
    assert state["steps"][:, 0].tolist() == [1, 0, 1, 1]
    assert torch.equal(state["exp_avg"][1], torch.zeros(2))
    # torch's Adam keeps moving entry 0 on its momentum: over four full-size steps in the next nine,
    # from one tiny gradient (m / sqrt(v) does not depend on its size).
    table = start.clone().requires_grad_()
    dense = torch.optim.Adam([table], lr=1e-2, betas=(0.9, 0.99), eps=1e-15)
    for grad in grads:
        table.grad = grad.clone()
        dense.step()
    drift = float((start[0, 0] - table.detach()[0, 0]))
    assert drift > 4e-2, drift


def test_sparse_adam_counts_steps_per_entry():
    # An entry first reached at step 5 gets a fresh Adam's first step (lr * sign), not a
    # bias correction made for step 5.
    grads = [torch.zeros(2, 1) for _ in range(5)]
    for grad in grads:
        grad[0] = 1.0
    grads[4][1] = -3.0
    start = torch.randn(2, 1, generator=torch.Generator().manual_seed(1))
    table, state = _sparse_run(False, grads)
    assert state["steps"].ravel().tolist() == [5, 1]
    torch.testing.assert_close(table[1] - start[1], torch.tensor([1e-2]), rtol=1e-5, atol=0)


def test_sparse_adam_kernel_matches_its_reference():
    built_kernel("sparseadam")
    grads = _masked_grads(15)
    reference, ref_state = _sparse_run(False, grads)
    fast, fast_state = _sparse_run(True, grads)
    start = torch.randn(grads[0].shape, generator=torch.Generator().manual_seed(1))
    assert not torch.equal(reference, start)
    torch.testing.assert_close(fast, reference, rtol=1e-5, atol=1e-7)
    for key in ("exp_avg", "exp_avg_sq"):
        torch.testing.assert_close(fast_state[key], ref_state[key], rtol=1e-5, atol=1e-7)
    assert torch.equal(fast_state["steps"], ref_state["steps"])
    # Unreached entries of the last step kept their values from the step before, in both.
    assert int((grads[-1] == 0).sum()) > 0
