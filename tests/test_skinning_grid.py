"""Tests of the canonical skinning-weight grid: box, construction, lookups, blended transforms."""

import numpy as np
import pytest
import torch

from igavatar.errors import InputError
from igavatar.skinning.grid import (
    SPREAD_FAR_M,
    SPREAD_NEAR_M,
    apply_affine,
    blended_transform_grid,
    build_skinning_grid,
    canonical_grid_box,
    distance_adaptive_weights,
    grid_point_positions,
    inside_grid,
    sample_blended_transforms,
    sample_grid,
    sample_skinning_weights,
    smooth_weights_grid,
)


def _smooth_weights(points: np.ndarray, num_joints: int = 5) -> np.ndarray:
    """A smooth synthetic skinning weighting: softmax of fixed low-frequency functions."""
    rng = np.random.default_rng(7)
    slopes = rng.normal(size=(3, num_joints)) * 1.5
    logits = points @ slopes + 0.3 * np.sin(2.0 * points[:, :1] + np.arange(num_joints))
    logits -= logits.max(axis=1, keepdims=True)
    weights = np.exp(logits)
    return weights / weights.sum(axis=1, keepdims=True)


def _trilinear_reference(grid: torch.Tensor, box_min, box_max, point) -> torch.Tensor:
    """Naive trilinear interpolation with explicit D<->z, H<->y, W<->x indexing."""
    num_d, num_h, num_w = grid.shape[1:]
    sizes = torch.tensor([num_w, num_h, num_d], dtype=torch.float64)
    continuous = (point.double() - box_min.double()) / (box_max.double() - box_min.double()) * (sizes - 1)
    continuous = torch.minimum(continuous.clamp_min(0.0), sizes - 1)
    lower = torch.minimum(continuous.floor(), sizes - 2).long()
    frac = continuous - lower
    value = torch.zeros(grid.shape[0], dtype=torch.float64)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                weight = (
                    (frac[0] if dx else 1 - frac[0])
                    * (frac[1] if dy else 1 - frac[1])
                    * (frac[2] if dz else 1 - frac[2])
                )
                value += weight * grid[:, lower[2] + dz, lower[1] + dy, lower[0] + dx].double()
    return value


def test_canonical_grid_box_cube_and_squeezed_depth():
    vertices = torch.tensor([[-0.3, -0.1, 0.0], [0.5, 0.2, 1.6], [0.1, 0.0, 0.4]])
    box_min, box_max = canonical_grid_box(vertices)
    center = torch.tensor([0.1, 0.05, 0.8])
    half = 0.8 * 1.2  # largest half-extent is along z (1.6 / 2)
    torch.testing.assert_close(box_min, center - half)
    torch.testing.assert_close(box_max, center + half)

    box_min, box_max = canonical_grid_box(vertices.numpy(), squeeze_axis=1, squeeze=4.0)
    torch.testing.assert_close((box_max - box_min) / 2, torch.tensor([half, half / 4, half]))
    torch.testing.assert_close((box_max + box_min) / 2, center)


def test_canonical_grid_box_margin_keeps_room_behind_a_deep_body():
    # A body 0.5 m deep and 1.6 m tall: the depth squeeze alone (half 0.96 / 4 = 0.24) would end
    # 1 cm inside its bounds; the box reaches them at least, and with a margin keeps 6 cm on every
    # side, leaving the wide axes alone.
    vertices = torch.tensor([[-0.3, -0.4, 0.0], [0.5, 0.1, 1.6]])
    squeezed = canonical_grid_box(vertices, squeeze_axis=1)
    torch.testing.assert_close(squeezed[0][1], torch.tensor(-0.4))
    torch.testing.assert_close(squeezed[1][1], torch.tensor(0.1))
    box_min, box_max = canonical_grid_box(vertices, squeeze_axis=1, margin=0.06)
    torch.testing.assert_close(box_min[1], torch.tensor(-0.46))
    torch.testing.assert_close(box_max[1], torch.tensor(0.16))
    for axis in (0, 2):
        torch.testing.assert_close(box_min[axis], squeezed[0][axis])
        torch.testing.assert_close(box_max[axis], squeezed[1][axis])
    # A thin body keeps Fast-SNARF's box exactly.
    thin = torch.tensor([[-0.3, -0.1, 0.0], [0.5, 0.1, 1.6]])
    for got, want in zip(canonical_grid_box(thin, squeeze_axis=1, margin=0.06), canonical_grid_box(thin, squeeze_axis=1)):
        torch.testing.assert_close(got, want)


