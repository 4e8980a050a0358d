"""An optical-flow term for the landmark fit: the body's surface moves as the person's pixels move.

    target = FlowTarget.of(images, masks)                  # forward flow between consecutive frames
    loss = target.loss_px(uv, depth)                       # robust mean px off the flow

Landmarks are detected in each frame on its own, a few pixels off, and the fit's smoothness prior
that averages this jitter away also flattens fast real motion (a walk, a squat). The frames
themselves say how every visible pixel moved from one frame to the next: dense optical flow
(OpenCV's DIS) between consecutive frames. Each visible surface point of the posed body projects
to uv_t in frame t and uv_t+1 in frame t+1; the term asks uv_t+1 - uv_t to equal the flow read at
uv_t. It ties consecutive poses together where the person's texture is, without a prior on how
fast they may change, and needs no avatar.

Only reliable flow counts: inside frame t's mask, and where the backward flow brings the pixel back
within FORWARD_BACKWARD_PX (occlusions and untextured areas fail that check). A point counts where
it is visible in both frames: nearest to the camera within DEPTH_MARGIN_M among the points that
project into the same OCCLUSION_BIN_PX cell (a z-buffer of points; the arm in front of the torso
hides the torso's points behind it, the far side of the body is hidden by the near side).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from igavatar.body.image_maps import frame_px_grid, huber_px, shrunk_size

#: Flow maps are kept at most this many pixels on a side (float32, as the silhouette's distance maps).
FLOW_MAP_SIDE = 512
#: Flow is trusted where the backward flow returns within this many pixels of the start.
FORWARD_BACKWARD_PX = 1.0
#: Occlusion test: points projecting into one cell of this many pixels...
OCCLUSION_BIN_PX = 12.0
#: ... are visible within this depth of the cell's nearest point.
DEPTH_MARGIN_M = 0.04
#: Below this many pixels off the flow, the penalty is quadratic.
HUBER_PX = 1.0


@dataclass(frozen=True)
class FlowTarget:
    """Forward flow between consecutive frames and where it is reliable.

    Attributes:
        flow: (N-1, 2, h, w) float32 the motion (x, y) of each pixel of frame t into frame t+1, in
            frame px, at 1 / map_scale of the frame's size.
        reliable: (N-1, 1, h, w) float32 1 where the flow is trusted (inside frame t's mask and
            forward-backward consistent), else 0.
        map_scale: frame px per map px.
    """

    flow: torch.Tensor
    reliable: torch.Tensor
    map_scale: float

    @classmethod
    def of(cls, images: list[np.ndarray] | np.ndarray, masks: np.ndarray) -> "FlowTarget":
        """From N frames (each (H, W, 3) uint8 RGB) and their (N, H, W) mask probabilities."""
        if len(images) < 2:
            raise ValueError("FlowTarget needs at least two frames")
        scale, size = shrunk_size(*np.asarray(images[0]).shape[:2], FLOW_MAP_SIDE)
        grey = [cv2.resize(cv2.cvtColor(np.asarray(image), cv2.COLOR_RGB2GRAY), size, interpolation=cv2.INTER_AREA)
                for image in images]
        inside = [cv2.resize(np.asarray(mask, dtype=np.float32), size, interpolation=cv2.INTER_AREA) >= 0.5
                  for mask in masks]
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        flows, reliable = [], []
        for t in range(len(grey) - 1):
            forward = dis.calc(grey[t], grey[t + 1], None)
            backward = dis.calc(grey[t + 1], grey[t], None)
            flows.append(forward * np.float32(scale))
            reliable.append(inside[t] & (_round_trip_px(forward, backward) <= FORWARD_BACKWARD_PX / scale))
        flow = torch.as_tensor(np.stack(flows)).permute(0, 3, 1, 2).contiguous()
        return cls(flow, torch.as_tensor(np.stack(reliable), dtype=torch.float32)[:, None], float(scale))

    def residual_px(self, uv: torch.Tensor, depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N-1, S) distance of each point's image motion from the flow (px), and its (N-1, S) weight
        (1 where the point is visible in both frames and the flow there is reliable, else 0).

        Args:
            uv: (N, S) x 2 pixels of the posed surface points in each frame (differentiable).
            depth: (N, S) their camera-frame depths (meters), for the occlusion test.
        """
        with torch.no_grad():
            visible = visible_points(uv, depth)
            flow, reliable = self._sample(uv[:-1].detach())
            weight = visible[:-1] & visible[1:] & (reliable > 0.5)
        moved = uv[1:] - uv[:-1]
        return (moved - flow.to(uv.dtype)).norm(dim=-1), weight.to(uv.dtype)

    def loss_px(self, uv: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """Robust mean of residual_px over the weighted points (0 if none)."""
        residual, weight = self.residual_px(uv, depth)
        return (weight * huber_px(residual, HUBER_PX)).sum() / weight.sum().clamp_min(1.0)

    def mean_px(self, uv: torch.Tensor, depth: torch.Tensor) -> float:
        """For the record: the mean residual_px over the weighted points (NaN if none)."""
        with torch.no_grad():
            residual, weight = self.residual_px(uv, depth)
            return float((weight * residual).sum() / weight.sum()) if float(weight.sum()) > 0 else float("nan")

    def _sample(self, uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The flow (N-1, S, 2) and reliability (N-1, S) at frame px uv (N-1, S, 2); outside the
        image the reliability reads 0."""
        grid = frame_px_grid(uv, self.map_scale, *self.flow.shape[-2:])[:, None].to(self.flow.dtype)
        flow = torch.nn.functional.grid_sample(self.flow, grid, mode="bilinear", padding_mode="border",
                                               align_corners=True)[:, :, 0].transpose(1, 2)
        reliable = torch.nn.functional.grid_sample(self.reliable, grid, mode="bilinear", padding_mode="zeros",
                                                   align_corners=True)[:, 0, 0]
        return flow, reliable


def _round_trip_px(forward: np.ndarray, backward: np.ndarray) -> np.ndarray:
    """(h, w) how far (map px) a pixel lands from its start after the forward then the backward flow."""
    height, width = forward.shape[:2]
    x, y = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    back = cv2.remap(backward, x + forward[..., 0], y + forward[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=(1e3, 1e3))
    return np.linalg.norm(forward + back, axis=-1)


def visible_points(uv: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
    """(N, S) bool: each projected point is within DEPTH_MARGIN_M of the nearest point in its
    OCCLUSION_BIN_PX cell of its frame (a z-buffer of the points themselves).

    Args:
        uv: (N, S, 2) pixels; depth: (N, S) camera-frame depths (meters).
    """
    cells = torch.floor(uv / OCCLUSION_BIN_PX).long()
    cells = cells - cells.amin(dim=1, keepdim=True)
    columns = int(cells[..., 0].max()) + 1
    key = cells[..., 1] * columns + cells[..., 0]  # (N, S) cell index within the frame
    n_cells = int(key.max()) + 1
    nearest = torch.full((uv.shape[0], n_cells), float("inf"), dtype=depth.dtype)
    nearest = nearest.scatter_reduce(1, key, depth, reduce="amin")
    return depth <= torch.gather(nearest, 1, key) + DEPTH_MARGIN_M
