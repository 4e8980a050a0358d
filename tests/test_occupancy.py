"""Occupancy grid (update rule, decay, moving box, rebuild) and the occupancy-aware ray sampler."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from igavatar.render.occupancy import OccupancyGrid
from igavatar.render.rays import RayBundle, rays_in_box
from igavatar.render.sampler import compact_samples, sample_along_rays

BETA = 0.01
RADIUS = 0.3
RES = 16


def sphere_density(center: tuple[float, float, float], radius: float = RADIUS):
    center_t = torch.tensor(center)

    def density(x: torch.Tensor) -> torch.Tensor:
        sdf = torch.linalg.vector_norm(x - center_t.to(x), dim=-1) - radius
        return (0.5 + 0.5 * torch.sign(-sdf) * (1.0 - torch.exp(-sdf.abs() / BETA))) / BETA

    return density


def zero_density(x: torch.Tensor) -> torch.Tensor:
    return torch.zeros(x.shape[0], device=x.device)


def unit_grid(**kwargs) -> OccupancyGrid:
    return OccupancyGrid(-torch.ones(3), torch.ones(3), resolution=RES, **kwargs)


def center_distances(grid: OccupancyGrid, center: tuple[float, float, float]) -> torch.Tensor:
    return torch.linalg.vector_norm(grid.cell_centers() - torch.tensor(center), dim=-1)


def test_starts_fully_occupied_and_outside_is_free() -> None:
    grid = unit_grid()
    assert grid.occupied.all()
    x = torch.tensor([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [0.0, -1.01, 0.0]])
    assert grid.is_occupied(x).tolist() == [True, False, False]


def test_update_follows_the_released_rule() -> None:
    """occupied = maxpool3(1 - exp(-0.01 cached)) > min(mean, 0.01), cached = max(0.8 cached, sigma)."""
    grid = unit_grid()
    density = sphere_density((0.1, -0.2, 0.0))
    grid.update(density, generator=torch.Generator().manual_seed(0))
    first = grid.cached.clone()
    grid.update(density, generator=torch.Generator().manual_seed(1))
    # Reference: same jittered points (same seed) evaluated by hand.
    rng = torch.Generator().manual_seed(1)
    offsets = torch.rand((RES, RES, RES, 3), generator=rng)
    iz, iy, ix = torch.meshgrid(*(torch.arange(RES, dtype=torch.float32),) * 3, indexing="ij")
    points = -1.0 + (torch.stack([ix, iy, iz], -1) + offsets) / RES * 2.0
    fresh = density(points.reshape(-1, 3)).reshape(RES, RES, RES)
    cached = torch.maximum(0.8 * first, fresh)
    assert torch.allclose(grid.cached, cached)
    occ = F.max_pool3d((1 - torch.exp(-0.01 * cached))[None, None], 3, stride=1, padding=1)[0, 0]
    assert torch.equal(grid.occupied, occ > occ.mean().clamp(max=0.01))


def test_sphere_cells_occupied_and_far_cells_free() -> None:
    grid = unit_grid()
    center = (0.1, -0.2, 0.0)
    grid.update(sphere_density(center), generator=torch.Generator().manual_seed(0))
    dist = center_distances(grid, center)
    cell_diagonal = (2.0 / RES) * 3**0.5
    assert grid.occupied[dist < RADIUS].all()
    # Density 1/m is reached ~beta*ln(50) outside; pooling dilates by one cell; plus jitter.
    assert not grid.occupied[dist > RADIUS + 5 * BETA + 2 * cell_diagonal].any()
    assert 0.0 < grid.occupied_fraction < 0.5
    # Point queries agree with the cells.
    assert grid.is_occupied(torch.tensor([center])).item()
    assert not grid.is_occupied(torch.tensor([[0.9, 0.9, 0.9]])).item()


def test_decay_forgets_a_moved_sphere() -> None:
    grid = unit_grid()
    gen = torch.Generator().manual_seed(0)
    old, new = (-0.5, 0.0, 0.0), (0.5, 0.0, 0.0)
    grid.update(sphere_density(old), generator=gen)
    before = grid.cached.clone()
    grid.update(zero_density, generator=gen)
    assert torch.allclose(grid.cached, 0.8 * before)
    old_cells = center_distances(grid, old) < RADIUS
    for _ in range(30):
        grid.update(sphere_density(new), generator=gen)
    new_cells = center_distances(grid, new) < RADIUS
    assert grid.occupied[new_cells].all()
    assert not grid.occupied[old_cells].any()  # 100 * 0.8^31 -> occupancy far below 0.01


def test_moving_box_keeps_cached_density_in_place() -> None:
    grid = unit_grid()
    center = (0.2, 0.1, -0.1)
    grid.update(sphere_density(center), generator=torch.Generator().manual_seed(0))
    shift = torch.tensor([0.35, -0.2, 0.1])
    grid.update(zero_density, box_min=-torch.ones(3) + shift, box_max=torch.ones(3) + shift)
    assert torch.allclose(grid.box_min, -torch.ones(3) + shift)
    dist = center_distances(grid, center)
    # The sphere's cells, now at other indices, are still occupied (resampled, decayed once).
    assert grid.occupied[dist < RADIUS - 2.0 / RES].all()
    assert not grid.occupied[dist > RADIUS + 5 * BETA + 3 * (2.0 / RES) * 3**0.5].any()


def test_rebuild_resets_the_cache() -> None:
    grid = unit_grid()
    gen = torch.Generator().manual_seed(0)
    old, new = (-0.5, 0.0, 0.0), (0.4, 0.3, 0.0)
    grid.update(sphere_density(old), generator=gen)
    grid.rebuild(sphere_density(new), -torch.ones(3) * 0.9, torch.ones(3) * 0.9, num_passes=3, generator=gen)
    assert grid.occupied[center_distances(grid, new) < RADIUS].all()
    assert not grid.occupied[center_distances(grid, old) < RADIUS].any()


def test_chunked_evaluation_matches_single_chunk() -> None:
    calls: list[int] = []
    density = sphere_density((0.0, 0.0, 0.0))

    def counting(x: torch.Tensor) -> torch.Tensor:
        calls.append(x.shape[0])
        return density(x)

    small, large = unit_grid(chunk_size=1000), unit_grid()
    small.update(counting, generator=torch.Generator().manual_seed(5))
    assert max(calls) == 1000 and sum(calls) == RES**3
    large.update(density, generator=torch.Generator().manual_seed(5))
    assert torch.equal(small.cached, large.cached) and torch.equal(small.occupied, large.occupied)


def test_bad_inputs_raise() -> None:
    grid = unit_grid()
    with pytest.raises(ValueError, match="density_fn returned shape"):
        grid.update(lambda x: torch.zeros(x.shape[0], 1))
    with pytest.raises(ValueError, match="box_max"):
        OccupancyGrid(torch.ones(3), torch.zeros(3))
    with pytest.raises(ValueError, match="both"):
        grid.update(zero_density, box_min=torch.zeros(3))


# ------------------------------------------------------------------------------------ sampler
def rays_through_box(r: int, gen: torch.Generator) -> RayBundle:
    origins = torch.nn.functional.normalize(torch.randn(r, 3, generator=gen), dim=-1) * 2.5
    targets = (torch.rand(r, 3, generator=gen) - 0.5) * 0.8
    directions = torch.nn.functional.normalize(targets - origins, dim=-1)
    return rays_in_box(origins, directions, -torch.ones(3), torch.ones(3))


@pytest.fixture(scope="module")
def sphere_grid() -> OccupancyGrid:
    grid = unit_grid()
    grid.update(sphere_density((0.0, 0.1, 0.0)), generator=torch.Generator().manual_seed(0))
    return grid


def test_samples_lie_in_occupied_cells_within_near_far_and_sorted(sphere_grid: OccupancyGrid) -> None:
    gen = torch.Generator().manual_seed(1)
    rays = rays_through_box(40, gen)
    samples = sample_along_rays(rays, 64, sphere_grid.is_occupied, generator=gen, compact=False)
    valid = samples.valid
    assert valid.any() and not valid.all()
    assert sphere_grid.is_occupied(samples.positions[valid]).all()
    # Every occupied sample point was kept.
    occ = sphere_grid.is_occupied(samples.positions.reshape(-1, 3)).reshape(valid.shape)
    assert torch.equal(valid, occ & (rays.far > rays.near)[:, None])
    t = samples.t
    assert ((t >= rays.near[:, None]) & (t <= rays.far[:, None]))[valid].all()
    assert ((samples.t_starts <= t) & (t <= samples.t_ends)).all()
    assert (t[:, 1:] > t[:, :-1]).all()  # uncompacted: every slot increasing
    expected = rays.origins[:, None] + t[..., None] * rays.directions[:, None]
    assert torch.allclose(samples.positions, expected, atol=1e-6)
    assert torch.allclose(samples.deltas[valid], ((rays.far - rays.near) / 64)[:, None].expand_as(t)[valid])


def test_compaction_keeps_valid_samples_in_order(sphere_grid: OccupancyGrid) -> None:
    gen = torch.Generator().manual_seed(2)
    rays = rays_through_box(40, gen)
    padded = sample_along_rays(rays, 64, sphere_grid.is_occupied, generator=gen, compact=False)
    packed = compact_samples(padded)
    counts = padded.valid.sum(1)
    assert packed.valid.shape == (40, int(counts.max()))
    assert torch.equal(packed.valid.sum(1), counts)
    for i in range(40):
        n = int(counts[i])
        assert packed.valid[i, :n].all() and not packed.valid[i, n:].any()
        assert torch.equal(packed.t[i, :n], padded.t[i][padded.valid[i]])
        assert torch.equal(packed.positions[i, :n], padded.positions[i][padded.valid[i]])
    assert (packed.deltas[~packed.valid] == 0).all()


def test_sampling_is_repeatable_with_a_generator_and_midpoints_at_eval() -> None:
    gen = torch.Generator().manual_seed(3)
    rays = rays_through_box(10, gen)
    a = sample_along_rays(rays, 32, generator=torch.Generator().manual_seed(7))
    b = sample_along_rays(rays, 32, generator=torch.Generator().manual_seed(7))
    c = sample_along_rays(rays, 32, generator=torch.Generator().manual_seed(8))
    assert torch.equal(a.t, b.t) and not torch.equal(a.t, c.t)
    mid = sample_along_rays(rays, 32, stratified=False)
    assert torch.allclose(mid.t, 0.5 * (mid.t_starts + mid.t_ends))
    # Jitter is uniform within the bin: the mean offset is about one half.
    big = sample_along_rays(rays, 512, generator=gen)
    frac = (big.t - big.t_starts) / (big.t_ends - big.t_starts)
    assert abs(float(frac.mean()) - 0.5) < 0.01


def test_missed_rays_get_no_samples() -> None:
    origins = torch.tensor([[0.0, 3.0, -3.0], [0.0, 0.0, -3.0]])
    directions = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    rays = rays_in_box(origins, directions, -torch.ones(3), torch.ones(3))
    samples = sample_along_rays(rays, 8)
    assert samples.valid.sum(1).tolist() == [0, 8]


@pytest.mark.parametrize("radius", [1, 2])
def test_max_filter_equals_max_pool3d(radius):
    """The separable max filter against its reference, max_pool3d, on random and sparse grids."""
    import torch.nn.functional as F

    from igavatar.render.occupancy import max_filter_3d

    generator = torch.Generator().manual_seed(radius)
    dense = torch.rand(9, 5, 13, generator=generator)
    sparse = (torch.rand(16, 16, 16, generator=generator) > 0.97).float()
    tiny = torch.rand(1, 2, 3, generator=generator)
    for values in (dense, sparse, tiny):
        expected = F.max_pool3d(values[None, None], 2 * radius + 1, stride=1, padding=radius)[0, 0]
        assert torch.equal(max_filter_3d(values, radius), expected)
    assert torch.equal(max_filter_3d(dense, 0), dense)