def test_canonical_grid_box_rejects_bad_input():
    with pytest.raises(InputError, match="vertices_canonical"):
        canonical_grid_box(torch.zeros(4, 2))
    with pytest.raises(InputError, match="squeeze_axis"):
        canonical_grid_box(torch.rand(4, 3), squeeze_axis=3)
    with pytest.raises(InputError, match="margin"):
        canonical_grid_box(torch.rand(4, 3), margin=-0.01)


def test_grid_point_positions_follow_d_z_h_y_w_x():
    box_min, box_max = torch.tensor([0.0, 1.0, 2.0]), torch.tensor([1.0, 3.0, 6.0])
    positions = grid_point_positions(box_min, box_max, (5, 3, 2))
    assert positions.shape == (5, 3, 2, 3)
    torch.testing.assert_close(positions[0, 0, 0], box_min)
    torch.testing.assert_close(positions[-1, -1, -1], box_max)
    torch.testing.assert_close(positions[1, 0, 0], torch.tensor([0.0, 1.0, 3.0]))  # D steps z
    torch.testing.assert_close(positions[0, 1, 0], torch.tensor([0.0, 2.0, 2.0]))  # H steps y
    torch.testing.assert_close(positions[0, 0, 1], torch.tensor([1.0, 1.0, 2.0]))  # W steps x


def test_built_grid_is_a_partition_of_unity_everywhere():
    rng = np.random.default_rng(0)
    vertices = rng.uniform(-0.5, 0.5, size=(400, 3)) * [1.0, 0.3, 2.0]
    weights = rng.dirichlet(np.full(6, 0.3), size=400)  # rough, to stress the construction
    box_min, box_max = canonical_grid_box(vertices, squeeze_axis=1)
    grid = build_skinning_grid(vertices, weights, box_min, box_max, (12, 6, 10), k=8, smoothing_iterations=3)
    assert grid.shape == (6, 12, 6, 10) and grid.dtype == torch.float32
    assert bool((grid >= 0).all())
    torch.testing.assert_close(grid.sum(dim=0), torch.ones(12, 6, 10), atol=1e-6, rtol=0)
    # Sampled anywhere (inside or outside the box) the weights stay a partition of unity.
    points = torch.rand(300, 3) * 1.6 - 0.8
    sampled = sample_skinning_weights(grid, box_min, box_max, points)
    assert bool((sampled >= 0).all())
    torch.testing.assert_close(sampled.sum(dim=1), torch.ones(300), atol=1e-5, rtol=0)


def test_nearest_vertex_grid_without_smoothing_matches_brute_force():
    rng = np.random.default_rng(1)
    vertices = rng.uniform(-1, 1, size=(50, 3))
    weights = rng.dirichlet(np.ones(4), size=50)
    box_min, box_max = torch.tensor([-1.0, -1.0, -1.0]), torch.tensor([1.0, 1.0, 1.0])
    grid = build_skinning_grid(vertices, weights, box_min, box_max, (4, 3, 5), k=1, smoothing_iterations=0)
    positions = grid_point_positions(box_min.double(), box_max.double(), (4, 3, 5)).reshape(-1, 3).numpy()
    nearest = np.argmin(((positions[:, None, :] - vertices[None]) ** 2).sum(-1), axis=1)
    expected = torch.from_numpy(weights[nearest].T.reshape(4, 4, 3, 5)).float()
    torch.testing.assert_close(grid, expected)


def test_sampled_weights_reproduce_a_smooth_weighting_at_vertices():
    rng = np.random.default_rng(2)
    vertices = rng.uniform(-0.5, 0.5, size=(3000, 3))
    weights = _smooth_weights(vertices)
    box_min, box_max = canonical_grid_box(vertices, scale=1.1)
    grid = build_skinning_grid(vertices, weights, box_min, box_max, (16, 16, 16), k=8, smoothing_iterations=2)
    sampled = sample_skinning_weights(grid, box_min, box_max, torch.from_numpy(vertices).float())
    error = (sampled - torch.from_numpy(weights).float()).abs()
    assert float(error.mean()) < 0.01
    assert float(error.max()) < 0.06


def test_smoothing_keeps_constant_fields_and_the_simplex():
    constant = torch.tensor([0.2, 0.5, 0.3])[:, None, None, None].expand(3, 4, 5, 6).contiguous()
    torch.testing.assert_close(smooth_weights_grid(constant, 4), constant)
    spikes = torch.zeros(2, 5, 5, 5)
    spikes[0] = 1.0
    spikes[:, 2, 2, 2] = torch.tensor([0.0, 1.0])
    smoothed = smooth_weights_grid(spikes, 2)
    assert bool((smoothed >= 0).all())
    torch.testing.assert_close(smoothed.sum(0), torch.ones(5, 5, 5))
    assert 0.0 < float(smoothed[1, 2, 2, 2]) < 1.0  # the spike spread out


