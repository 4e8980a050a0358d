"""Pose-conditioned non-rigid offset field f_dx(x_c, theta) -> dx added to the rigid correspondence.

    offsets = NonRigidOffset(NonRigidConfig(pose_dim=69)); offsets.set_enabled(True); offsets.set_window(0.5)
    x_canonical = x_rigid + offsets(x_rigid, pose_condition)           # (P, 3) + (P, 3)

Hann-windowed positional encoding of x_c (Nerfies' coarse-to-fine window: band k is weighted by
`(1 - cos(pi * clamp(alpha - k, 0, 1))) / 2`, alpha opened from 0 to the number of frequencies over
training) concatenated with the pose vector, an MLP, and a bounded output `max_offset * tanh(.)`.
The last layer starts near zero, so switching the field on does not jolt the geometry. While
disabled (warm-up) it returns zeros without running the MLP.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from igavatar.errors import InputError
from igavatar.kernels import kernels_enabled
from igavatar.model.linear import linear, pad_rows

__all__ = ["NonRigidConfig", "NonRigidOffset", "hann_window"]


@dataclass(frozen=True)
class NonRigidConfig:
    """Shape of the non-rigid offset network (defaults: the official InstantGeoAvatar code)."""

    pose_dim: int = 69
    """Length of the pose-conditioning vector (69 for SMPL body pose; larger for Anny)."""
    num_frequencies: int = 6
    """Positional-encoding octaves of x_c: sin/cos(2^k pi x), k = 0 .. num_frequencies - 1."""
    hidden_width: int = 128
    """Width of each hidden layer."""
    hidden_layers: int = 4
    """Number of hidden layers (ReLU)."""
    max_offset: float = 0.1
    """Bound of each offset component (world units): output is max_offset * tanh(.)."""
    last_layer_init_std: float = 1e-5
    """Std of the last layer's initial weights (its bias starts at 0): offsets start ~0."""

    def __post_init__(self) -> None:
        if self.pose_dim < 0 or self.num_frequencies < 0:
            raise InputError(
                f"NonRigidConfig: pose_dim={self.pose_dim}, num_frequencies={self.num_frequencies}; "
                "expected both >= 0"
            )
        if self.hidden_width < 1 or self.hidden_layers < 1:
            raise InputError(
                f"NonRigidConfig: hidden_width={self.hidden_width}, hidden_layers={self.hidden_layers}; "
                "expected both >= 1"
            )
        if self.max_offset <= 0:
            raise InputError(f"NonRigidConfig.max_offset: {self.max_offset}, expected > 0")


def hann_window(alpha: float, num_frequencies: int, device=None, dtype=None) -> torch.Tensor:
    """(num_frequencies,) band weights `(1 - cos(pi * clamp(alpha - k, 0, 1))) / 2`.

    alpha = 0 closes every band; alpha >= num_frequencies opens all of them.
    """
    k = torch.arange(num_frequencies, device=device, dtype=dtype)
    return 0.5 * (1.0 - torch.cos(math.pi * (alpha - k).clamp(0.0, 1.0)))


