"""C++ hash-grid kernel against the PyTorch reference: features, Jacobian, table and point gradients.

    .venv/bin/python -m pytest tests/test_kernel_hashgrid.py -q

Skipped (with the loader's reason) when the kernel cannot be built on this machine.
"""

import pytest
import torch

import igavatar.kernels as kernels
from igavatar.model.hashgrid import HashGridConfig, HashGridEncoding
from tests.conftest import built_kernel

# 2 dense levels (5^3, 9^3 <= 2^10) and 4 hashed ones, up to 64 cells per axis.
CONFIG = HashGridConfig(n_levels=6, log2_hashmap_size=10, base_resolution=4, finest_resolution=64)
BOX_MIN = torch.tensor([-0.9, -1.2, -0.4])
BOX_MAX = torch.tensor([0.7, 1.1, 0.6])


# Every test here runs with the kernels forced on (whatever IGAVATAR_KERNELS says).
pytestmark = pytest.mark.usefixtures("kernels_on")


@pytest.fixture(scope="module")
def kernel():
    return built_kernel("hashgrid")


def make_grid(config=CONFIG, seed=0):
    torch.manual_seed(seed)
    grid = HashGridEncoding(config, BOX_MIN, BOX_MAX)
    with torch.no_grad():
        grid.table.copy_(torch.randn_like(grid.table))
    return grid


def test_config_has_dense_and_hashed_levels():
    assert CONFIG.level_is_dense() == [True, True, False, False, False, False]


