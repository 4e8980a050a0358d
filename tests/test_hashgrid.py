"""Hash-grid encoding against the loop reference: values, table gradients, closed-form Jacobian.

    .venv/bin/python -m pytest tests/test_hashgrid.py -q
"""

import dataclasses

import pytest
import torch
from torch.func import functional_call

from igavatar.errors import InputError
from igavatar.model.hashgrid import HashGridConfig, HashGridEncoding, hashgrid_reference

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])

# 2 dense levels (5^3, 7^3 <= 2^9) and 3 hashed ones (13^3 > 2^9).
TINY = HashGridConfig(n_levels=5, n_features_per_level=2, log2_hashmap_size=9, base_resolution=4, finest_resolution=32)
BOX_MIN = torch.tensor([-0.9, -1.2, -0.4])
BOX_MAX = torch.tensor([0.7, 1.1, 0.6])


def make_grid(config=TINY, dtype=torch.float64, device="cpu", seed=0):
    """Encoding with table values in [-1, 1] so that every corner visibly matters."""
    torch.manual_seed(seed)
    grid = HashGridEncoding(config, BOX_MIN, BOX_MAX).to(device=device, dtype=dtype)
    with torch.no_grad():
        grid.table.uniform_(-1.0, 1.0)
    return grid


def points(n, dtype=torch.float64, device="cpu", margin=0.2, seed=1):
    """n points uniform in the box grown by ``margin`` of its extent on each side (some outside)."""
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 3, generator=g, dtype=dtype) * (1 + 2 * margin) - margin
    return (BOX_MIN.to(dtype) + u * (BOX_MAX - BOX_MIN).to(dtype)).to(device)


def reference(grid, x):
    return hashgrid_reference(x, grid.level_tables(), grid.config, (grid.box_min, grid.box_max))


def test_level_layout():
    cfg = HashGridConfig()
    res = cfg.level_resolutions()
    assert res[0] == 16 and res[-1] == 2048 and len(res) == 16
    assert all(b > a for a, b in zip(res, res[1:]))
    assert cfg.level_is_dense() == [(n + 1) ** 3 <= 2**19 for n in res]
    assert sum(cfg.level_is_dense()) == 5  # 16..58 dense, 80..2048 hashed
    assert TINY.level_is_dense() == [True, True, False, False, False]
    grid = HashGridEncoding(TINY, BOX_MIN, BOX_MAX)
    assert grid.table.shape == (sum(TINY.level_table_sizes()), 2)
    assert [t.shape[0] for t in grid.level_tables()] == [125, 343, 512, 512, 512]
    assert grid.table.abs().max() <= 1e-4 and grid.table.abs().max() > 0
    assert grid.output_dim == 10


@pytest.mark.parametrize("device", DEVICES)
def test_values_match_reference(device):
    grid = make_grid(device=device)
    x = points(3000, device=device)
    expected = reference(grid, x)
    assert torch.allclose(grid(x), expected, atol=1e-12, rtol=0)
    with torch.no_grad():  # inference path (chunked, no autograd)
        assert torch.allclose(grid(x), expected, atol=1e-12, rtol=0)
    features, _ = grid.forward_with_jacobian(x)
    assert torch.allclose(features, expected, atol=1e-12, rtol=0)


def test_default_config_hashing_matches_reference():
    """The real primes and resolutions up to 2048 overflow int32 products: wrap must equal uint32."""
    cfg = HashGridConfig()
    grid = make_grid(cfg, dtype=torch.float32)
    x = points(400, dtype=torch.float32)
    with torch.no_grad():
        expected = reference(grid, x)
        assert torch.allclose(grid(x), expected, atol=1e-5, rtol=0)
        assert torch.allclose(grid.forward_with_jacobian(x)[0], expected, atol=1e-5, rtol=0)


def test_chunking_is_invisible():
    grid = make_grid(dataclasses.replace(TINY, chunk_size=7, grad_chunk_size=11))
    whole = make_grid()
    x = points(100)
    with torch.no_grad():
        assert torch.allclose(grid(x), whole(x), atol=1e-12)
    f, j = grid.forward_with_jacobian(x)
    f0, j0 = whole.forward_with_jacobian(x)
    assert torch.allclose(f, f0, atol=1e-12) and torch.allclose(j, j0, atol=1e-12)


def test_table_gradient_matches_reference():
    grid = make_grid()
    x = points(2000)
    upstream = torch.randn(2000, grid.output_dim, dtype=torch.float64)
    (grid(x) * upstream).sum().backward()
    ours = grid.table.grad.clone()
    grid.table.grad = None
    (reference(grid, x) * upstream).sum().backward()
    assert torch.allclose(ours, grid.table.grad, atol=1e-12, rtol=0)
    assert (ours != 0).any(dim=1).sum() > 500  # many rows of every level touched


