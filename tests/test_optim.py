"""The fused Adam of the fast path against torch's reference loop, and the resume flags."""

from __future__ import annotations

import torch

from igavatar import kernels
from igavatar.training.optim import adam


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