class NonRigidOffset(nn.Module):
    """f_dx: (x_canonical (P, 3), pose_condition (pose_dim,) or (P, pose_dim)) -> offsets (P, 3).

    Schedule state (`enabled`, window `alpha`) is part of the state dict (extra state), so a
    resumed checkpoint continues where it stopped.
    """

    def __init__(self, config: NonRigidConfig = NonRigidConfig()) -> None:
        super().__init__()
        self.config = config
        # Training switches the field on after warm-up; disabled it returns zeros.
        self.enabled = False
        # Hann window position in [0, num_frequencies]; 0 = no frequency band open.
        self.alpha = 0.0
        self.register_buffer(
            "frequencies",
            (2.0 ** torch.arange(config.num_frequencies, dtype=torch.float32)) * math.pi,
            persistent=False,
        )
        input_dim = 3 + 6 * config.num_frequencies + config.pose_dim
        layers: list[nn.Module] = []
        width_in = input_dim
        for _ in range(config.hidden_layers):
            layers += [nn.Linear(width_in, config.hidden_width), nn.ReLU(inplace=True)]
            width_in = config.hidden_width
        self.hidden = nn.Sequential(*layers)
        self.output = nn.Linear(width_in, 3)
        nn.init.normal_(self.output.weight, std=config.last_layer_init_std)
        nn.init.zeros_(self.output.bias)

    def set_enabled(self, enabled: bool) -> None:
        """Switch the field on (after warm-up) or off."""
        self.enabled = bool(enabled)

    def set_window(self, progress: float) -> None:
        """Open the frequency window: progress 0 -> only x itself, 1 -> all bands (alpha = L)."""
        if not 0.0 <= progress <= 1.0:
            raise InputError(f"NonRigidOffset.set_window: progress {progress}, expected in [0, 1]")
        self.alpha = float(progress) * self.config.num_frequencies

    def encode(self, x_canonical: torch.Tensor, alpha: float | None = None) -> torch.Tensor:
        """Windowed positional encoding.

        Args:
            x_canonical: (P, 3).
            alpha: window position; None uses the module's `alpha`.
        Returns:
            (P, 3 + 6 L): x, then sin of all (band, axis) pairs band-major, then cos likewise.
        """
        alpha = self.alpha if alpha is None else float(alpha)
        frequencies = self.frequencies.to(x_canonical.dtype)
        scaled = x_canonical.unsqueeze(1) * frequencies[None, :, None]  # (P, L, 3)
        window = hann_window(alpha, self.config.num_frequencies, x_canonical.device, x_canonical.dtype)
        window = window[None, :, None]
        sines = (torch.sin(scaled) * window).flatten(1)
        cosines = (torch.cos(scaled) * window).flatten(1)
        return torch.cat([x_canonical, sines, cosines], dim=1)

    def forward(
        self, x_canonical: torch.Tensor, pose_condition: torch.Tensor, alpha: float | None = None
    ) -> torch.Tensor:
        """Offsets at canonical points.

        Args:
            x_canonical: (P, 3) rigid canonical correspondences.
            pose_condition: (pose_dim,) shared by all points, or (P, pose_dim).
            alpha: window override; None uses `self.alpha` (see `set_window`).
        Returns:
            (P, 3) offsets, each component in (-max_offset, max_offset); zeros when disabled.
        """
        if x_canonical.ndim != 2 or x_canonical.shape[1] != 3:
            raise InputError(f"x_canonical: shape {tuple(x_canonical.shape)}, expected (P, 3)")
        num_points = x_canonical.shape[0]
        pose_dim = self.config.pose_dim
        if pose_condition.shape not in ((pose_dim,), (num_points, pose_dim)):
            raise InputError(
                f"pose_condition: shape {tuple(pose_condition.shape)}, expected ({pose_dim},) or ({num_points}, {pose_dim})"
            )
        if not self.enabled:
            return torch.zeros_like(x_canonical)
        if pose_condition.ndim == 1 and kernels_enabled():
            return self._forward_shared_pose(x_canonical, pose_condition, alpha)
        return self._forward_reference(x_canonical, pose_condition, alpha)

    def _forward_shared_pose(self, x_canonical: torch.Tensor, pose_condition: torch.Tensor, alpha: float | None) -> torch.Tensor:
        """Fast path for one pose shared by all points: the first layer's pose columns are applied
        once (W [enc; pose] + b = W_enc enc + (W_pose pose + b)), not once per point. With Anny's
        309-d pose that is ~90% of the first layer and ~40% of the network's work, forward and
        backward. Same function as `_forward_reference` up to float rounding (tested)."""
        first = self.hidden[0]
        encoded = self.encode(x_canonical, alpha)
        n_encoded = encoded.shape[1]
        weight = first.weight.to(x_canonical.dtype)
        bias = first.bias.to(x_canonical.dtype) + weight[:, n_encoded:] @ pose_condition.to(x_canonical.dtype)
        # Rows padded to a cached matrix shape (see linear.pad_rows), sliced off at the output.
        h = linear(pad_rows(encoded), weight[:, :n_encoded], bias, relu=True)
        for layer in self.hidden[2::2]:  # the Linear modules after the first (ReLU between them)
            h = linear(h, layer.weight, layer.bias, relu=True)
        out = linear(h, self.output.weight, self.output.bias)[: x_canonical.shape[0]]
        return self.config.max_offset * torch.tanh(out)

    def _forward_reference(self, x_canonical: torch.Tensor, pose_condition: torch.Tensor, alpha: float | None) -> torch.Tensor:
        """The network as written: [encoding, pose] concatenated per point through the MLP."""
        num_points, pose_dim = x_canonical.shape[0], self.config.pose_dim
        features = torch.cat(
            [
                self.encode(x_canonical, alpha),
                pose_condition.to(x_canonical.dtype).expand(num_points, pose_dim),
            ],
            dim=1,
        )
        return self.config.max_offset * torch.tanh(self.output(self.hidden(features)))

    def get_extra_state(self) -> dict[str, Any]:
        return {"enabled": self.enabled, "alpha": self.alpha}

    def set_extra_state(self, state: dict[str, Any]) -> None:
        self.enabled = bool(state["enabled"])
        self.alpha = float(state["alpha"])
