"""Canonical fields: hash-grid SDF (with analytic gradient), color field and Laplace density.

    sdf_field = SDFField(SDFFieldConfig(), box_min=torch.full((3,), -1.0), box_max=torch.ones(3))
    sdf, feature, grad_sdf = sdf_field.forward_with_gradient(x_canonical)  # (P,), (P, 16), (P, 3)

``SDFField`` maps a canonical point to a signed distance (meters, positive outside) and a 16-d
feature whose channel 0 is that distance (as in the official InstantGeoAvatar code). Its input is the
hash-grid encoding plus the point itself, centerd on the box and divided by the box's largest
half-extent. ``forward_with_gradient`` returns ``d sdf / d x_canonical`` in closed form: the hash
grid's spatial Jacobian chained with the MLP's Jacobian (a reverse sweep over the small MLP), so the
eikonal and smoothness losses train the field with one ordinary backward pass.
``ColorField`` maps (feature, canonical normal) to RGB; ``LaplaceDensity`` maps distance to VolSDF
density ``sigma = (1 / beta) * Psi_beta(-d)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import nn
from torch.nn import functional as F

from igavatar.errors import InputError
from igavatar.model.hashgrid import HashGridConfig, HashGridEncoding
from igavatar.model.linear import linear, pad_rows
from igavatar.model.sdf_head import sdf_head_applies, sdf_head_forward, sdf_head_with_gradient


_SOFTPLUS_THRESHOLD = 20.0  # F.softplus's default: identity where beta * z > 20


def _require(config_name: str, field_name: str, value: object, ok: bool, why: str) -> None:
    if not ok:
        raise InputError(f"{config_name}.{field_name}: {value!r} {why}")


def fibonacci_sphere(n: int) -> torch.Tensor:
    """``n`` nearly uniformly spread unit vectors (golden-angle spiral), float64 ``(n, 3)``."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = torch.sqrt(1.0 - z * z)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return torch.stack((r * torch.cos(phi), r * torch.sin(phi), z), dim=-1)


@dataclass(frozen=True)
class SDFFieldConfig:
    """Architecture and initial shape of the canonical SDF field."""

    hash_grid: HashGridConfig = field(default_factory=HashGridConfig)
    """Multiresolution hash encoding of the canonical point."""

    use_hash_grid: bool = True
    """False: a plain MLP on the (positionally encoded) point, no hash grid -- the slow-but-smooth
    baseline of the quality benchmark (a stand-in for Vid2Avatar-style MLP SDFs)."""

    hidden_dim: int = 64
    """Width of the MLP's hidden layers."""

    n_hidden_layers: int = 1
    """Number of hidden layers (official: 1)."""

    feature_dim: int = 16
    """Output channels; channel 0 is the signed distance, all 16 are the feature passed on."""

    softplus_beta: float = 100.0
    """Sharpness of the Softplus activation (a smooth ReLU, so the SDF has smooth gradients)."""

    sphere_radius: float = 0.5
    """Radius in meters of the sphere, centerd on the box, that the SDF represents at initialization."""

    pe_frequencies: int = 0
    """Fourier frequencies of a positional encoding added to the MLP input (the hybrid encoding
    of the paper's `hybrid-pe` ablation, after Shinobi); 0 = off (InstantGeoAvatar)."""

    def __post_init__(self) -> None:
        name = "SDFFieldConfig"
        _require(name, "hidden_dim", self.hidden_dim, self.hidden_dim >= 4, "must be >= 4")
        _require(name, "n_hidden_layers", self.n_hidden_layers, self.n_hidden_layers >= 1, "must be >= 1")
        _require(name, "feature_dim", self.feature_dim, self.feature_dim >= 1, "must be >= 1")
        _require(name, "softplus_beta", self.softplus_beta, self.softplus_beta > 0, "must be > 0")
        _require(name, "sphere_radius", self.sphere_radius, self.sphere_radius > 0, "must be > 0")
        _require(name, "pe_frequencies", self.pe_frequencies, self.pe_frequencies >= 0, "must be >= 0")