def test_sample_grid_matches_naive_trilinear_reference():
    torch.manual_seed(0)
    grid = torch.rand(3, 4, 5, 6)
    box_min, box_max = torch.tensor([-1.0, 0.0, 0.5]), torch.tensor([2.0, 1.0, 1.5])
    points = box_min + torch.rand(40, 3) * (box_max - box_min)
    sampled = sample_grid(grid, box_min, box_max, points)
    expected = torch.stack([_trilinear_reference(grid, box_min, box_max, p) for p in points]).float()
    torch.testing.assert_close(sampled, expected, atol=1e-5, rtol=0)
    # Voxel sample positions return the stored values exactly.
    positions = grid_point_positions(box_min, box_max, (4, 5, 6)).reshape(-1, 3)
    at_voxels = sample_grid(grid, box_min, box_max, positions)
    torch.testing.assert_close(at_voxels, grid.reshape(3, -1).T, atol=1e-5, rtol=0)


def test_inside_grid():
    box_min, box_max = torch.zeros(3), torch.ones(3)
    points = torch.tensor([[0.5, 0.5, 0.5], [0.0, 1.0, 0.2], [1.01, 0.5, 0.5], [0.5, -0.1, 0.5]])
    assert inside_grid(box_min, box_max, points).tolist() == [True, True, False, False]


def _random_rigid(num: int, generator: torch.Generator) -> torch.Tensor:
    q, _ = torch.linalg.qr(torch.randn(num, 3, 3, generator=generator))
    q = q * torch.sign(torch.linalg.det(q))[:, None, None]
    transforms = torch.eye(4).repeat(num, 1, 1)
    transforms[:, :3, :3] = q
    transforms[:, :3, 3] = torch.randn(num, 3, generator=generator)
    return transforms


def test_blended_lookup_equals_direct_lbs_blend():
    generator = torch.Generator().manual_seed(3)
    num_joints = 7
    grid = torch.rand(num_joints, 6, 5, 8, generator=generator)
    grid = grid / grid.sum(0, keepdim=True)
    bones = _random_rigid(num_joints, generator)
    box_min, box_max = torch.tensor([-1.0, -0.5, -1.0]), torch.tensor([1.0, 0.5, 1.0])
    points = torch.rand(200, 3, generator=generator) * 2.4 - 1.2  # some outside (border padding)
    blended = blended_transform_grid(grid, bones)
    assert blended.shape == (12, 6, 5, 8)
    transforms = sample_blended_transforms(blended, box_min, box_max, points)
    weights = sample_skinning_weights(grid, box_min, box_max, points)
    direct = torch.einsum("pj,jrc->prc", weights, bones[:, :3, :])
    torch.testing.assert_close(transforms, direct, atol=1e-5, rtol=1e-5)
    posed_per_bone = torch.einsum("jrc,pc->pjr", bones[:, :3, :3], points) + bones[None, :, :3, 3]
    x_posed_direct = (weights[:, :, None] * posed_per_bone).sum(1)
    torch.testing.assert_close(apply_affine(transforms, points), x_posed_direct, atol=1e-5, rtol=1e-5)


def test_blended_transform_grid_rejects_joint_mismatch():
    with pytest.raises(InputError, match="bone_transforms"):
        blended_transform_grid(torch.rand(4, 2, 2, 2), torch.eye(4).repeat(5, 1, 1))


def _two_legs() -> tuple[np.ndarray, np.ndarray]:
    """Two parallel 'legs' 16 cm apart (600 vertices each), each skinned fully to its own bone."""
    rng = np.random.default_rng(3)
    leg = rng.uniform([-0.04, -0.04, -0.9], [0.04, 0.04, 0.0], size=(600, 3))
    vertices = np.concatenate([leg - [0.08, 0, 0], leg + [0.08, 0, 0]])
    weights = np.zeros((1200, 2))
    weights[:600, 0] = weights[600:, 1] = 1.0
    return vertices, weights


def _own_weight(grid: torch.Tensor, box_min: torch.Tensor, box_max: torch.Tensor, vertices: np.ndarray) -> float:
    """Mean weight of each leg's own bone at its vertices (1 = no leak between the legs)."""
    sampled = sample_skinning_weights(grid, box_min, box_max, torch.from_numpy(vertices).float())
    return float(torch.cat((sampled[:600, 0], sampled[600:, 1])).mean())


