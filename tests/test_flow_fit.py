"""The landmark fit's optical-flow term: surface points move as the person's pixels move."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from igavatar.body.flow_fit import FlowTarget, visible_points


def _texture(height: int, width: int, seed: int = 0) -> np.ndarray:
    """(H, W, 3) uint8 smooth random texture (blobs a few px wide), which optical flow can follow."""
    import cv2

    noise = np.random.default_rng(seed).random((height, width)).astype(np.float32)
    grey = cv2.GaussianBlur(noise, (0, 0), 2.0)
    grey = (grey - grey.min()) / (grey.max() - grey.min())
    return np.repeat((255 * grey).astype(np.uint8)[..., None], 3, axis=-1)


def _shifted_frames(shift_xy: tuple[int, int]) -> tuple[list[np.ndarray], np.ndarray]:
    """Two 96 x 128 frames, the second the first's texture moved by shift_xy px, and full masks."""
    big = _texture(140, 170)
    dx, dy = shift_xy
    first = big[20:116, 20:148]
    second = big[20 - dy:116 - dy, 20 - dx:148 - dx]
    return [first, second], np.ones((2, 96, 128), np.float32)


def test_visible_points_keeps_the_nearest_point_of_a_cell_and_every_lone_point():
    uv = torch.tensor([[[5.0, 5.0], [6.0, 6.0], [50.0, 50.0], [7.0, 5.0]]], dtype=torch.float64)
    depth = torch.tensor([[2.0, 2.5, 3.0, 2.02]], dtype=torch.float64)
    visible = visible_points(uv, depth)
    # Points 0, 1 and 3 share a cell: the one 50 cm behind is hidden, the one 2 cm behind is not.
    assert visible.tolist() == [[True, False, True, True]]


def test_flow_of_a_shifted_texture_is_the_shift_and_points_moving_with_it_cost_nothing():
    images, masks = _shifted_frames((3, -2))
    target = FlowTarget.of(images, masks)
    assert target.flow.shape == (1, 2, 96, 128) and target.map_scale == 1.0
    inner = target.flow[0, :, 20:76, 20:108]
    assert torch.allclose(inner.median(dim=-1).values.median(dim=-1).values, torch.tensor([3.0, -2.0]), atol=0.2)
    assert float(target.reliable[0, 0, 20:76, 20:108].mean()) > 0.9
    # Spread apart so that no two points share an occlusion cell: every point is visible.
    start = torch.stack(torch.meshgrid(torch.arange(5) * 14.0 + 30, torch.arange(4) * 13.0 + 25, indexing="xy"),
                        -1).reshape(-1, 2).to(torch.float64)
    depth = torch.full((2, len(start)), 2.0, dtype=torch.float64)
    moving = torch.stack((start, start + torch.tensor([3.0, -2.0], dtype=torch.float64)))
    residual, weight = target.residual_px(moving, depth)
    assert float(weight.mean()) > 0.9
    assert float((residual * weight).sum() / weight.sum()) < 0.3
    assert target.mean_px(moving, depth) == pytest.approx(float((residual * weight).sum() / weight.sum()))
    # Points that stay still are off by the whole motion, and the loss's gradient moves them with it.
    still = torch.stack((start, start.clone())).requires_grad_(True)
    residual, weight = target.residual_px(still, depth)
    assert float((residual * weight).sum().detach() / weight.sum()) == pytest.approx(np.hypot(3, 2), abs=0.3)
    target.loss_px(still, depth).backward()
    step = -still.grad[1][weight[0] > 0]
    direction = step / step.norm(dim=-1, keepdim=True)
    assert float((direction @ torch.tensor([3.0, -2.0], dtype=torch.float64) / np.hypot(3, 2)).min()) > 0.95


def test_flow_is_not_trusted_outside_the_mask():
    images, masks = _shifted_frames((2, 1))
    masks[0, :, 64:] = 0.0
    target = FlowTarget.of(images, masks)
    assert float(target.reliable[0, 0, :, 70:].max()) == 0.0
    assert float(target.reliable[0, 0, 10:86, 10:58].mean()) > 0.9
