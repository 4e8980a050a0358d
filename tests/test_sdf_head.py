"""The fused SDF MLP with analytic gradient (igavatar/model/sdf_head.py + csrc/sdfhead.cpp) against
the plain PyTorch reference of SDFField.forward_with_gradient.

Values and every gradient (points, hash table, both layers' weights and biases) must agree to float32
rounding, on points that exercise both branches of the Softplus (its identity above the threshold and
its exponential tail), with partly opened hash levels, and for losses on the feature only, the
gradient only, or both.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

import igavatar.model.fields as fields
from igavatar import kernels
from igavatar.model import sdf_head
from igavatar.model.fields import SDFField, SDFFieldConfig
from igavatar.model.linear import onednn_linear_available

from conftest import built_kernel

pytestmark = pytest.mark.usefixtures("kernels_on")


@pytest.fixture(autouse=True)
def _needs_fast_path():
    if not onednn_linear_available():
        pytest.skip("this torch build has no working oneDNN linear op: only the reference runs here")
    built_kernel("sdfhead")


def _field(config: SDFFieldConfig = SDFFieldConfig()) -> SDFField:
    torch.manual_seed(0)
    field = SDFField(config, torch.full((3,), -1.0), torch.ones(3))
    with torch.no_grad():
        if field.encoding is not None:
            field.encoding.table.normal_(0.0, 0.05)  # features that matter, not the init's +-1e-4
        field.layers[0].weight.mul_(3.0)  # pre-activations from far below to far above the threshold
    field.set_level_weights(0.6)  # some levels half open: the level weights enter grad_sdf
    return field


def _values_and_grads(field: SDFField, x: torch.Tensor, fast: bool, loss_on: str):
    kernels.set_kernels_enabled(fast)
    generator = torch.Generator().manual_seed(7)
    weight_feature = torch.randn(x.shape[0], field.config.feature_dim, generator=generator)
    weight_gradient = torch.randn(x.shape[0], 3, generator=generator)
    field.zero_grad(set_to_none=True)
    points = x.clone().requires_grad_()
    sdf, feature, grad_sdf = field.forward_with_gradient(points)
    loss = 0.0
    if loss_on in ("feature", "both"):
        loss = loss + (feature * weight_feature).sum()
    if loss_on in ("gradient", "both"):
        loss = loss + (grad_sdf * weight_gradient).sum()
    loss.backward()
    grads = {name: p.grad for name, p in field.named_parameters()}
    return {"sdf": sdf.detach(), "feature": feature.detach(), "grad_sdf": grad_sdf.detach(), "points": points.grad, **grads}


def _assert_same(reference: dict, fast: dict) -> None:
    assert reference.keys() == fast.keys()
    for name, expected in reference.items():
        actual = fast[name]
        if expected is None:
            assert actual is None or not actual.any(), name
            continue
        assert actual is not None, name
        scale = expected.abs().max().item()
        error = (actual - expected).abs().max().item()
        # float32 rounding of sums over up to a few thousand points, relative to the largest entry
        assert error <= 2e-5 * scale + 1e-6, f"{name}: max error {error:.3g} (largest entry {scale:.3g})"


@pytest.fixture
def points() -> torch.Tensor:
    generator = torch.Generator().manual_seed(3)
    return torch.rand(3000, 3, generator=generator) * 2.0 - 1.0


@pytest.mark.parametrize("loss_on", ["both", "feature", "gradient"])
def test_fused_head_equals_reference_in_values_and_all_gradients(points, loss_on, monkeypatch):
    field = _field()
    calls = []
    fused = fields.sdf_head_with_gradient
    monkeypatch.setattr(fields, "sdf_head_with_gradient", lambda *a: calls.append(1) or fused(*a))
    reference = _values_and_grads(field, points, fast=False, loss_on=loss_on)
    assert not calls
    fast = _values_and_grads(field, points, fast=True, loss_on=loss_on)
    assert calls, "the fused head did not run with the kernels on"
    _assert_same(reference, fast)
    # Both Softplus branches were exercised (beta * z above the threshold, and far below zero).
    with torch.no_grad():
        z = fields.SDFField._mlp_input(field, points, field.encoding(points)) @ field.layers[0].weight.T + field.layers[0].bias
    beta_z = field.config.softplus_beta * z
    assert (beta_z > fields._SOFTPLUS_THRESHOLD).any() and (beta_z < -fields._SOFTPLUS_THRESHOLD).any()


def test_fused_head_without_point_gradient_and_under_no_grad(points):
    field = _field()
    kernels.set_kernels_enabled(False)
    sdf_ref, feature_ref, grad_ref = field.forward_with_gradient(points)
    kernels.set_kernels_enabled(True)
    with torch.no_grad():
        sdf, feature, grad_sdf = field.forward_with_gradient(points)
    torch.testing.assert_close(feature, feature_ref.detach(), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(grad_sdf, grad_ref.detach(), rtol=1e-5, atol=1e-4)
    assert torch.equal(sdf, feature[:, 0])


def test_other_architectures_keep_the_reference(points, monkeypatch):
    calls = []
    monkeypatch.setattr(fields, "sdf_head_with_gradient", lambda *a: calls.append(1))
    for config in (SDFFieldConfig(n_hidden_layers=2), SDFFieldConfig(pe_frequencies=2)):
        field = _field(config)
        sdf, feature, grad_sdf = field.forward_with_gradient(points[:50])
        assert grad_sdf.shape == (50, 3)
    assert not calls


def test_activation_kernel_matches_torch_softplus_and_its_slope():
    kernel = built_kernel("sdfhead")
    beta, threshold = 100.0, 20.0
    beta_z = np.concatenate([np.linspace(-120, 40, 3996), [-1e4, -87.5, -20.0, 0.0, 19.999, 20.0, 20.001, 30.0, 1e4]])
    z = torch.tensor(beta_z / beta, dtype=torch.float32).reshape(-1, 9)
    w0 = torch.linspace(-2.0, 2.0, 9)
    a, u = torch.empty_like(z), torch.empty_like(z)
    kernel.activation_forward(z.numpy(), w0.numpy(), beta, threshold, a.numpy(), u.numpy())
    z64 = z.double().requires_grad_()
    soft = F.softplus(z64, beta=beta, threshold=threshold)
    slope = torch.autograd.grad(soft.sum(), z64, create_graph=True)[0]
    torch.testing.assert_close(a.double(), soft.detach(), rtol=2e-6, atol=1e-9)
    torch.testing.assert_close(u.double(), (slope * w0.double()).detach(), rtol=2e-6, atol=1e-9)
    # Backward: d/dz of (softplus . grad_a + slope * w0 . grad_u), against float64 autograd.
    generator = torch.Generator().manual_seed(0)
    grad_a, grad_u = torch.randn(z.shape, generator=generator), torch.randn(z.shape, generator=generator)
    grad_z, grad_w0 = torch.empty_like(z), torch.empty(9)
    kernel.activation_backward(z.numpy(), grad_a.numpy(), grad_u.numpy(), w0.numpy(), beta, threshold,
                               grad_z.numpy(), grad_w0.numpy())
    w0_64 = w0.double().requires_grad_()
    objective = (soft * grad_a.double()).sum() + (slope * w0_64 * grad_u.double()).sum()
    expected_z, expected_w0 = torch.autograd.grad(objective, (z64, w0_64))
    torch.testing.assert_close(grad_z.double(), expected_z, rtol=1e-5, atol=1e-3)
    torch.testing.assert_close(grad_w0.double(), expected_w0, rtol=1e-5, atol=1e-5)


def test_kernel_rejects_bad_arrays():
    kernel = built_kernel("sdfhead")
    z = torch.zeros(4, 8)
    w0 = torch.zeros(8)
    good = torch.empty(4, 8)
    with pytest.raises(ValueError, match="wrong shape"):
        kernel.activation_forward(z.numpy(), torch.zeros(7).numpy(), 100.0, 20.0, good.numpy(), torch.empty(4, 8).numpy())
    with pytest.raises(ValueError, match="C-contiguous"):
        kernel.activation_forward(z.numpy(), w0.numpy(), 100.0, 20.0, good.numpy(), torch.empty(8, 4).t().numpy())
    with pytest.raises(ValueError, match="float32"):
        kernel.activation_forward(z.numpy(), w0.numpy(), 100.0, 20.0, good.numpy(), np.empty((4, 8)))
    with pytest.raises(ValueError, match="beta"):
        kernel.activation_forward(z.numpy(), w0.numpy(), 0.0, 20.0, good.numpy(), torch.empty(4, 8).numpy())
    with pytest.raises(ValueError, match="jacobian"):
        kernel.gradient_forward(torch.zeros(4, 10).numpy(), torch.zeros(4, 6, 3).numpy(), torch.zeros(10).numpy(),
                                torch.empty(4, 3).numpy())


def test_fused_forward_without_gradients_equals_reference(points, monkeypatch):
    field = _field()
    calls = []
    fused = fields.sdf_head_forward
    monkeypatch.setattr(fields, "sdf_head_forward", lambda *a: calls.append(1) or fused(*a))
    kernels.set_kernels_enabled(False)
    with torch.no_grad():
        sdf_ref, feature_ref = field(points)
    kernels.set_kernels_enabled(True)
    with torch.no_grad():
        sdf, feature = field(points)
    assert calls
    torch.testing.assert_close(feature, feature_ref, rtol=1e-5, atol=1e-5)
    assert torch.equal(sdf, feature[:, 0])
    # With gradients wanted (shape initialization), forward stays on the differentiable reference.
    calls.clear()
    sdf_grad, _ = field(points)
    assert sdf_grad.requires_grad and not calls


def test_softplus_kernel_matches_torch():
    kernel = built_kernel("sdfhead")
    z = torch.linspace(-1.5, 0.5, 64 * 40).reshape(40, 64)
    a = torch.empty_like(z)
    kernel.softplus(z.numpy(), 100.0, 20.0, a.numpy())
    torch.testing.assert_close(a.double(), F.softplus(z.double(), beta=100.0, threshold=20.0), rtol=2e-6, atol=1e-9)


def test_fused_head_backward_with_an_output_gradient_missing(points):
    """With gradient materialisation off, autograd hands None for an unused output."""
    field = _field()
    h = field._mlp_input(points, field.encoding(points)).detach().requires_grad_()
    _, jacobian = field.encoding.forward_with_jacobian(points)
    grad_scale = torch.cat((field.input_scale.reciprocal().expand(3), field._feature_scale(torch.float32)))
    class _NoMaterialise(sdf_head._SDFHead):
        @staticmethod
        def forward(ctx, *args):
            ctx.set_materialize_grads(False)
            return sdf_head._SDFHead.forward(ctx, *args)

    for use in ("feature", "gradient"):
        args = (h, jacobian.detach(), *(p for layer in field.layers for p in (layer.weight, layer.bias)), grad_scale,
                100.0, fields._SOFTPLUS_THRESHOLD)
        feature, grad_sdf = _NoMaterialise.apply(*args)
        expected_feature, expected_grad = sdf_head._SDFHead.apply(*args)
        (feature if use == "feature" else grad_sdf).sum().backward()
        got = h.grad.clone()
        h.grad = None
        field.zero_grad(set_to_none=True)
        (expected_feature if use == "feature" else expected_grad).sum().backward()
        torch.testing.assert_close(got, h.grad)
        h.grad = None
        field.zero_grad(set_to_none=True)