def test_fewer_blur_passes_keep_two_close_legs_apart():
    """Two parallel 'legs' 16 cm apart, each skinned to its own bone: InstantAvatar's 30 blur passes
    (at the default grid's ~3.4 cm cells) leak a large share of one leg's weight into the other,
    which is what `preprocess --weight-smoothing` trades against smoothness."""
    vertices, weights = _two_legs()
    box_min, box_max = torch.tensor([-1.1, -0.3, -1.1]), torch.tensor([1.1, 0.3, 1.1])
    own = {}
    for passes in (2, 15, 30):
        grid = build_skinning_grid(vertices, weights, box_min, box_max, (64, 16, 64), smoothing_iterations=passes)
        own[passes] = _own_weight(grid, box_min, box_max, vertices)
    assert own[2] > 0.9 and own[2] > own[15] > own[30], own
    assert own[30] < 0.75, own  # measured 0.94, 0.75, 0.69


def test_spread_keeps_the_legs_own_weights_near_them_and_the_blur_far_away():
    """With `spread`, voxels near the legs take the distance-adaptive kernel's weights (each leg
    skinned by its own bone, where 30 blur passes leak a quarter of the weight across the gap),
    voxels far away keep the blurred grid's smooth mix, and the hand-over between is gradual."""
    vertices, weights = _two_legs()
    box_min, box_max = torch.tensor([-1.1, -0.3, -1.1]), torch.tensor([1.1, 0.3, 1.1])
    shape = (64, 16, 64)
    blurred = build_skinning_grid(vertices, weights, box_min, box_max, shape, smoothing_iterations=30)
    spread = build_skinning_grid(vertices, weights, box_min, box_max, shape, smoothing_iterations=30, spread=1.0)
    assert _own_weight(spread, box_min, box_max, vertices) > 0.95 > 0.75 > _own_weight(blurred, box_min, box_max, vertices)
    torch.testing.assert_close(spread.sum(dim=0), torch.ones(shape), atol=1e-5, rtol=0)
    positions = grid_point_positions(box_min.double(), box_max.double(), shape).reshape(-1, 3).numpy()
    from scipy.spatial import cKDTree

    distance = torch.from_numpy(cKDTree(vertices).query(positions)[0].reshape(shape))
    far = distance >= SPREAD_FAR_M
    torch.testing.assert_close(spread[:, far], blurred[:, far], atol=1e-6, rtol=0)

    def largest_step(grid: torch.Tensor, where: torch.Tensor) -> float:
        """The largest weight change between neighbouring voxels that both lie in `where`."""
        steps = []
        for axis in (1, 2, 3):  # neighbours along z, y and x
            n = shape[axis - 1]
            step = (grid.narrow(axis, 1, n - 1) - grid.narrow(axis, 0, n - 1)).abs()
            steps.append(float(step[:, where.narrow(axis - 1, 1, n - 1) & where.narrow(axis - 1, 0, n - 1)].max()))
        return max(steps)

    # Between the legs and the far space the weights change by no more than the unblurred grid's do.
    handover = (distance > SPREAD_NEAR_M / 2) & (distance < SPREAD_FAR_M * 1.5)
    inverse = build_skinning_grid(vertices, weights, box_min, box_max, shape, smoothing_iterations=0)
    assert largest_step(spread, handover) <= largest_step(inverse, handover) + 1e-6
    with pytest.raises(InputError, match="spread"):
        build_skinning_grid(vertices, weights, box_min, box_max, shape, spread=-1.0)


def test_distance_adaptive_weights_match_the_kernel_over_all_vertices():
    """Near the body the nearest-neighbour truncation changes nothing: the blend equals the same
    Gaussian summed over every vertex (brute force), and it is continuous (1 mm apart, close weights)."""
    rng = np.random.default_rng(5)
    vertices = rng.uniform(-0.3, 0.3, size=(400, 3))
    weights = _smooth_weights(vertices, 4)
    points = rng.uniform(-0.35, 0.35, size=(50, 3))
    got = distance_adaptive_weights(vertices, weights, points, spread=0.5)
    distance = np.linalg.norm(points[:, None] - vertices[None], axis=-1)
    nearest = distance.min(axis=1, keepdims=True)
    kernel = np.exp(-0.5 * (distance**2 - nearest**2) / (0.01 + 0.5 * nearest) ** 2)
    expected = kernel @ weights / kernel.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(got, expected, atol=1e-6)
    np.testing.assert_allclose(got.sum(axis=1), 1.0, atol=1e-9)
    moved = distance_adaptive_weights(vertices, weights, points + [0.001, 0, 0], spread=0.5)
    assert np.abs(moved - got).max() < 0.05