class SDFField(nn.Module):
    """Canonical SDF: ``x_canonical (P, 3) -> (sdf (P,), feature (P, feature_dim))``.

    Submodules: ``encoding`` (HashGridEncoding over the box), ``layers`` (nn.ModuleList of Linear:
    input ``3 + L*F`` -> hidden ... -> ``feature_dim``). Buffers: ``center (3,)`` (box center) and
    ``input_scale`` (largest half-extent of the box, meters).
    """

    def __init__(self, config: SDFFieldConfig, box_min: torch.Tensor, box_max: torch.Tensor) -> None:
        super().__init__()
        self.config = config
        self.encoding = HashGridEncoding(config.hash_grid, box_min, box_max) if config.use_hash_grid else None
        box_min = torch.as_tensor(box_min, dtype=torch.float32)
        box_max = torch.as_tensor(box_max, dtype=torch.float32)
        center = 0.5 * (box_min + box_max)
        half_extent = 0.5 * (box_max - box_min)
        self.register_buffer("centre", center)
        self.register_buffer("input_scale", half_extent.max().reshape(()))
        # Per-level multipliers of the hash features: all ones except while the hybrid encoding
        # opens its levels coarse-to-fine (set_level_weights).
        self.register_buffer("level_weights", torch.ones(config.hash_grid.n_levels))
        self.register_buffer(
            "pe_omegas", math.pi * 2.0 ** torch.arange(config.pe_frequencies, dtype=torch.float32)
        )
        encoded_dim = self.encoding.output_dim if self.encoding is not None else 0
        dims = [3 + 6 * config.pe_frequencies + encoded_dim] + [config.hidden_dim] * config.n_hidden_layers + [config.feature_dim]
        self.layers = nn.ModuleList(nn.Linear(d_in, d_out) for d_in, d_out in zip(dims[:-1], dims[1:]))
        self.reset_to_sphere()

    @torch.no_grad()
    def reset_to_sphere(self) -> None:
        """Geometric initialization: ``sdf(x) ~= |x - center| - sphere_radius`` over the whole space.

        A variant of SAL's geometric init (Atzmon & Lipman 2020) made exact rather than exact in
        expectation: with zero biases every first-layer unit is ``relu(a * d_i . x_in)`` and, for
        directions d_i spread uniformly over the sphere, ``sum_i relu(d_i . u)`` is nearly the
        same for every unit vector u. With 64 units, Fibonacci-sphere directions make it so to 0.4 %
        (std over u; SAL's random Gaussian rows leave 15-20 %); the output weight then
        normalizes the sum to ``|x_in| * input_scale = |x - center|`` and the bias is ``-radius``
        (the official release forgets this bias). Deeper hidden layers start as the identity,
        which passes ``relu`` activations through unchanged. The hash-feature columns get small
        Gaussian weights: the table starts at +-1e-4, so they perturb the sphere by ~1e-4 m,
        yet the table receives gradients from the first step (zero columns would block them).
        """
        cfg = self.config
        hidden = cfg.hidden_dim
        # Unit rows: a Softplus(beta) unit is then sharp within input_scale / beta (~1 cm for a 1 m
        # box) of its plane; SAL's smaller N(0, 2/hidden) rows would round the sphere far more.
        row_norm = 1.0
        directions = fibonacci_sphere(hidden)
        first = self.layers[0]
        first.weight.zero_()
        first.bias.zero_()
        first.weight[:, :3] = (row_norm * directions).to(first.weight.dtype)
        # Positional-encoding columns (hybrid-pe only) start at zero: their inputs are O(1) and
        # would bend the sphere; they still receive gradients.
        n_pe = 6 * cfg.pe_frequencies
        nn.init.normal_(first.weight[:, 3 + n_pe:], mean=0.0, std=math.sqrt(2.0 / hidden))
        for layer in self.layers[1:-1]:
            layer.weight.copy_(torch.eye(hidden, dtype=layer.weight.dtype))
            layer.bias.zero_()
        # Mean over many unit vectors of sum_i relu(row_norm * d_i . u): the gain of the hidden sum.
        probe = fibonacci_sphere(4096)
        gain = torch.relu(row_norm * probe @ directions.T).sum(dim=1).mean().item()
        last = self.layers[-1]
        nn.init.kaiming_uniform_(last.weight, a=math.sqrt(5))  # nn.Linear's default for features
        last.bias.zero_()
        last.weight[0] = float(self.input_scale) / gain
        # Bias: -radius corrected by the Softplus offsets (ln 2 / beta per unit near its plane), so
        # that the sphere is exactly the zero level on average.
        last.bias[0] = 0.0
        on_sphere = self.centre.double() + cfg.sphere_radius * fibonacci_sphere(1024)
        last.bias[0] = -self.forward(on_sphere.to(last.weight.dtype))[0].mean()

    def set_level_weights(self, progress: float) -> None:
        """Open the hash levels coarse-to-fine: level l gets clamp(progress * L - l, 0, 1), level 0 always 1.

        progress >= 1 restores plain hash features (the default state).
        """
        levels = torch.arange(self.config.hash_grid.n_levels, dtype=self.level_weights.dtype, device=self.level_weights.device)
        weights = (progress * self.config.hash_grid.n_levels - levels + 1.0).clamp(0.0, 1.0)
        self.level_weights.copy_(weights)

    def _feature_scale(self, dtype: torch.dtype) -> torch.Tensor:
        """(C,) multipliers of the encoded features (each level's weight, repeated per feature)."""
        if self.encoding is None:
            return self.level_weights.new_zeros(0, dtype=dtype)
        return self.level_weights.to(dtype).repeat_interleave(self.config.hash_grid.n_features_per_level)

    def _encode(self, x_canonical: torch.Tensor) -> torch.Tensor:
        if self.encoding is None:
            return x_canonical.new_zeros((x_canonical.shape[0], 0))
        return self.encoding(x_canonical)

    def _encode_with_jacobian(self, x_canonical: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if self.encoding is None:
            return x_canonical.new_zeros((x_canonical.shape[0], 0)), x_canonical.new_zeros((x_canonical.shape[0], 0, 3))
        return self.encoding.forward_with_jacobian(x_canonical)

    def _mlp_input(self, x_canonical: torch.Tensor, encoded: torch.Tensor) -> torch.Tensor:
        x_centerd = (x_canonical.to(encoded.dtype) - self.centre.to(encoded.dtype)) / self.input_scale.to(encoded.dtype)
        parts = [x_centerd]
        if self.config.pe_frequencies:
            angles = x_centerd[:, None, :] * self.pe_omegas.to(encoded.dtype)[None, :, None]  # (P, K, 3)
            parts.append(torch.stack((angles.sin(), angles.cos()), dim=2).flatten(1))  # (P, K*2*3)
        parts.append(encoded * self._feature_scale(encoded.dtype))
        return torch.cat(parts, dim=-1)

    def forward(self, x_canonical: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``x_canonical (P, 3)`` -> ``(sdf (P,), feature (P, feature_dim))``, ``sdf = feature[:, 0]``."""
        h = self._mlp_input(x_canonical, self._encode(x_canonical))
        beta = self.config.softplus_beta
        if not torch.is_grad_enabled() and self.config.pe_frequencies == 0 and sdf_head_applies(h, self.layers):
            # Fast path for queries without gradients (root-finding scores, occupancy, meshing).
            feature = sdf_head_forward(h, self.layers[0], self.layers[-1], beta, _SOFTPLUS_THRESHOLD)
            return feature[:, 0], feature
        for layer in self.layers[:-1]:
            h = F.softplus(layer(h), beta=beta, threshold=_SOFTPLUS_THRESHOLD)
        feature = self.layers[-1](h)
        return feature[:, 0], feature

    def forward_with_gradient(self, x_canonical: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``x_canonical (P, 3)`` -> ``(sdf (P,), feature (P, feature_dim), grad_sdf (P, 3))``.

        ``grad_sdf = d sdf / d x_canonical`` in closed form; all three outputs are differentiable wrt
        the parameters (a loss on ``grad_sdf`` trains the table and the MLP with one backward pass).
        """
        encoded, jacobian = self._encode_with_jacobian(x_canonical)  # (P, C), (P, C, 3); C = 0 without a grid
        h = self._mlp_input(x_canonical, encoded)
        beta = self.config.softplus_beta
        if self.config.pe_frequencies == 0 and sdf_head_applies(h, self.layers):
            # Fast path (one hidden layer): the same function fused into one autograd node.
            scale = self.input_scale.to(h.dtype)
            grad_scale = torch.cat((scale.reciprocal().expand(3), self._feature_scale(h.dtype)))
            feature, grad_sdf = sdf_head_with_gradient(
                h, jacobian, grad_scale, self.layers[0], self.layers[-1], beta, _SOFTPLUS_THRESHOLD
            )
            return feature[:, 0], feature, grad_sdf
        slopes = []
        for layer in self.layers[:-1]:
            z = layer(h)
            # d softplus_beta(z) / dz, with F.softplus's switch to the identity above beta*z > 20
            # so that grad_sdf is exactly the derivative of the sdf that forward() returns.
            slopes.append(torch.where(beta * z > _SOFTPLUS_THRESHOLD, 1.0, torch.sigmoid(beta * z)))
            h = F.softplus(z, beta=beta, threshold=_SOFTPLUS_THRESHOLD)
        feature = self.layers[-1](h)

        # Reverse sweep of the scalar sdf = feature[:, 0] through the MLP: (P, width) vectors only.
        grad_h = self.layers[-1].weight[0]  # (hidden,), broadcasts over points
        for layer, slope in zip(reversed(self.layers[:-1]), reversed(slopes)):
            grad_h = (grad_h * slope) @ layer.weight
        grad_input = grad_h  # (P, 3 + 6K + C): d sdf / d (x_centerd, pe, encoded)
        scale = self.input_scale.to(grad_input.dtype)
        n_pe = 6 * self.config.pe_frequencies
        grad_x_centerd = grad_input[:, :3]
        if n_pe:
            x_centerd = (x_canonical.to(grad_input.dtype) - self.centre.to(grad_input.dtype)) / scale
            omegas = self.pe_omegas.to(grad_input.dtype)[None, :, None]
            angles = x_centerd[:, None, :] * omegas  # (P, K, 3)
            grad_pe = grad_input[:, 3:3 + n_pe].reshape(-1, self.config.pe_frequencies, 2, 3)
            # d sin(w x)/dx = w cos(w x); d cos(w x)/dx = -w sin(w x), per axis.
            grad_x_centerd = grad_x_centerd + (
                grad_pe[:, :, 0] * omegas * angles.cos() - grad_pe[:, :, 1] * omegas * angles.sin()
            ).sum(dim=1)
        grad_encoded = grad_input[:, 3 + n_pe:] * self._feature_scale(grad_input.dtype)
        grad_sdf = grad_x_centerd / scale + torch.einsum("pc,pcd->pd", grad_encoded, jacobian)
        return feature[:, 0], feature, grad_sdf


@dataclass(frozen=True)
class ColorFieldConfig:
    """Architecture of the canonical color field (no view direction, as in the official code)."""

    feature_dim: int = 16
    """Channels of the SDF feature it is conditioned on (SDFFieldConfig.feature_dim)."""

    hidden_dim: int = 64
    """Width of the hidden layers."""

    n_hidden_layers: int = 2
    """Number of ReLU hidden layers."""

    normal_gradient: bool = True
    """Whether the colour loss reaches the geometry through the normal input (the official code).
    False detaches the normal: a dark stripe can then no longer be explained by tilting the
    surface (texture copied into the geometry, issue 36)."""

    feature_gradient: bool = True
    """Whether the colour loss reaches the geometry through the SDF's features (the official code).
    False detaches them: the colour network reads the geometry's features but cannot reshape the
    field to suit its colours, the main channel by which bold stripes were carved (issue 36)."""

    hash_grid: HashGridConfig | None = None
    """A hash grid of the colour's own on the canonical point, whose features are added to the
    input, or None (the official code: the SDF's features only)."""

    def __post_init__(self) -> None:
        name = "ColorFieldConfig"
        _require(name, "feature_dim", self.feature_dim, self.feature_dim >= 1, "must be >= 1")
        _require(name, "hidden_dim", self.hidden_dim, self.hidden_dim >= 1, "must be >= 1")
        _require(name, "n_hidden_layers", self.n_hidden_layers, self.n_hidden_layers >= 1, "must be >= 1")


class ColorField(nn.Module):
    """Canonical color: ``(feature (P, feature_dim), normal_canonical (P, 3)[, x_canonical (P, 3)])
    -> rgb (P, 3)`` in [0, 1]; x_canonical is read by the colour's own hash grid when it has one."""

    def __init__(self, config: ColorFieldConfig, box_min: torch.Tensor | None = None,
                 box_max: torch.Tensor | None = None) -> None:
        super().__init__()
        self.config = config
        grid_dim = 0
        if config.hash_grid is not None:
            if box_min is None or box_max is None:
                raise ValueError("ColorField: a colour hash grid needs the canonical box")
            self.encoding = HashGridEncoding(config.hash_grid, box_min, box_max)
            grid_dim = self.encoding.output_dim
        dims = [config.feature_dim + 3 + grid_dim] + [config.hidden_dim] * config.n_hidden_layers
        layers: list[nn.Module] = []
        for d_in, d_out in zip(dims[:-1], dims[1:]):
            layers += [nn.Linear(d_in, d_out), nn.ReLU()]
        layers.append(nn.Linear(dims[-1], 3))
        self.mlp = nn.Sequential(*layers)

    def forward(self, feature: torch.Tensor, normal_canonical: torch.Tensor,
                x_canonical: torch.Tensor | None = None) -> torch.Tensor:
        """``feature (P, feature_dim)``, ``normal_canonical (P, 3)`` (unit), ``x_canonical (P, 3)``
        (needed with a colour hash grid) -> ``rgb (P, 3)`` in [0, 1]."""
        if feature.shape[:-1] != normal_canonical.shape[:-1] or feature.shape[-1] != self.config.feature_dim \
                or normal_canonical.shape[-1] != 3:
            raise ValueError(
                f"ColorField: expected feature (P, {self.config.feature_dim}) and normal_canonical (P, 3), "
                f"got {tuple(feature.shape)} and {tuple(normal_canonical.shape)}"
            )
        inputs = [feature if self.config.feature_gradient else feature.detach(), normal_canonical]
        if self.config.hash_grid is not None:
            if x_canonical is None or x_canonical.shape != normal_canonical.shape:
                raise ValueError("ColorField: a colour hash grid needs x_canonical (P, 3)")
            inputs.append(self.encoding(x_canonical))
        # The same network as self.mlp (Linear, ReLU, ..., Linear), on rows padded to a cached
        # matrix shape when the fast path applies (see linear.pad_rows), sliced at the output.
        h = pad_rows(torch.cat(inputs, dim=-1))
        for layer in self.mlp[:-1:2]:
            h = linear(h, layer.weight, layer.bias, relu=True)
        return torch.sigmoid(linear(h, self.mlp[-1].weight, self.mlp[-1].bias)[: feature.shape[0]])


#: Radius (meters) of the limb the silhouette offset is computed for: between an arm (4 cm) and
#: a torso (15 cm); the offset grows only with the logarithm of it.
SILHOUETTE_RADIUS_M = 0.1


def silhouette_offset(beta: float, radius: float = SILHOUETTE_RADIUS_M) -> float:
    """Meters outside the SDF's zero level at which the rendered silhouette of a limb lies.

    The Laplace density's tail reaches outside the zero level: a ray passing a cylinder of radius
    r at distance d (d << r) crosses an optical depth of `0.5 sqrt(2 pi r / beta) exp(-d / beta)`,
    which is ln 2 (opacity 1/2) at `d = beta ln(sqrt(2 pi r / beta) / (2 ln 2))`: 2.4 beta for an
    arm (r = 4 cm at beta = 1 mm), 2.9 beta at r = 10 cm, 3.1 beta for a torso (r = 15 cm); 0 when
    beta is not small against r (there is no such tail then). Fitting that silhouette to the masks
    leaves the zero level this far inside the subject (docs/DESIGN.md, Geometry); meshes are made at
    this level set (igavatar.model.avatar.SURFACE_LEVELS).
    """
    beta = float(beta)
    if not beta > 0:
        return 0.0
    return beta * max(0.0, math.log(math.sqrt(2.0 * math.pi * radius / beta) / (2.0 * math.log(2.0))))


@dataclass(frozen=True)
class LaplaceDensityConfig:
    """VolSDF density from signed distance: the CDF of a zero-mean Laplace distribution of scale beta."""

    beta_init: float = 0.1
    """Initial beta in meters (official: 0.075 after the body-shape initialization)."""

    beta_min: float = 1e-4
    """Lower bound of beta, so the density stays finite."""

    def __post_init__(self) -> None:
        name = "LaplaceDensityConfig"
        _require(name, "beta_min", self.beta_min, self.beta_min > 0, "must be > 0")
        _require(name, "beta_init", self.beta_init, self.beta_init >= self.beta_min,
                 f"must be >= beta_min ({self.beta_min})")


class LaplaceDensity(nn.Module):
    """``sdf (...) -> sigma (...)``, ``sigma = (1/beta) (0.5 + 0.5 sign(-d) (1 - exp(-|d|/beta)))``.

    Parameter ``beta_offset`` (scalar): ``beta = min(beta_min + |beta_offset|, beta_ceiling)``. The
    absolute value (as in VolSDF) keeps beta >= beta_min with a non-zero gradient; a hard clamp would
    freeze beta for good once an optimizer step pushed it below the bound. Buffer ``beta_ceiling``
    (scalar, +inf unless training anneals it, see TrainConfig.beta_final) caps the learned beta.
    """

    def __init__(self, config: LaplaceDensityConfig = LaplaceDensityConfig()) -> None:
        super().__init__()
        self.config = config
        self.beta_offset = nn.Parameter(torch.tensor(config.beta_init - config.beta_min))
        self.register_buffer("beta_ceiling", torch.tensor(float("inf")))

    @property
    def beta(self) -> torch.Tensor:
        """Current Laplace scale (scalar tensor, differentiable below the ceiling)."""
        return torch.minimum(self.config.beta_min + self.beta_offset.abs(), self.beta_ceiling)

    def set_ceiling(self, ceiling: float) -> None:
        """Cap beta at `ceiling` meters (inf: no cap)."""
        self.beta_ceiling.fill_(ceiling)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:
        # Models written before the cap existed have no ceiling: they load uncapped.
        state_dict.setdefault(prefix + "beta_ceiling", torch.tensor(float("inf")))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def forward(self, sdf: torch.Tensor) -> torch.Tensor:
        """Density of the same shape as ``sdf``; ``0.5 / beta`` at the surface, monotone decreasing."""
        beta = self.beta.to(sdf.dtype)
        # One exp of a non-positive argument: never overflows, and both branches stay finite so
        # torch.where's gradient has no NaN. Outside: 0.5 e^{-d/b}; inside: 1 - 0.5 e^{d/b}.
        decay = torch.exp(-sdf.abs() / beta)
        return torch.where(sdf > 0, 0.5 * decay, 1.0 - 0.5 * decay) / beta