def test_jacobian_matches_autograd_and_finite_differences():
    grid = make_grid()
    x = points(200, margin=0.0).requires_grad_(True)
    features, jacobian = grid.forward_with_jacobian(x)
    assert jacobian.shape == (200, grid.output_dim, 3)
    autograd_rows = [torch.autograd.grad(grid(x)[:, c].sum(), x)[0] for c in range(grid.output_dim)]
    assert torch.allclose(jacobian, torch.stack(autograd_rows, dim=1), atol=1e-10, rtol=0)
    reference_rows = [torch.autograd.grad(reference(grid, x)[:, c].sum(), x)[0] for c in range(grid.output_dim)]
    assert torch.allclose(jacobian, torch.stack(reference_rows, dim=1), atol=1e-10, rtol=0)

    eps = 1e-7
    with torch.no_grad():
        for axis in range(3):
            step = torch.zeros(3, dtype=torch.float64)
            step[axis] = eps
            fd = (grid(x + step) - grid(x - step)) / (2 * eps)
            # A step across a cell face makes the difference quotient jump; such points are rare.
            close = (fd - jacobian[:, :, axis]).abs().amax(dim=1) < 1e-5
            assert close.float().mean() > 0.95


def test_outside_points_are_clamped():
    grid = make_grid()
    inside = points(300, margin=0.0)
    offset = torch.tensor([2.0, 0.0, -2.0], dtype=torch.float64)
    outside = inside + offset  # x beyond box_max, z below box_min on every point
    clamped = torch.maximum(torch.minimum(outside, BOX_MAX.double()), BOX_MIN.double())
    features, jacobian = grid.forward_with_jacobian(outside)
    assert torch.allclose(features, grid(clamped), atol=1e-12)
    assert torch.allclose(features, reference(grid, outside), atol=1e-12)
    assert (jacobian[:, :, 0] == 0).all() and (jacobian[:, :, 2] == 0).all()
    assert (jacobian[:, :, 1] != 0).any()


def test_gradcheck_features_and_jacobian():
    cfg = HashGridConfig(n_levels=3, log2_hashmap_size=7, base_resolution=2, finest_resolution=8)
    assert cfg.level_is_dense() == [True, True, False]
    grid = make_grid(cfg)
    # Points at least 0.2 cell from every face of the finest level (coarser faces are a subset:
    # resolutions 2, 4, 8), so no difference quotient straddles a face.
    g = torch.Generator().manual_seed(3)
    u = (torch.randint(0, 8, (6, 3), generator=g) + 0.2 + 0.6 * torch.rand(6, 3, generator=g, dtype=torch.float64)) / 8
    x = (BOX_MIN.double() + u * (BOX_MAX - BOX_MIN).double()).requires_grad_(True)
    table = grid.table.detach().clone().requires_grad_(True)

    def features(x_, table_):
        return functional_call(grid, {"table": table_}, (x_,))

    jacobian_module = _JacobianOf(grid)

    def jacobian(x_, table_):
        return functional_call(jacobian_module, {"grid.table": table_}, (x_,))

    assert torch.autograd.gradcheck(features, (x, table), eps=1e-6, atol=1e-7)
    assert torch.autograd.gradcheck(jacobian, (x.detach(), table), eps=1e-6, atol=1e-7)
    assert torch.autograd.gradcheck(jacobian, (x, table.detach()), eps=1e-6, atol=1e-7)


class _JacobianOf(torch.nn.Module):
    """Module whose forward is ``grid.forward_with_jacobian(x)[1]``, for functional_call."""

    def __init__(self, grid):
        super().__init__()
        self.grid = grid

    def forward(self, x):
        return self.grid.forward_with_jacobian(x)[1]


def test_loss_on_jacobian_matches_double_backward_through_reference():
    """An eikonal-like loss on the closed-form Jacobian trains the table like a double backward."""
    grid = make_grid()
    x = points(500, margin=0.0).requires_grad_(True)
    direction = torch.randn(grid.output_dim, dtype=torch.float64)
    _, jacobian = grid.forward_with_jacobian(x)
    grad_x = torch.einsum("c,pcd->pd", direction, jacobian)
    ((grad_x.norm(dim=-1) - 1) ** 2).mean().backward()
    ours = grid.table.grad.clone()

    grid.table.grad = None
    projected = reference(grid, x) @ direction
    grad_x_ref = torch.autograd.grad(projected.sum(), x, create_graph=True)[0]
    ((grad_x_ref.norm(dim=-1) - 1) ** 2).mean().backward()
    assert torch.allclose(ours, grid.table.grad, atol=1e-12, rtol=0)
    assert ours.abs().max() > 0


def test_float32_state_dict_and_dtype_follow_module():
    grid = make_grid(dtype=torch.float32)
    state = grid.state_dict()
    assert set(state) == {"table", "box_min", "box_max"}
    copy = HashGridEncoding(TINY, torch.zeros(3), torch.ones(3))
    copy.load_state_dict(state)
    x = points(50, dtype=torch.float32)
    with torch.no_grad():
        assert torch.equal(copy(x), grid(x))
        assert grid(x.double()).dtype == torch.float32


def test_bad_inputs():
    with pytest.raises(InputError, match="HashGridConfig.finest_resolution"):
        HashGridConfig(base_resolution=32, finest_resolution=16)
    with pytest.raises(InputError, match="log2_hashmap_size"):
        HashGridConfig(log2_hashmap_size=40)
    with pytest.raises(InputError, match="box_max"):
        HashGridEncoding(TINY, torch.zeros(3), torch.tensor([1.0, 0.0, 1.0]))
    with pytest.raises(InputError, match=r"shape \(3,\)"):
        HashGridEncoding(TINY, torch.zeros(2), torch.ones(2))
    grid = make_grid()
    with pytest.raises(ValueError, match=r"\(P, 3\)"):
        grid(torch.zeros(4, 2, dtype=torch.float64))
