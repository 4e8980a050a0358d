"""The weight-gradient kernel (igavatar/kernels/csrc/wgrad.cpp) against float64 matrix products.

``outer_sum(a, b, out, a_sums, b_sums)`` computes a^T b and the column sums; ``weight_gradients``
dispatches each layer shape to it (either orientation) or to oneDNN, and must equal
``weight_gradients_reference`` to float32 rounding. Every ISA copy the CPU runs (``copies()``) is
checked, not only the one it dispatches to.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from igavatar.model import linear as linear_module
from igavatar.model.linear import onednn_linear_available, weight_gradients, weight_gradients_reference
from tests.conftest import built_kernel

pytestmark = pytest.mark.usefixtures("kernels_on")


@pytest.fixture(scope="module")
def wgrad():
    return built_kernel("wgrad")


def _reference(a: np.ndarray, b: np.ndarray):
    a64, b64 = a.astype(np.float64), b.astype(np.float64)
    return a64.T @ b64, a64.sum(0), b64.sum(0)


# Rows: fewer than one block, one block, not a multiple of the block, several blocks per thread.
# Columns of b: every 16-multiple tail (16, 32, 48) after 64-wide slabs; rows of out: 1-3 left over.
SHAPES = [(1, 1, 16), (5, 3, 32), (128, 4, 48), (300, 7, 64), (1000, 39, 128), (2049, 130, 80), (0, 5, 16)]


@pytest.mark.parametrize(("rows", "m", "n"), SHAPES)
def test_outer_sum_equals_float64_products_and_sums(wgrad, rows, m, n):
    generator = np.random.default_rng(rows + m + n)
    a = generator.standard_normal((rows, m)).astype(np.float32)
    b = generator.standard_normal((rows, n)).astype(np.float32)
    out = np.full((m, n), np.nan, np.float32)  # every entry must be written
    a_sums, b_sums = np.full(m, np.nan, np.float32), np.full(n, np.nan, np.float32)
    wgrad.outer_sum(a, b, out, a_sums, b_sums)
    want, want_a, want_b = _reference(a, b)
    scale = max(1.0, np.sqrt(rows))  # a sum of `rows` unit products
    np.testing.assert_allclose(out, want, rtol=0, atol=2e-6 * scale * 4)
    # The column sums are accumulated in double: only the final rounding to float32 is left.
    np.testing.assert_allclose(a_sums, want_a, rtol=2e-7, atol=1e-6)
    np.testing.assert_allclose(b_sums, want_b, rtol=2e-7, atol=1e-6)


def test_every_isa_copy_this_cpu_runs_equals_float64_products(wgrad):
    # One copy per register file (AVX-512, AVX2, plain): each has its own vector width and tiles, and
    # the default is the fastest this CPU runs. Copies the CPU lacks are refused, not run.
    copies = wgrad.copies()
    assert copies[-1] == "base" and set(copies) <= {"avx512", "avx2", "base"}
    for rows, m, n in SHAPES:
        generator = np.random.default_rng(7 * rows + m + n)
        a = generator.standard_normal((rows, m)).astype(np.float32)
        b = generator.standard_normal((rows, n)).astype(np.float32)
        want, want_a, want_b = _reference(a, b)
        default = np.empty((m, n), np.float32)
        wgrad.outer_sum(a, b, default, np.empty(0, np.float32), np.empty(0, np.float32))
        for copy in copies:
            out = np.full((m, n), np.nan, np.float32)
            a_sums, b_sums = np.full(m, np.nan, np.float32), np.full(n, np.nan, np.float32)
            wgrad.outer_sum(a, b, out, a_sums, b_sums, copy)
            np.testing.assert_allclose(out, want, rtol=0, atol=8e-6 * max(1.0, np.sqrt(rows)), err_msg=copy)
            np.testing.assert_allclose(a_sums, want_a, rtol=2e-7, atol=1e-6, err_msg=copy)
            np.testing.assert_allclose(b_sums, want_b, rtol=2e-7, atol=1e-6, err_msg=copy)
            if copy == copies[0]:
                np.testing.assert_array_equal(out, default)
    for missing in {"avx512", "avx2"} - set(copies):
        with pytest.raises(ValueError, match="does not run on this CPU"):
            wgrad.outer_sum(np.zeros((4, 1), np.float32), np.zeros((4, 16), np.float32), np.zeros((1, 16), np.float32),
                            np.empty(0, np.float32), np.empty(0, np.float32), missing)


def test_column_sums_stay_exact_when_the_running_sum_is_large(wgrad):
    # A bias gradient like a loss weighted by linspace(-1, 1): partial sums ~100x the result.
    rows = 20000
    a = (np.linspace(-1.0, 1.0, rows)[:, None] * np.array([[0.1, 0.3, -0.2]]) + 1e-3).astype(np.float32)
    b = np.ones((rows, 16), np.float32)
    a_sums, b_sums, out = np.empty(3, np.float32), np.empty(16, np.float32), np.empty((3, 16), np.float32)
    wgrad.outer_sum(a, b, out, a_sums, b_sums)
    want = a.astype(np.float64).sum(0)
    np.testing.assert_allclose(a_sums, want, rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(b_sums, np.full(16, rows, np.float32))


def test_outer_sum_skips_empty_sums_and_is_deterministic(wgrad):
    generator = np.random.default_rng(0)
    a = generator.standard_normal((5000, 24)).astype(np.float32)
    b = generator.standard_normal((5000, 64)).astype(np.float32)
    empty = np.empty(0, np.float32)
    first, second = np.empty((24, 64), np.float32), np.empty((24, 64), np.float32)
    wgrad.outer_sum(a, b, first, empty, empty)
    wgrad.outer_sum(a, b, second, empty, empty)
    assert np.array_equal(first, second)  # same thread count, same order of sums: bit for bit
    np.testing.assert_allclose(first, _reference(a, b)[0], rtol=0, atol=1e-3)


def test_outer_sum_rejects_bad_arrays(wgrad):
    a = np.zeros((10, 4), np.float32)
    b = np.zeros((10, 32), np.float32)
    empty = np.empty(0, np.float32)
    with pytest.raises(ValueError, match="multiple of 16"):
        wgrad.outer_sum(a, np.zeros((10, 20), np.float32), np.zeros((4, 20), np.float32), empty, empty)
    with pytest.raises(ValueError, match="same number of rows"):
        wgrad.outer_sum(a, np.zeros((11, 32), np.float32), np.zeros((4, 32), np.float32), empty, empty)
    with pytest.raises(ValueError, match="wrong shape"):
        wgrad.outer_sum(a, b, np.zeros((32, 4), np.float32), empty, empty)
    with pytest.raises(ValueError, match="float32"):
        wgrad.outer_sum(a, b, np.zeros((4, 32), np.float64), empty, empty)
    with pytest.raises(ValueError, match="C-contiguous"):
        wgrad.outer_sum(a, b, np.zeros((32, 4), np.float32).T, empty, empty)
    with pytest.raises(ValueError, match="a_sums"):
        wgrad.outer_sum(a, b, np.zeros((4, 32), np.float32), np.zeros(5, np.float32), empty)


@pytest.mark.parametrize(("rows", "d_in", "d_out", "kernel_used"),
                         [(3000, 128, 128, True), (3000, 39, 128, True), (3000, 128, 3, True), (3000, 27, 64, True),
                          (500, 5, 7, False)])
@pytest.mark.parametrize("with_bias", [False, True])
def test_weight_gradients_dispatch_and_equal_the_reference(wgrad, monkeypatch, rows, d_in, d_out, kernel_used, with_bias):
    if not kernel_used and not onednn_linear_available():
        pytest.skip("this torch build has no working oneDNN linear op: the fallback cannot run here")
    calls = []
    original = linear_module.onednn_weight_gradients
    monkeypatch.setattr(linear_module, "onednn_weight_gradients", lambda *args: calls.append(1) or original(*args))
    generator = torch.Generator().manual_seed(rows + d_in)
    grad = torch.randn(rows, d_out, generator=generator)
    x = torch.relu(torch.randn(rows, d_in, generator=generator))
    weight = torch.randn(d_out, d_in, generator=generator)
    got_weight, got_bias = weight_gradients(grad, x, weight, with_bias)
    want_weight, want_bias = weight_gradients_reference(grad.double(), x.double(), with_bias)
    assert bool(calls) != kernel_used
    assert got_weight.shape == (d_out, d_in) and got_weight.is_contiguous()
    torch.testing.assert_close(got_weight.double(), want_weight, rtol=1e-5, atol=1e-5 * float(want_weight.abs().max()))
    if with_bias:
        torch.testing.assert_close(got_bias.double(), want_bias, rtol=1e-5, atol=1e-5 * float(want_bias.abs().max()))
    else:
        assert got_bias is None
