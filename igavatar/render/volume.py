"""Alpha compositing of ray samples through a field given as a callable (no model imports).

    out = render_rays(samples, field_fn, background)          # training: noise background, every sample
    out = march_rays(samples, field_fn, white)                # eval: front to back, stops when opaque
    image = render_image(K, w2c, H, W, field_fn, box_min, box_max, occupied_fn=grid.is_occupied)

``field_fn`` maps the **valid** sample positions only, flattened to (M, 3), to a
:class:`FieldOutput` (or a mapping with the same keys). It is free to warp posed points to
canonical space, run the SDF and color networks and turn the SDF into density; the renderer only
composites. Compositing (paper Sec. 3.2): ``alpha_i = 1 - exp(-sigma_i * delta_i)``, transmittance
``T_i = prod_{j<i} (1 - alpha_j) = exp(-sum_{j<i} sigma_j delta_j)`` (computed as an exclusive
cumulative sum in log space, which stays accurate where the product underflows), weights
``w_i = alpha_i T_i``, color ``sum_i w_i c_i + (1 - sum_i w_i) * background``. Invalid samples have
sigma * delta = 0, so they neither add color nor attenuate later samples.

``delta_i`` is the sample's interval length along the posed-space ray (as the released code
does; the paper's notation writes canonical points). ``sigma`` must be >= 0: training-time density
noise belongs inside ``field_fn``, clamped there.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from igavatar.render.rays import pixel_grid, pixel_rays, rays_in_box
from igavatar.render.sampler import OccupiedFn, RaySamples, sample_along_rays

__all__ = ["FieldFn", "FieldOutput", "ImageRender", "RenderOutput", "march_rays", "render_image", "render_rays"]


@dataclass(frozen=True)
class FieldOutput:
    """What a field callable returns for M points.

    Attributes:
        sigma: (M,) non-negative density.
        rgb: (M, 3) color in [0, 1].
        gradient: (M, 3) or None; SDF gradient (analytic), used by the eikonal and smoothness
            losses; also gives the normal map when ``normal`` is None.
        normal: (M, 3) or None; unit normal for the normal map when it differs from the
            normalized gradient (e.g. gradient in canonical space, normal rotated to posed).
        sdf: (M,) or None; signed distance, passed through for losses that want it.
    """

    sigma: Tensor
    rgb: Tensor
    gradient: Tensor | None = None
    normal: Tensor | None = None
    sdf: Tensor | None = None

    @staticmethod
    def coerce(value: FieldOutput | Mapping[str, Tensor], num_points: int) -> FieldOutput:
        """Accept a FieldOutput or a mapping with keys sigma, rgb[, gradient, normal, sdf]; check shapes."""
        if isinstance(value, Mapping):
            unknown = set(value) - {"sigma", "rgb", "gradient", "normal", "sdf"}
            if unknown or "sigma" not in value or "rgb" not in value:
                raise ValueError(
                    f"field_fn returned keys {sorted(value)}; expected sigma, rgb and optionally "
                    "gradient, normal, sdf"
                )
            value = FieldOutput(**value)
        if not isinstance(value, FieldOutput):
            raise TypeError(f"field_fn returned {type(value).__name__}, expected FieldOutput or a mapping")
        m = num_points
        expected = {"sigma": (m,), "rgb": (m, 3), "gradient": (m, 3), "normal": (m, 3), "sdf": (m,)}
        for name, shape in expected.items():
            tensor = getattr(value, name)
            if tensor is not None and tuple(tensor.shape) != shape:
                raise ValueError(f"field_fn returned {name} of shape {tuple(tensor.shape)}, expected {shape}")
        return value


FieldFn = Callable[[Tensor], FieldOutput | Mapping[str, Tensor]]
"""x (M, 3) valid sample positions in the rays' frame -> FieldOutput for those M points."""


