"""The C++ skinning kernel (igavatar/kernels/csrc/skinning.cpp) against its PyTorch reference.

Lookups must equal `grid_sample` (border padding, align_corners=True) to float32 rounding; the
Broyden kernel must find the same roots as `_broyden_reference` and the same valid candidates
through `canonicalize` on a posed stick figure.
"""

from __future__ import annotations

import pytest
import torch

from igavatar.kernels import set_kernels_enabled
from igavatar.model.deformer import DeformerConfig, FastSnarfDeformer, _broyden, _broyden_reference, init_parts
from igavatar.skinning.grid import apply_affine, blended_transform_grid, sample_blended_transforms, sample_grid
from tests.conftest import built_kernel
from tests.test_deformer import INIT_BONES, PARENTS, _bone_transforms, _canonical_points, _recovery, _stick_figure_grid


# Every test here runs with the kernels forced on (whatever IGAVATAR_KERNELS says).
pytestmark = pytest.mark.usefixtures("kernels_on")


@pytest.fixture(scope="module")
def kernel():
    return built_kernel("skinning")


def _points_around_box(box_min, box_max, count, seed):
    """Points inside, outside, exactly on the faces and exactly on voxel centers of the box."""
    generator = torch.Generator().manual_seed(seed)
    extent = box_max - box_min
    u = torch.rand(count, 3, generator=generator) * 1.4 - 0.2  # 20% beyond each face
    u[: count // 8] = torch.randint(0, 2, (count // 8, 3), generator=generator).float()  # corners/faces
    return box_min + u * extent


def test_lookups_equal_grid_sample(kernel):
    generator = torch.Generator().manual_seed(0)
    values = torch.randn(7, 5, 6, 9, generator=generator)  # (C, D, H, W)
    box_min, box_max = torch.tensor([-0.5, -1.0, 0.2]), torch.tensor([0.7, 1.5, 0.9])
    x = _points_around_box(box_min, box_max, 2000, seed=1)
    # Exactly on voxel centers too (align_corners=True puts voxels on the box faces).
    lattice = torch.stack(torch.meshgrid(*(torch.linspace(0, 1, n) for n in (9, 6, 5)), indexing="ij"), -1).reshape(-1, 3)
    x = torch.cat([x, box_min + lattice * (box_max - box_min)])
    blended = torch.randn(12, 5, 6, 9, generator=generator)
    posed = kernel.lbs(blended.permute(1, 2, 3, 0).contiguous(), box_min, box_max, x)
    torch.testing.assert_close(posed, apply_affine(sample_blended_transforms(blended, box_min, box_max, x), x),
                               atol=2e-5, rtol=1e-5)

    starts = x[-600:].reshape(200, 3, 3)  # (N, C, 3), C = 3 channels; includes the voxel-center points
    grid3 = values[:3]
    diagonal = kernel.sample_diagonal(grid3.permute(1, 2, 3, 0).contiguous(), box_min, box_max, starts)
    full = sample_grid(grid3, box_min, box_max, starts.reshape(-1, 3)).reshape(200, 3, 3)
    torch.testing.assert_close(diagonal, torch.diagonal(full, dim1=1, dim2=2), atol=2e-6, rtol=1e-5)


def test_kernel_rejects_wrong_layouts(kernel):
    grid = torch.zeros(4, 4, 4, 12)
    box = torch.zeros(3), torch.ones(3)
    with pytest.raises(RuntimeError, match=r"\(N, 3\)"):
        kernel.lbs(grid, *box, torch.zeros(5, 2))
    with pytest.raises(RuntimeError, match="12 channels"):
        kernel.lbs(torch.zeros(4, 4, 4, 5), *box, torch.zeros(5, 3))
    with pytest.raises(RuntimeError, match="float32"):
        kernel.lbs(grid.double(), *box, torch.zeros(5, 3))


@pytest.mark.parametrize("seed", [3, 4])
def test_broyden_kernel_matches_reference(kernel, seed):
    weights, box_min, box_max = _stick_figure_grid()
    deformer = FastSnarfDeformer(weights, box_min, box_max, DeformerConfig(init_bones=INIT_BONES))
    frame = deformer.prepare(_bone_transforms(seed))
    assert frame.blended_grid_last is not None
    x_true = _canonical_points(3000, seed=seed)
    x_posed = deformer.forward_skinning(x_true, frame)
    x_init = deformer.initial_points(x_posed, frame).reshape(-1, 3)
    x_target = x_posed[:, None, :].expand(-1, len(INIT_BONES), -1).reshape(-1, 3)
    config = deformer.config
    fast_x, fast_norm = _broyden(frame, x_target, x_init, config)
    ref_x, ref_norm = _broyden_reference(frame, x_target, x_init, config)
    converged_fast = fast_norm < config.converge_threshold
    converged_ref = ref_norm < config.converge_threshold
    # Float32 rounding may move a start across the threshold; it must stay a rare borderline case.
    agree = converged_fast == converged_ref
    assert float(agree.float().mean()) > 0.995
    both = converged_fast & converged_ref
    assert int(both.sum()) > 1000
    torch.testing.assert_close(fast_x[both], ref_x[both], atol=5e-5, rtol=0)
    # Starts that did not converge reach the same best residual up to rounding growth.
    torch.testing.assert_close(fast_norm[agree], ref_norm[agree], atol=1e-4, rtol=1e-3)


@pytest.mark.parametrize("ranked_by_parts", [False, True])
def test_canonicalize_same_with_and_without_kernel(kernel, ranked_by_parts):
    weights, box_min, box_max = _stick_figure_grid()
    parts = init_parts(PARENTS, INIT_BONES) if ranked_by_parts else None
    deformer = FastSnarfDeformer(weights, box_min, box_max,
                                 DeformerConfig(init_bones=INIT_BONES, init_top_k=4, init_parts=parts))
    bones = _bone_transforms(5)
    x_true = _canonical_points(2000, seed=5)
    frame = deformer.prepare(bones)
    x_posed = deformer.forward_skinning(x_true, frame)
    fast_candidates, fast_valid = deformer.canonicalize(x_posed, frame)
    set_kernels_enabled(False)
    frame_reference = deformer.prepare(bones)
    assert frame_reference.blended_grid_last is None  # the reference path really ran
    ref_candidates, ref_valid = deformer.canonicalize(x_posed, frame_reference)
    assert float((fast_valid == ref_valid).float().mean()) > 0.995
    both = fast_valid & ref_valid
    torch.testing.assert_close(fast_candidates[both], ref_candidates[both], atol=5e-5, rtol=0)
    # Both recover the true canonical point for (nearly) every posed point.
    assert float(_recovery(fast_candidates, fast_valid, x_true).float().mean()) > 0.99
    assert float(_recovery(ref_candidates, ref_valid, x_true).float().mean()) > 0.99


def test_forward_skinning_keeps_autograd_on_the_reference_path(kernel):
    weights, box_min, box_max = _stick_figure_grid()
    deformer = FastSnarfDeformer(weights, box_min, box_max, DeformerConfig(init_bones=INIT_BONES))
    frame = deformer.prepare(_bone_transforms(2))
    x = _canonical_points(50, seed=2).requires_grad_(True)
    posed = deformer.forward_skinning(x, frame)  # the kernel has no backward: must not be used
    posed.sum().backward()
    assert x.grad is not None and bool(x.grad.abs().sum() > 0)
    with torch.no_grad():
        torch.testing.assert_close(deformer.forward_skinning(x, frame), posed.detach(), atol=2e-5, rtol=1e-5)


def test_prepared_frame_grids_equal_the_reference_layout(kernel):
    weights, box_min, box_max = _stick_figure_grid()
    deformer = FastSnarfDeformer(weights.clone(), box_min, box_max, DeformerConfig(init_bones=INIT_BONES))
    bones = _bone_transforms(8)
    frame = deformer.prepare(bones)
    torch.testing.assert_close(frame.blended_grid, blended_transform_grid(weights, bones), atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(frame.blended_grid_last, frame.blended_grid.permute(1, 2, 3, 0))
    init = torch.tensor(INIT_BONES)
    torch.testing.assert_close(frame.init_weights_last, weights[init].permute(1, 2, 3, 0))
    # An in-place change of the weights (load_state_dict) must not leave a stale channel-last copy.
    with torch.no_grad():
        deformer.weights_grid.mul_(0.5)
    frame = deformer.prepare(bones)
    torch.testing.assert_close(frame.init_weights_last, 0.5 * weights[init].permute(1, 2, 3, 0))
