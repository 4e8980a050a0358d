"""oneDNN linear layers (igavatar/model/linear.py) against the plain F.linear reference.

Values and every gradient (input, weight, bias) must agree to float32 rounding, with and without
the fused ReLU; padding the rows of an MLP's input must change nothing but the shapes computed on.
"""

from __future__ import annotations

import pytest
import torch

from igavatar import kernels
from igavatar.model.fields import ColorField, ColorFieldConfig
from igavatar.model.linear import linear, linear_reference, onednn_linear_available, pad_rows, padded_rows
from igavatar.model.nonrigid import NonRigidConfig, NonRigidOffset

pytestmark = pytest.mark.usefixtures("kernels_on")


@pytest.fixture(autouse=True)
def _needs_onednn():
    if not onednn_linear_available():
        pytest.skip("this torch build has no working oneDNN linear op: only the reference runs here")


def _value_and_grads(path, x, weight, bias, relu, grad_out):
    inputs = [x, weight] + ([bias] if bias is not None else [])
    y = path(x, weight, bias, relu)
    return (y, *torch.autograd.grad(y, inputs, grad_out))


@pytest.mark.parametrize("relu", [False, True])
@pytest.mark.parametrize(("rows", "d_in", "d_out", "with_bias"), [(1000, 39, 128, True), (333, 128, 3, True), (7, 5, 4, False)])
def test_fast_linear_equals_f_linear_in_value_and_gradients(rows, d_in, d_out, with_bias, relu):
    generator = torch.Generator().manual_seed(rows)
    x = torch.randn(rows, d_in, generator=generator, requires_grad=True)
    # A column slice, as the non-rigid MLP's shared-pose first layer passes: not contiguous.
    weight_full = torch.randn(d_out, d_in + 2, generator=generator) / d_in**0.5
    weight = weight_full[:, :d_in].requires_grad_()
    bias = torch.randn(d_out, generator=generator, requires_grad=True) if with_bias else None
    grad_out = torch.randn(rows, d_out, generator=generator)
    fast = _value_and_grads(linear, x, weight, bias, relu, grad_out)
    reference = _value_and_grads(linear_reference, x, weight, bias, relu, grad_out)
    assert type(fast[0].grad_fn).__name__ == "_OneDnnLinearBackward"
    if relu:
        assert (fast[0] == 0).any() and (fast[0] > 0).any()  # the mask matters
    for got, want in zip(fast, reference):
        # Float32 tolerance at the tensor's own scale: the weight gradient sums `rows` products
        # in another order than mm does.
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5 * float(want.detach().abs().max()))


def test_reference_is_used_when_kernels_are_off_or_inputs_do_not_apply():
    x = torch.randn(10, 4)
    weight = torch.randn(3, 4, requires_grad=True)
    kernels.set_kernels_enabled(False)
    try:
        off = linear(x, weight)
        assert pad_rows(x) is x
    finally:
        kernels.set_kernels_enabled(True)
    assert type(off.grad_fn).__name__ != "_OneDnnLinearBackward"
    double = linear(x.double(), weight.double())
    assert type(double.grad_fn).__name__ != "_OneDnnLinearBackward"
    torch.testing.assert_close(double, x.double() @ weight.double().T)


def test_padded_rows_bound_the_padding_and_the_number_of_shapes():
    for rows in [1, 255, 256, 257, 4095, 4096, 17380, 65537, 250_000]:
        padded = padded_rows(rows)
        assert padded >= rows and padded % 256 == 0
        assert padded - rows < max(256, rows / 16 + 1)
    # About 16 distinct shapes per doubling of the row count.
    assert len({padded_rows(rows) for rows in range(16384, 32768)}) <= 17


def test_padding_the_input_rows_changes_nothing_but_the_shape():
    torch.manual_seed(10)  # a seed at which unscaled tolerances failed (see below)
    x = torch.randn(1000, 6, requires_grad=True)
    padded = pad_rows(x)
    assert padded.shape == (padded_rows(1000), 6) and torch.equal(padded[:1000], x) and (padded[1000:] == 0).all()
    weight = torch.randn(5, 6, requires_grad=True)
    bias = torch.randn(5, requires_grad=True)
    grad_out = torch.randn(1000, 5)
    fast = linear(linear(padded, weight, bias, relu=True), torch.eye(5), None)[:1000]
    reference = linear_reference(linear_reference(x, weight, bias, True), torch.eye(5), None)
    torch.testing.assert_close(fast, reference)
    fast_grads = torch.autograd.grad(fast, (x, weight, bias), grad_out)
    reference_grads = torch.autograd.grad(reference, (x, weight, bias), grad_out)
    for got, want in zip(fast_grads, reference_grads):
        # The weight's gradient sums 1000 rows (entries up to ~60) in another order: float32
        # round-off of ~2e-5 lands on entries near zero, so the tolerance scales with the largest.
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6 * float(want.abs().max()) + 1e-6)


def test_color_and_nonrigid_fields_agree_with_kernels_off_and_on():
    torch.manual_seed(0)
    color = ColorField(ColorFieldConfig())
    nonrigid = NonRigidOffset(NonRigidConfig(pose_dim=4))
    nonrigid.set_enabled(True)
    nonrigid.set_window(1.0)
    with torch.no_grad():
        nonrigid.output.weight.normal_(std=0.1)  # offsets large enough to compare
    feature = torch.randn(700, 16, requires_grad=True)
    normal = torch.nn.functional.normalize(torch.randn(700, 3), dim=1)
    x = (torch.rand(700, 3) - 0.5).requires_grad_()
    pose = torch.randn(4)
    results = {}
    for enabled in (False, True):
        kernels.set_kernels_enabled(enabled)
        color.zero_grad()
        nonrigid.zero_grad()
        rgb, offset = color(feature, normal), nonrigid(x, pose)
        (rgb.square().sum() + offset.square().sum() * 100).backward()
        grads = [p.grad.clone() for p in (*color.parameters(), *nonrigid.parameters())]
        results[enabled] = (rgb.detach(), offset.detach(), *grads)
        feature.grad = x.grad = None
    for got, want in zip(results[True], results[False]):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-6)