@dataclass(frozen=True)
class RenderOutput:
    """Composited pixels and the per-sample quantities the losses need.

    Attributes:
        rgb: (R, 3) color composited on the background.
        opacity: (R,) accumulated weight ``sum_i w_i`` (= 1 - final transmittance).
        depth: (R,) expected termination distance ``sum_i w_i t_i`` (0 contribution from the
            background; divide by opacity for the depth of the surface alone).
        normal: (R, 3) ``sum_i w_i n_i`` with unit per-sample normals (length ~ opacity);
            zeros when the field returns neither normal nor gradient.
        weights: (R, S) compositing weights, zero on invalid or terminated samples.
        sigma: (R, S) densities, zero on invalid samples.
        t: (R, S) sample distances.
        valid: (R, S) samples the field was evaluated at (with early termination: minus the
            samples skipped after the ray became opaque).
        gradient: (R, S, 3) or None; the field's gradient, zeros on invalid samples. The eikonal
            term takes ``gradient[valid]`` (M, 3); the smoothness term takes (gradient, valid).
            None only when the field returned no gradient; all zeros when it was never called.
        sdf: (R, S) or None; zeros on invalid samples (same None rule as ``gradient``).
        sample_rgb: (R, S, 3) the field's colour at each sample, zeros on invalid samples.
    """

    rgb: Tensor
    opacity: Tensor
    depth: Tensor
    normal: Tensor
    weights: Tensor
    sigma: Tensor
    t: Tensor
    valid: Tensor
    gradient: Tensor | None
    sdf: Tensor | None
    sample_rgb: Tensor | None = None

    def rgb_on_fixed_weights(self, background: Tensor) -> Tensor:
        """(R, 3) the same composite as `rgb`, through which a loss reaches the colours only, not
        the weights (and so not the geometry): sum_i sg(w_i) c_i + (1 - sg(opacity)) background."""
        weights = self.weights.detach()
        return (weights[..., None] * self.sample_rgb).sum(dim=1) + (1.0 - weights.sum(dim=1))[:, None] * background

    def rgb_with_weights_gradient(self, background: Tensor, scale: float | Tensor) -> Tensor:
        """(R, 3) the same composite as `rgb`, through which a loss reaches the colours in full and
        the weights (the geometry) scaled by `scale` in [0, 1]: 1 is `rgb`, 0 `rgb_on_fixed_weights`.
        `scale` is one number, or (R,) one per ray (igavatar.training.outline).
        fixed + scale (rgb - fixed): the difference is zero in value and in its colour gradient."""
        if isinstance(scale, Tensor):
            scale = scale.to(self.rgb)[:, None]
        elif scale == 1.0:
            return self.rgb
        elif scale == 0.0:
            return self.rgb_on_fixed_weights(background)
        fixed = self.rgb_on_fixed_weights(background)
        return fixed + scale * (self.rgb - fixed)


def _scatter(values: Tensor, mask: Tensor) -> Tensor:
    """Place (M, ...) values at the True slots of mask (R, S) in a zero (R, S, ...) tensor, differentiably."""
    full = values.new_zeros((*mask.shape, *values.shape[1:]))
    full[mask] = values
    return full


def _join(parts: list[Tensor]) -> Tensor:
    """Chunks along the sample axis joined; one chunk (every training step) is returned as is."""
    return parts[0] if len(parts) == 1 else torch.cat(parts, dim=1)


def render_rays(samples: RaySamples, field_fn: FieldFn, background: Tensor) -> RenderOutput:
    """Volume-render R rays from all their samples at once (training: the graph is kept).

    Args:
        samples: RaySamples (R, S) from :func:`sample_along_rays`.
        field_fn: x (M, 3) -> FieldOutput, called on the valid samples only (not called when
            there are none, in which case every ray shows the background).
        background: (R, 3) or (3,) color behind the subject (random noise in training, white
            at eval).

    Returns:
        RenderOutput.
    """
    background = _checked_background(samples, background)
    chunk = _chunk_fields(samples, field_fn, samples.valid, 0, samples.valid.shape[1], _Optional())
    weights, _ = _chunk_weights(chunk.sigma, samples.deltas, samples.t.new_zeros(samples.valid.shape[0]))
    return _output(samples, background, [chunk], [weights], chunk.optional)


def march_rays(
    samples: RaySamples,
    field_fn: FieldFn,
    background: Tensor,
    *,
    early_stop_transmittance: float = 1e-4,
    march_chunk: int = 32,
) -> RenderOutput:
    """Volume-render R rays front to back, `march_chunk` sample slots at a time (eval), no longer
    evaluating a ray once its transmittance falls below `early_stop_transmittance`.

    Weights of samples with T_i below the threshold are zeroed, which changes the color by at most
    the threshold. Arguments and result as :func:`render_rays`.
    """
    if not 0.0 < early_stop_transmittance < 1.0:
        raise ValueError(f"march_rays: early_stop_transmittance must be in (0, 1), got {early_stop_transmittance}")
    background = _checked_background(samples, background)
    r, s = samples.valid.shape
    width = max(1, int(march_chunk))
    log_threshold = math.log(early_stop_transmittance)
    log_t_run = samples.t.new_zeros(r)  # log transmittance before the current chunk
    optional = _Optional()
    chunks, weight_parts = [], []
    for s0 in range(0, s, width):
        s1 = min(s, s0 + width)
        active = samples.valid[:, s0:s1] & (log_t_run >= log_threshold)[:, None]
        chunk = _chunk_fields(samples, field_fn, active, s0, s1, optional)
        weights, log_t_run = _chunk_weights(chunk.sigma, samples.deltas[:, s0:s1], log_t_run, early_stop_transmittance)
        chunks.append(chunk)
        weight_parts.append(weights)
    return _output(samples, background, chunks, weight_parts, optional)


