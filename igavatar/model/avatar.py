"""The avatar: canonical SDF + color fields, Laplace density, non-rigid offsets, Fast-SNARF deformer.

    avatar = Avatar(AvatarConfig(), canonical_box, skinning_grid, grid_box_min, grid_box_max, pose_dim)
    frame = avatar.deformer.prepare(bone_transforms)                   # once per frame
    x_canonical, found = avatar.correspond(x_posed, frame, pose_condition)  # posed -> canonical (no grad)
    out = avatar.field_at(x_canonical, pose_condition)                 # sigma, rgb, gradient, sdf

Posing follows the paper: the rigid correspondence from root finding plus a pose-conditioned
offset, `x = x_rigid + f_dx(x_rigid, theta)`, at which the canonical fields are evaluated. Among
several valid roots of one posed point the one with the highest density wins (official code).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import torch
from torch import nn
from torch.nn import functional as F

from igavatar.model.deformer import DeformerConfig, FastSnarfDeformer, PreparedFrame, init_parts
from igavatar.model.fields import (
    ColorField,
    ColorFieldConfig,
    LaplaceDensity,
    LaplaceDensityConfig,
    SDFField,
    SDFFieldConfig,
    silhouette_offset,
)
from igavatar.model.nonrigid import NonRigidConfig, NonRigidOffset
from igavatar.model.shading import SHADINGS, WorldShading, posed_normals
from igavatar.render.volume import FieldOutput

#: Where meshes are made: "silhouette" (the level set where the renderer's silhouette lies,
#: `silhouette_offset(beta)` outside the SDF's zero level) or "zero" (the zero level itself).
SURFACE_LEVELS = ("silhouette", "zero")


@dataclass(frozen=True)
class AvatarConfig:
    """Architecture of every learned part, and how posed points find their canonical match."""

    sdf: SDFFieldConfig = field(default_factory=SDFFieldConfig)
    """Canonical SDF field (hash grid + MLP)."""
    color: ColorFieldConfig = field(default_factory=ColorFieldConfig)
    """Canonical color field."""
    density: LaplaceDensityConfig = field(default_factory=lambda: LaplaceDensityConfig(beta_init=0.075))
    """Laplace density; beta starts at 0.075 after shape initialization (official)."""
    nonrigid_width: int = 128
    """Hidden width of the non-rigid offset MLP."""
    nonrigid_layers: int = 4
    """Hidden layers of the non-rigid offset MLP."""
    nonrigid_max_offset: float = 0.1
    """Bound of the non-rigid offset in meters (output = bound * tanh)."""
    deformer: DeformerConfig = field(default_factory=lambda: DeformerConfig(init_top_k=4))
    """Root finding; by default each point starts from the 4 bones that best explain it rigidly."""
    shading: str = "none"
    """How the posed colour is lit: "none" (the paper: the canonical colour as it is) or "sh9"
    (the canonical colour is the albedo, times the clip's light as nine spherical harmonics of the
    posed surface's world normal; igavatar.model.shading)."""

    def __post_init__(self) -> None:
        if self.shading not in SHADINGS:
            raise ValueError(f"AvatarConfig.shading {self.shading!r}: expected one of {', '.join(SHADINGS)}")


class Avatar(nn.Module):
    """All learned parts of one subject, plus the (fixed) skinning grid inside the deformer.

    Args:
        config: AvatarConfig.
        canonical_box: (2, 3) box of the SDF's hash grid in canonical space.
        skinning_grid: (J, D, H, W) canonical skinning weights.
        grid_box_min, grid_box_max: (3,) box of the skinning grid.
        pose_dim: length of the pose-conditioning vector of the non-rigid offset.
        init_bones: bones root finding starts from (the body's major bones), overriding the
            deformer config's; None keeps the config's.
        parents: (J,) the skeleton's parent per bone; with init_bones, the starts are ranked by
            their parts' weights (DeformerConfig.init_parts).
    """

    def __init__(
        self,
        config: AvatarConfig,
        canonical_box: torch.Tensor,
        skinning_grid: torch.Tensor,
        grid_box_min: torch.Tensor,
        grid_box_max: torch.Tensor,
        pose_dim: int,
        init_bones: tuple[int, ...] | None = None,
        parents: tuple[int, ...] | None = None,
    ) -> None:
        super().__init__()
        self.config = config
        self.sdf_field = SDFField(config.sdf, canonical_box[0], canonical_box[1])
        self.color_field = ColorField(config.color, canonical_box[0], canonical_box[1])
        self.density = LaplaceDensity(config.density)
        self.nonrigid = NonRigidOffset(
            NonRigidConfig(
                pose_dim=pose_dim, hidden_width=config.nonrigid_width, hidden_layers=config.nonrigid_layers,
                max_offset=config.nonrigid_max_offset,
            )
        )
        deformer_config = config.deformer
        if init_bones is not None:
            parts = None if parents is None else init_parts(parents, init_bones)
            deformer_config = replace(deformer_config, init_bones=tuple(init_bones), init_parts=parts)
        self.deformer = FastSnarfDeformer(skinning_grid, grid_box_min, grid_box_max, deformer_config)
        self.register_buffer("canonical_box", canonical_box.clone())
        self.shading = WorldShading() if config.shading == "sh9" else None

    def surface_level(self, mode: str) -> float:
        """Meters outside the SDF's zero level at which meshes are made: 0 for "zero", where the
        renderer's silhouette lies for "silhouette" (SURFACE_LEVELS)."""
        if mode not in SURFACE_LEVELS:
            raise ValueError(f"surface level {mode!r}: expected one of {SURFACE_LEVELS}")
        if mode == "zero":
            return 0.0
        return silhouette_offset(float(self.density.beta.detach()))

    def surface_sdf(self, x_canonical: torch.Tensor, level_m: float) -> torch.Tensor:
        """(M,) signed distance to the meshed surface (the SDF minus `level_m`, see `surface_level`)
        at (M, 3) canonical points."""
        return self.sdf_field(x_canonical)[0].reshape(-1) - level_m

    def canonical_density(self, x_canonical: torch.Tensor) -> torch.Tensor:
        """sigma (P,) at canonical points, without non-rigid offsets (for the occupancy grid)."""
        sdf, _ = self.sdf_field(x_canonical)
        return self.density(sdf)

    def offset_points(self, x_rigid: torch.Tensor, pose_condition: torch.Tensor, nonrigid: bool = True) -> torch.Tensor:
        """(M, 3) rigid canonical points plus the pose-conditioned non-rigid offset, when training
        has enabled it and the caller wants it (`nonrigid`: export --no-nonrigid does not)."""
        if not (nonrigid and self.nonrigid.enabled):
            return x_rigid
        return x_rigid + self.nonrigid(x_rigid, pose_condition)

    @torch.no_grad()
    def correspond(
        self, x_posed: torch.Tensor, frame: PreparedFrame, pose_condition: torch.Tensor, nonrigid: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Rigid canonical correspondences of posed points.

        Args:
            x_posed: (M, 3) posed world points.
            frame: the deformer's PreparedFrame of this frame.
            pose_condition: (pose_dim,) conditioning of the non-rigid offset (used to score candidates).
            nonrigid: whether candidates are scored with the offset (see `offset_points`).
        Returns:
            x_canonical (M, 3) rigid correspondences (before the non-rigid offset) and found (M,)
            bool: whether any valid root exists. Points not found get their first iterate.
        """
        candidates, valid = self.deformer.canonicalize(x_posed, frame)
        count = valid.sum(dim=1)
        chosen = torch.where(valid.any(dim=1, keepdim=True), valid.float().argmax(dim=1, keepdim=True), 0)[:, 0]
        ambiguous = count > 1
        if bool(ambiguous.any()):
            # Score only the candidates that matter: valid roots of points with several of them.
            cand = candidates[ambiguous]
            cand_valid = valid[ambiguous]
            sdf, _ = self.sdf_field(self.offset_points(cand[cand_valid], pose_condition, nonrigid))
            score = torch.full(cand_valid.shape, float("-inf"), dtype=sdf.dtype, device=sdf.device)
            score[cand_valid] = -sdf  # highest density = lowest signed distance
            chosen[ambiguous] = score.argmax(dim=1)
        x_canonical = candidates.gather(1, chosen[:, None, None].expand(-1, 1, 3))[:, 0]
        return x_canonical, count > 0

    def field_at(
        self,
        x_rigid: torch.Tensor,
        pose_condition: torch.Tensor,
        *,
        sigma_noise_std: float = 0.0,
        generator: torch.Generator | None = None,
        nonrigid: bool = True,
        frame: PreparedFrame | None = None,
    ) -> FieldOutput:
        """Canonical fields at rigid correspondences (the non-rigid offset is applied here).

        Args:
            x_rigid: (M, 3) canonical points from `correspond`.
            pose_condition: (pose_dim,) conditioning of the non-rigid offset.
            sigma_noise_std: std of Gaussian noise added to the density (early training), clamped >= 0.
            generator: RNG of that noise.
            nonrigid: whether the offset applies (see `offset_points`).
            frame: the posed frame, whose world normals light the colour when the avatar has a
                shading model (AvatarConfig.shading); None gives the canonical colour (albedo).
        Returns:
            FieldOutput with sigma (M,), rgb (M, 3), sdf (M,) and the analytic SDF gradient (M, 3)
            (closed form, so it costs no double backward), differentiable wrt the parameters.
        """
        x_canonical = self.offset_points(x_rigid, pose_condition, nonrigid)
        sdf, feature, gradient = self.sdf_field.forward_with_gradient(x_canonical)
        normal = F.normalize(gradient, dim=-1, eps=1e-12)
        # A detached normal keeps the colour loss from tilting the surface (ColorFieldConfig.normal_gradient).
        rgb = self.color_field(feature, normal if self.config.color.normal_gradient else normal.detach(), x_canonical)
        if self.shading is not None and frame is not None:
            # The light reads the surface's orientation but does not turn it: a shading error is
            # the light's or the albedo's to fix, not the geometry's (texture kept off the surface).
            normal_world = posed_normals(frame.blended_grid, frame.box_min, frame.box_max, x_rigid.detach(), normal.detach())
            rgb = rgb * self.shading(normal_world)
        sigma = self.density(sdf)
        if sigma_noise_std > 0:
            noise = torch.randn(sigma.shape, generator=generator, device=sigma.device, dtype=sigma.dtype)
            sigma = (sigma + sigma_noise_std * noise).clamp_min(0.0)
        return FieldOutput(sigma=sigma, rgb=rgb, gradient=gradient, sdf=sdf)
