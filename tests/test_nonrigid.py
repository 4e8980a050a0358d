"""Tests of the pose-conditioned non-rigid offset field."""

import math

import pytest
import torch

from igavatar.errors import InputError
from igavatar.model.nonrigid import NonRigidConfig, NonRigidOffset, hann_window


def _enabled_module(**overrides) -> NonRigidOffset:
    torch.manual_seed(0)
    module = NonRigidOffset(NonRigidConfig(**overrides))
    module.set_enabled(True)
    module.set_window(1.0)
    return module


def test_disabled_returns_zeros_without_running_the_mlp():
    module = NonRigidOffset(NonRigidConfig(pose_dim=5))
    calls = []
    encode = module.encode
    # Both paths (shared-pose fast path, reference) start by encoding the points.
    module.encode = lambda *args, **kwargs: calls.append(1) or encode(*args, **kwargs)
    offsets = module(torch.rand(7, 3), torch.rand(5))
    assert torch.equal(offsets, torch.zeros(7, 3)) and calls == []
    module.set_enabled(True)
    module(torch.rand(7, 3), torch.rand(5))
    assert calls == [1]


def test_output_is_bounded_for_extreme_inputs():
    module = _enabled_module(pose_dim=4, max_offset=0.1)
    with torch.no_grad():
        module.output.weight.normal_(std=100.0)  # saturate tanh
    x = torch.tensor([[1e4, -1e4, 3e3], [0.0, 0.0, 0.0], [-50.0, 20.0, 7.0]])
    pose = torch.tensor([1e3, -1e3, 50.0, 0.0])
    with torch.no_grad():
        offsets = module(x, pose)
    assert bool(torch.isfinite(offsets).all())
    assert bool((offsets.abs() <= torch.tensor(0.1)).all())  # float32 0.1 * tanh(.) <= float32 0.1
    assert float(offsets.abs().max()) > 0.09  # saturated, so the bound is what holds it


def test_offsets_start_near_zero():
    module = _enabled_module(pose_dim=69)
    with torch.no_grad():
        offsets = module(torch.rand(256, 3) * 2 - 1, torch.randn(69) * 0.5)
    assert float(offsets.abs().max()) < 1e-3
    assert float(offsets.abs().max()) > 0.0
    assert torch.equal(module.output.bias, torch.zeros(3))


def test_hann_window_values():
    torch.testing.assert_close(hann_window(0.0, 4), torch.zeros(4))
    torch.testing.assert_close(hann_window(4.0, 4), torch.ones(4))
    torch.testing.assert_close(hann_window(1.5, 3), torch.tensor([1.0, 0.5, 0.0]))
    window = hann_window(2.25, 4)
    torch.testing.assert_close(window[2], torch.tensor((1 - math.cos(math.pi * 0.25)) / 2))


def test_closed_window_makes_output_independent_of_frequency_features():
    module = _enabled_module(pose_dim=3)
    module.set_window(0.0)
    x, pose = torch.rand(32, 3), torch.rand(3)
    encoding = module.encode(x)
    torch.testing.assert_close(encoding[:, :3], x)
    assert torch.equal(encoding[:, 3:], torch.zeros(32, 36))
    before = module(x, pose)
    # Re-randomising the first layer's columns that read the frequency features changes nothing.
    with torch.no_grad():
        module.hidden[0].weight[:, 3:39].normal_(std=10.0)
    torch.testing.assert_close(module(x, pose), before, atol=0, rtol=0)
    # Opening two bands (alpha override) makes them matter: bands 0, 1 are sin/cos columns 3..8, 21..26.
    encoding = module.encode(x, alpha=2.0)
    assert bool((encoding[:, 9:21] == 0).all()) and bool((encoding[:, 27:] == 0).all())
    torch.testing.assert_close(encoding[:, 3:6], torch.sin(math.pi * x))
    torch.testing.assert_close(encoding[:, 24:27], torch.cos(2 * math.pi * x))
    assert not torch.allclose(module(x, pose, alpha=2.0), before)


def test_set_window_maps_progress_to_alpha_and_validates():
    module = NonRigidOffset(NonRigidConfig(num_frequencies=6))
    module.set_window(0.5)
    assert module.alpha == 3.0
    with pytest.raises(InputError, match="progress"):
        module.set_window(1.5)


def test_per_point_pose_and_shape_errors():
    module = _enabled_module(pose_dim=2)
    x = torch.rand(4, 3)
    shared = module(x, torch.tensor([0.3, -0.2]))
    per_point = module(x, torch.tensor([0.3, -0.2]).expand(4, 2))
    torch.testing.assert_close(shared, per_point)
    with pytest.raises(InputError, match="pose"):
        module(x, torch.rand(3))
    with pytest.raises(InputError, match="x_canonical"):
        module(torch.rand(4, 2), torch.rand(2))


def test_every_parameter_gets_gradients_and_changes_after_a_step():
    module = _enabled_module(pose_dim=8)
    optimizer = torch.optim.Adam(module.parameters(), lr=1e-3)
    before = {name: p.detach().clone() for name, p in module.named_parameters()}
    x, pose = torch.rand(64, 3), torch.randn(8)
    target = torch.full((64, 3), 0.01)
    loss = (module(x, pose) - target).square().mean()
    loss.backward()
    for name, parameter in module.named_parameters():
        assert parameter.grad is not None, name
        assert float(parameter.grad.abs().max()) > 0.0, name
    optimizer.step()
    for name, parameter in module.named_parameters():
        assert not torch.equal(parameter.detach(), before[name]), name


def test_schedule_state_round_trips_through_state_dict():
    module = _enabled_module(pose_dim=3)
    module.set_window(0.25)
    restored = NonRigidOffset(NonRigidConfig(pose_dim=3))
    restored.load_state_dict(module.state_dict())
    assert restored.enabled and restored.alpha == module.alpha
    x, pose = torch.rand(5, 3), torch.rand(3)
    torch.testing.assert_close(restored(x, pose), module(x, pose))


def test_shared_pose_fast_path_equals_the_reference_in_value_and_gradients():
    """The first layer's pose columns applied once (fast path) against the concatenated network."""
    torch.manual_seed(0)
    net = NonRigidOffset(NonRigidConfig(pose_dim=40, hidden_width=32, hidden_layers=3, last_layer_init_std=0.1))
    net.set_enabled(True)
    net.set_window(0.7)
    x = (torch.rand(500, 3) * 2 - 1).requires_grad_(True)
    pose = torch.randn(40)
    results = []
    for path in (net._forward_shared_pose, net._forward_reference):
        net.zero_grad()
        x.grad = None
        out = path(x, pose, None)
        (out * torch.linspace(-1, 1, out.numel()).reshape(out.shape)).sum().backward()
        results.append((out.detach(), x.grad.clone(), {n: p.grad.clone() for n, p in net.named_parameters()}))
    (fast, fast_x, fast_params), (ref, ref_x, ref_params) = results
    torch.testing.assert_close(fast, ref, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(fast_x, ref_x, atol=1e-6, rtol=1e-5)
    for name in ref_params:
        torch.testing.assert_close(fast_params[name], ref_params[name], atol=1e-6, rtol=1e-4)
    # forward() takes the fast path for a shared pose, the reference for per-point poses.
    torch.testing.assert_close(net(x, pose), fast)
    torch.testing.assert_close(net(x, pose.expand(500, 40)), ref)