def _checked_background(samples: RaySamples, background: Tensor) -> Tensor:
    """The background as (R, 3) in the samples' dtype and device; ValueError for another shape."""
    r = samples.valid.shape[0]
    if background.shape not in ((3,), (r, 3)):
        raise ValueError(f"render_rays: background has shape {tuple(background.shape)}, expected (3,) or ({r}, 3)")
    return background.to(samples.t).expand(r, 3)


@dataclass
class _Optional:
    """Whether the field returns a gradient and an SDF (None until its first call); every call must agree."""

    gradient: bool | None = None
    sdf: bool | None = None

    def check(self, out: FieldOutput) -> None:
        if self.gradient is None:
            self.gradient, self.sdf = out.gradient is not None, out.sdf is not None
        if self.gradient != (out.gradient is not None) or self.sdf != (out.sdf is not None):
            raise ValueError("field_fn must return the same optional outputs on every call")


@dataclass(frozen=True)
class _Chunk:
    """The field's outputs on sample slots s0:s1 of every ray, zero where not active."""

    sigma: Tensor  # (R, W)
    rgb: Tensor  # (R, W, 3)
    gradient: Tensor  # (R, W, 3)
    normal: Tensor  # (R, W, 3)
    sdf: Tensor  # (R, W)
    active: Tensor  # (R, W) bool
    optional: _Optional


def _chunk_fields(samples: RaySamples, field_fn: FieldFn, active: Tensor, s0: int, s1: int,
                  optional: _Optional) -> _Chunk:
    """Call the field on the active samples of slots s0:s1 (not at all when none is active)."""
    r, width = active.shape[0], s1 - s0
    zeros3 = samples.t.new_zeros((r, width, 3))
    m = int(active.sum())
    if m == 0:
        return _Chunk(samples.t.new_zeros((r, width)), zeros3, zeros3, zeros3, samples.t.new_zeros((r, width)),
                      active, optional)
    out = FieldOutput.coerce(field_fn(samples.positions[:, s0:s1][active]), m)
    optional.check(out)
    if out.normal is not None:
        normal = _scatter(out.normal, active)
    elif out.gradient is not None:
        normal = _scatter(torch.nn.functional.normalize(out.gradient, dim=-1, eps=1e-12), active)
    else:
        normal = zeros3
    return _Chunk(
        sigma=_scatter(out.sigma, active), rgb=_scatter(out.rgb, active),
        gradient=_scatter(out.gradient, active) if out.gradient is not None else zeros3, normal=normal,
        sdf=_scatter(out.sdf, active) if out.sdf is not None else samples.t.new_zeros((r, width)),
        active=active, optional=optional,
    )


def _chunk_weights(sigma: Tensor, deltas: Tensor, log_t_run: Tensor,
                   early_stop_transmittance: float | None = None) -> tuple[Tensor, Tensor]:
    """Compositing weights (R, W) of a chunk given the log transmittance (R,) before it, and the log
    transmittance after it; weights where T < early_stop_transmittance are zeroed."""
    tau = sigma * deltas  # optical depth of each sample; 0 where not active
    cum = torch.cumsum(tau, dim=1)
    log_t = log_t_run[:, None] - (cum - tau)  # exclusive cumulative sum
    transmittance = torch.exp(log_t)
    alpha = -torch.expm1(-tau)  # 1 - exp(-tau) without cancellation for small tau
    weights = alpha * transmittance
    if early_stop_transmittance is not None:
        weights = torch.where(transmittance >= early_stop_transmittance, weights, 0.0)
    return weights, log_t_run - cum[:, -1]