def hard_points(config=CONFIG, seed=1):
    """Random points inside and outside the box, on its faces and corners, and on cell faces."""
    g = torch.Generator().manual_seed(seed)
    extent = BOX_MAX - BOX_MIN
    inside = BOX_MIN + torch.rand(400, 3, generator=g) * extent
    outside = BOX_MIN + (torch.rand(300, 3, generator=g) * 1.6 - 0.3) * extent
    # On the box faces: one coordinate exactly box_min or box_max, and all 8 box corners.
    faces = BOX_MIN + torch.rand(120, 3, generator=g) * extent
    axis = torch.arange(120) % 3
    side = (torch.arange(120) // 3) % 2 == 1
    faces[torch.arange(120), axis] = torch.where(side, BOX_MAX[axis], BOX_MIN[axis])
    corners = torch.stack(
        [torch.where(torch.tensor([(c >> a) & 1 for a in range(3)], dtype=torch.bool), BOX_MAX, BOX_MIN) for c in range(8)]
    )
    # On cell faces of random levels: u = k / N_l on one or all axes.
    res = torch.tensor(config.level_resolutions())
    n = res[torch.randint(0, len(res), (200,), generator=g)].float()[:, None]
    k = torch.floor(torch.rand(200, 3, generator=g) * (n + 1))
    on_cells = BOX_MIN + (k / n) * extent
    partial = inside[:200].clone()
    partial[:, 1] = on_cells[:, 1]
    return torch.cat([inside, outside, faces, corners, on_cells, partial]).contiguous()


def encode_both(grid, x, with_jacobian=True):
    ref = grid._encode_reference(x, with_jacobian)
    ker = grid._encode(x, with_jacobian)
    return ref, ker


def test_forward_matches_reference(kernel):
    grid = make_grid()
    x = hard_points()
    with torch.no_grad():
        (f_ref, j_ref), (f_ker, j_ker) = encode_both(grid, x)
        f_only = grid._encode(x, with_jacobian=False)
    assert f_ker.shape == f_ref.shape == (x.shape[0], CONFIG.output_dim)
    assert j_ker.shape == j_ref.shape == (x.shape[0], CONFIG.output_dim, 3)
    assert f_only[1] is None and torch.equal(f_only[0], f_ker)
    assert torch.allclose(f_ker, f_ref, atol=1e-5 * f_ref.abs().max().item(), rtol=0)
    assert torch.allclose(j_ker, j_ref, atol=1e-5 * j_ref.abs().max().item(), rtol=0)
    # Outside points have a zero Jacobian along every clamped axis, like the reference.
    assert torch.equal(j_ker == 0, j_ref == 0)


def test_public_api_uses_kernel_and_matches(kernel, monkeypatch):
    grid = make_grid()
    x = hard_points()
    calls = []
    real = grid._encode_kernel
    monkeypatch.setattr(grid, "_encode_kernel", lambda *a: calls.append(1) or real(*a))
    features, jacobian = grid.forward_with_jacobian(x)
    assert calls
    with torch.no_grad():
        f_ref, j_ref = grid._encode_reference(x, True)
    assert torch.allclose(features, f_ref, atol=1e-5 * f_ref.abs().max().item(), rtol=0)
    assert torch.allclose(jacobian, j_ref, atol=1e-5 * j_ref.abs().max().item(), rtol=0)


def gradients(grid, x, encode, weights):
    """d (linear loss on features and Jacobian) / d (table, x) through one encoding path."""
    x = x.clone().requires_grad_(True)
    features, jacobian = encode(x, True)
    loss = (features * weights[0]).sum() + (jacobian * weights[1]).sum()
    return torch.autograd.grad(loss, (grid.table, x))


@pytest.mark.parametrize("on", ["both", "features", "jacobian"])
def test_gradients_match_reference(kernel, on):
    grid = make_grid()
    x = hard_points()
    g = torch.Generator().manual_seed(5)
    weights = [torch.randn(x.shape[0], CONFIG.output_dim, generator=g),
               torch.randn(x.shape[0], CONFIG.output_dim, 3, generator=g)]
    if on == "features":
        weights[1] = torch.zeros_like(weights[1])
    elif on == "jacobian":
        weights[0] = torch.zeros_like(weights[0])
    table_ref, x_ref = gradients(grid, x, grid._encode_reference, weights)
    table_ker, x_ker = gradients(grid, x, grid._encode, weights)
    assert torch.allclose(table_ker, table_ref, atol=1e-5 * table_ref.abs().max().item(), rtol=0)
    assert torch.allclose(x_ker, x_ref, atol=1e-5 * x_ref.abs().max().item(), rtol=0)
    assert table_ref.abs().max() > 0 and x_ref.abs().max() > 0


def test_unused_jacobian_and_point_only_gradients(kernel):
    """Loss on features only (Jacobian output unused) and a frozen table (only x needs a gradient)."""
    grid = make_grid()
    x = hard_points()
    weights = torch.randn(x.shape[0], CONFIG.output_dim)
    grads = []
    for encode in (grid._encode, grid._encode_reference):
        x1 = x.clone().requires_grad_(True)
        features, _ = encode(x1, False)
        grads.append(torch.autograd.grad((features * weights).sum(), (grid.table, x1)))
    (table_ker, x_ker), (table_ref, x_ref) = grads
    assert torch.allclose(table_ker, table_ref, atol=1e-5 * table_ref.abs().max().item(), rtol=0)
    assert torch.allclose(x_ker, x_ref, atol=1e-5 * x_ref.abs().max().item(), rtol=0)

    grid.table.requires_grad_(False)
    x3 = x.clone().requires_grad_(True)
    features, jacobian = grid.forward_with_jacobian(x3)
    (grad_x,) = torch.autograd.grad(features.sum() + jacobian.square().sum(), x3)
    x4 = x.clone().requires_grad_(True)
    f_ref, j_ref = grid._encode_reference(x4, True)
    (grad_ref,) = torch.autograd.grad(f_ref.sum() + j_ref.square().sum(), x4)
    assert torch.allclose(grad_x, grad_ref, atol=1e-5 * grad_ref.abs().max().item(), rtol=0)


def test_chunked_kernel_matches_reference(kernel):
    import dataclasses

    grid = make_grid(dataclasses.replace(CONFIG, chunk_size=97, grad_chunk_size=131))
    x = hard_points().requires_grad_(True)
    features, jacobian = grid.forward_with_jacobian(x)
    (features.sum() + jacobian.square().sum()).backward()
    table_grad, x_grad = grid.table.grad.clone(), x.grad.clone()
    grid.table.grad = None
    x_ref = x.detach().clone().requires_grad_(True)
    f_ref, j_ref = grid._encode_reference(x_ref, True)
    (f_ref.sum() + j_ref.square().sum()).backward()
    assert torch.allclose(features, f_ref, atol=1e-5 * f_ref.abs().max().item(), rtol=0)
    assert torch.allclose(table_grad, grid.table.grad, atol=1e-5 * grid.table.grad.abs().max().item(), rtol=0)
    assert torch.allclose(x_grad, x_ref.grad, atol=1e-5 * x_ref.grad.abs().max().item(), rtol=0)


def test_disabled_kernels_use_the_reference(kernel, monkeypatch):
    grid = make_grid()
    x = hard_points()
    calls = []
    monkeypatch.setattr(grid, "_encode_kernel", lambda *a: calls.append(1))
    kernels.set_kernels_enabled(False)
    try:
        features, jacobian = grid.forward_with_jacobian(x)
        assert kernels.load_kernel("hashgrid") is None
    finally:
        kernels.set_kernels_enabled(None)
    assert not calls
    with torch.no_grad():
        f_ref, j_ref = grid._encode_reference(x, True)
    assert torch.equal(features, f_ref) and torch.equal(jacobian, j_ref)


def test_float64_and_bad_inputs(kernel):
    grid = make_grid().double()
    x = hard_points().double()
    calls = []
    grid._encode_kernel = lambda *a: calls.append(1)
    grid.forward_with_jacobian(x)
    assert not calls  # float64 runs the reference
    grid = make_grid()
    args = (grid._offset, grid._resolution_int, grid._multiplier, grid.n_dense_levels, CONFIG.hashmap_size,
            grid.box_min, grid.box_max)
    with pytest.raises(RuntimeError, match=r"x must have shape \(P, 3\)"):
        kernel.forward(torch.zeros(4, 2), grid.table.detach(), *args, True)
    with pytest.raises(RuntimeError, match="x must be float32"):
        kernel.forward(torch.zeros(4, 3, dtype=torch.float64), grid.table.detach(), *args, True)
    with pytest.raises(RuntimeError, match="exceed the table"):
        kernel.forward(torch.zeros(4, 3), grid.table.detach()[:100], *args, True)
    with pytest.raises(RuntimeError, match="grad_features must have shape"):
        kernel.backward(torch.zeros(4, 3), torch.empty(0), torch.zeros(4, 3), grid.table.detach(), *args, True)
