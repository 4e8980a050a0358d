"""A trained avatar in one frame: every posed-space query goes through here.

    posed = PosedAvatar.of(avatar, bone_transforms, pose_condition)   # (J, 4, 4) canonical -> world, (pose_dim,)
    posed.field_fn(x_posed)        # renderer FieldOutput; density 0 where no canonical root exists
    posed.sdf(x_posed, level_m)    # (M,) canonical SDF at the correspondences, NO_ROOT_SDF without one
    posed.colors(x_posed)          # (M, 3) sRGB in [0, 1]
    posed.pose_vertices(v_canon)   # canonical surface vertices -> world (non-rigid offset included)
    posed.occupancy(canonical_grid, posed_box, resolution)

Posed point -> canonical field (the paper's Sec. 3): Fast-SNARF root finding gives the rigid
correspondence x_r (`correspond`), the pose-conditioned non-rigid offset moves it to x_r + dx(x_r,
pose) where the canonical fields are read (`Avatar.field_at`). The trainer, the renderer, mesh
export, animation and evaluation all use this one path.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from igavatar.model.avatar import Avatar
from igavatar.model.deformer import PreparedFrame
from igavatar.model.posed_occupancy import posed_occupancy
from igavatar.render.occupancy import OccupancyGrid
from igavatar.render.sampler import RaySamples
from igavatar.render.volume import FieldOutput

#: Meters: the SDF of posed points with no canonical correspondence ("far outside").
NO_ROOT_SDF = 1.0


@dataclass(frozen=True)
class PosedAvatar:
    """An Avatar with one frame's bone transforms prepared and its pose conditioning.

    Attributes:
        avatar: the Avatar (canonical SDF, color, non-rigid offset, deformer).
        frame: the deformer's PreparedFrame of the frame's (J, 4, 4) bone transforms.
        pose_condition: (pose_dim,) conditioning of the non-rigid offset, on the avatar's device.
        nonrigid: whether the pose-conditioned offset applies (when training has enabled it);
            False poses by skinning alone (export --no-nonrigid).
    """

    avatar: Avatar
    frame: PreparedFrame
    pose_condition: torch.Tensor
    nonrigid: bool = True

    @classmethod
    def of(cls, avatar: Avatar, bone_transforms: torch.Tensor, pose_condition: torch.Tensor,
           nonrigid: bool = True) -> PosedAvatar:
        """Pose `avatar` with (J, 4, 4) canonical -> world transforms and (pose_dim,) conditioning."""
        device = avatar.canonical_box.device
        return cls(avatar, avatar.deformer.prepare(bone_transforms.to(device)), pose_condition.to(device), nonrigid)

    @property
    def offset_applies(self) -> bool:
        """Whether posed points move by the non-rigid offset (wanted here and enabled by training)."""
        return self.nonrigid and self.avatar.nonrigid.enabled

    @property
    def device(self) -> torch.device:
        return self.avatar.canonical_box.device

    def correspond(self, x_posed: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(M, 3) world points -> rigid canonical correspondences (M, 3) and found (M,) bool."""
        return self.avatar.correspond(x_posed, self.frame, self.pose_condition, self.nonrigid)

    def fields_at(
        self, x_rigid: torch.Tensor, *, sigma_noise_std: float = 0.0, generator: torch.Generator | None = None
    ) -> FieldOutput:
        """Differentiable canonical fields at rigid correspondences (see Avatar.field_at)."""
        return self.avatar.field_at(x_rigid, self.pose_condition, sigma_noise_std=sigma_noise_std, generator=generator,
                                    nonrigid=self.nonrigid, frame=self.frame)

    def canonical_samples(self, samples: RaySamples) -> tuple[RaySamples, torch.Tensor]:
        """Posed ray samples -> the same samples at their rigid canonical correspondences.

        Every kept sample is root-found once; samples without a root become empty (invalid).
        Returns the canonical RaySamples (positions (R, S, 3), valid (R, S)) and the (M, 3) rigid
        correspondences of its valid samples, in the samples' valid order.
        """
        x_rigid, found = self.correspond(samples.valid_positions())
        valid = samples.valid.clone()
        valid[samples.valid] = found
        x_rigid = x_rigid[found]
        positions = torch.zeros_like(samples.positions)
        positions[valid] = x_rigid
        return dataclasses.replace(samples, positions=positions, valid=valid), x_rigid

    def field_fn(self, x_posed: torch.Tensor) -> FieldOutput:
        """The renderer's field callable on (M, 3) world points; empty (density 0) without a root."""
        x_rigid, found = self.correspond(x_posed)
        out = self.fields_at(x_rigid)
        return FieldOutput(sigma=torch.where(found, out.sigma, 0.0), rgb=out.rgb, gradient=out.gradient, sdf=out.sdf)

    @torch.no_grad()
    def sdf(self, x_posed: torch.Tensor, level_m: float) -> torch.Tensor:
        """(M,) signed distance to the meshed surface (Avatar.surface_sdf at `level_m`) at the
        correspondences of (M, 3) world points; NO_ROOT_SDF without one."""
        x_rigid, found = self.correspond(x_posed)
        sdf = self.avatar.surface_sdf(self.avatar.offset_points(x_rigid, self.pose_condition, self.nonrigid), level_m)
        return torch.where(found, sdf, torch.full_like(sdf, NO_ROOT_SDF))

    @torch.no_grad()
    def canonical_points(self, x_posed: torch.Tensor) -> torch.Tensor:
        """(M, 3) canonical points (non-rigid offset applied) where (M, 3) world points read the fields."""
        x_rigid, _ = self.correspond(x_posed)
        return self.avatar.offset_points(x_rigid, self.pose_condition, self.nonrigid)

    @torch.no_grad()
    def skin(self, x_canonical: torch.Tensor) -> torch.Tensor:
        """(M, 3) canonical points -> (M, 3) world points by forward LBS (no non-rigid offset)."""
        return self.avatar.deformer.forward_skinning(x_canonical.to(self.device), self.frame)

    @torch.no_grad()
    def pose_vertices(self, vertices_canonical: np.ndarray, iterations: int = 3, chunk: int = 65536) -> np.ndarray:
        """World positions (V, 3) float32 of canonical surface vertices, the non-rigid offset included.

        A canonical surface point v is v = x_r + dx(x_r, pose), so x_r comes from the fixed-point
        iteration x_r <- v - dx(x_r, pose) (dx is bounded and smooth: a few iterations suffice)
        and is then skinned forward.
        """
        nonrigid = self.avatar.nonrigid
        posed = []
        for part in torch.from_numpy(np.asarray(vertices_canonical, np.float32)).split(chunk):
            v = part.to(self.device)
            x_rigid = v
            if self.offset_applies:
                for _ in range(iterations):
                    x_rigid = v - nonrigid(x_rigid, self.pose_condition)
            posed.append(self.avatar.deformer.forward_skinning(x_rigid, self.frame).cpu())
        if not posed:
            return np.zeros((0, 3), np.float32)
        return torch.cat(posed).numpy().astype(np.float32)

    def occupancy(self, canonical_grid: OccupancyGrid, posed_box: torch.Tensor, resolution: int) -> OccupancyGrid:
        """The frame's posed occupancy grid over a (2, 3) world box (the canonical grid pushed through LBS)."""
        return posed_occupancy(canonical_grid, self.avatar.deformer, self.frame, posed_box, resolution)