def _output(samples: RaySamples, background: Tensor, chunks: list[_Chunk], weight_parts: list[Tensor],
            optional: _Optional) -> RenderOutput:
    """Composite the chunks' colors, depths and normals into a RenderOutput."""
    weights = _join(weight_parts)
    rgb_samples = _join([c.rgb for c in chunks])
    normals = _join([c.normal for c in chunks])
    opacity = weights.sum(dim=1)
    rgb = (weights[..., None] * rgb_samples).sum(dim=1) + (1.0 - opacity)[:, None] * background
    return RenderOutput(
        rgb=rgb,
        opacity=opacity,
        depth=(weights * samples.t).sum(dim=1),
        normal=(weights[..., None] * normals).sum(dim=1),
        weights=weights,
        sigma=_join([c.sigma for c in chunks]),
        t=samples.t,
        valid=_join([c.active for c in chunks]),
        # A field never called (no valid sample) counts as having both, all zeros, so that the
        # losses see an empty selection instead of a missing tensor.
        gradient=_join([c.gradient for c in chunks]) if optional.gradient is not False else None,
        sdf=_join([c.sdf for c in chunks]) if optional.sdf is not False else None,
        sample_rgb=rgb_samples,
    )


@dataclass(frozen=True)
class ImageRender:
    """Maps of one rendered image.

    Attributes:
        rgb: (H, W, 3) color on the background.
        opacity: (H, W) accumulated weight.
        depth: (H, W) expected distance along the ray divided by opacity (surface depth; 0 where
            opacity < 1e-6). Distance along the ray, not camera z.
        normal: (H, W, 3) composited normal normalized to unit length (0 where opacity < 1e-6),
            in the frame of the field's normals.
    """

    rgb: Tensor
    opacity: Tensor
    depth: Tensor
    normal: Tensor


def render_image(
    K: Tensor,
    w2c: Tensor,
    height: int,
    width: int,
    field_fn: FieldFn,
    box_min: Tensor,
    box_max: Tensor,
    *,
    occupied_fn: OccupiedFn | None = None,
    num_samples: int = 256,
    background: Tensor | None = None,
    chunk_rays: int = 4096,
    early_stop_transmittance: float | None = 1e-4,
) -> ImageRender:
    """Render a full image in ray chunks (eval): midpoint samples, early termination, no graph kept.

    Rays are cast through every pixel center; near/far come from ``box_min``/``box_max`` (3,) in
    the rays' frame. Autograd stays enabled so a field may compute analytic gradients, but each
    chunk's outputs are detached so memory does not grow with the image.

    Args:
        K: (3, 3); w2c: (4, 4) in the frame of the box and the field.
        height, width: image size in pixels.
        field_fn: as in :func:`render_rays`.
        box_min, box_max: (3,) bounds used for near/far.
        occupied_fn: e.g. ``grid.is_occupied`` after ``grid.rebuild`` for this frame.
        num_samples: bins per ray.
        background: (3,) color, default white.
        chunk_rays: rays per call of the renderer.
        early_stop_transmittance: see :func:`march_rays`; None renders every sample (`render_rays`).

    Returns:
        ImageRender with (H, W, ...) maps.
    """
    device = K.device
    if background is None:
        background = torch.ones(3, device=device)
    pixels = pixel_grid(height, width, device=device)
    origins, directions = pixel_rays(K, w2c, pixels)
    rays = rays_in_box(origins, directions, box_min.to(origins), box_max.to(origins))
    rgb, opacity, depth, normal = [], [], [], []
    for start in range(0, rays.num_rays, chunk_rays):
        sub = rays.slice(start, start + chunk_rays)
        samples = sample_along_rays(sub, num_samples, occupied_fn, stratified=False)
        if early_stop_transmittance is None:
            out = render_rays(samples, field_fn, background.to(origins))
        else:
            out = march_rays(samples, field_fn, background.to(origins), early_stop_transmittance=early_stop_transmittance)
        rgb.append(out.rgb.detach())
        opacity.append(out.opacity.detach())
        depth.append(out.depth.detach())
        normal.append(out.normal.detach())
    opacity_map = torch.cat(opacity)
    seen = opacity_map > 1e-6
    depth_map = torch.where(seen, torch.cat(depth) / opacity_map.clamp_min(1e-6), 0.0)
    normal_map = torch.cat(normal)
    normal_map = torch.where(
        seen[:, None], torch.nn.functional.normalize(normal_map, dim=-1, eps=1e-12), 0.0
    )
    return ImageRender(
        rgb=torch.cat(rgb).reshape(height, width, 3),
        opacity=opacity_map.reshape(height, width),
        depth=depth_map.reshape(height, width),
        normal=normal_map.reshape(height, width, 3),
    )
