"""Canonical fields: sphere initialization, analytic SDF gradient, eikonal training gradient, density.

    .venv/bin/python -m pytest tests/test_fields.py -q
"""

import math

import pytest
import torch

from igavatar.errors import InputError
from igavatar.model.fields import (
    ColorField,
    ColorFieldConfig,
    LaplaceDensity,
    LaplaceDensityConfig,
    SDFField,
    SDFFieldConfig,
    fibonacci_sphere,
)
from igavatar.model.hashgrid import HashGridConfig

SMALL_GRID = HashGridConfig(n_levels=4, log2_hashmap_size=10, base_resolution=4, finest_resolution=40)
BOX_MIN = torch.tensor([-0.8, -1.1, -0.3])
BOX_MAX = torch.tensor([0.6, 1.2, 0.5])
CENTER = 0.5 * (BOX_MIN + BOX_MAX)


def make_field(n_hidden_layers=1, radius=0.4, dtype=torch.float32, seed=0, perturb_table=0.0):
    torch.manual_seed(seed)
    config = SDFFieldConfig(hash_grid=SMALL_GRID, n_hidden_layers=n_hidden_layers, sphere_radius=radius)
    field = SDFField(config, BOX_MIN, BOX_MAX).to(dtype)
    if perturb_table:
        # A trained-looking table, so the hash features matter in gradient checks.
        with torch.no_grad():
            field.encoding.table.uniform_(-perturb_table, perturb_table)
    return field


def box_points(n, dtype=torch.float32, seed=1):
    g = torch.Generator().manual_seed(seed)
    return BOX_MIN.to(dtype) + torch.rand(n, 3, generator=g, dtype=dtype) * (BOX_MAX - BOX_MIN).to(dtype)


@pytest.mark.parametrize("n_hidden_layers", [1, 2])
def test_initial_sdf_is_the_sphere(n_hidden_layers):
    field = make_field(n_hidden_layers=n_hidden_layers, radius=0.4)
    x = box_points(20000)
    with torch.no_grad():
        sdf, feature, grad = field.forward_with_gradient(x)
    analytic = (x - CENTER).norm(dim=-1) - 0.4
    assert feature.shape == (20000, 16) and torch.equal(sdf, feature[:, 0])
    # Softplus rounds the cone apex at the center by ~1.5 cm; the Fibonacci directions leave a ~1 %
    # direction-dependent gain, i.e. mm-level errors near the surface.
    assert (sdf - analytic).abs().max() < 0.025
    near_surface = analytic.abs() < 0.05
    assert near_surface.sum() > 500
    assert ((sdf - analytic)[near_surface]).abs().max() < 0.008
    norms = grad[near_surface].norm(dim=-1)
    assert (norms - 1).abs().max() < 0.03
    # The gradient points away from the center (outward normal of the sphere).
    radial = torch.nn.functional.normalize(x - CENTER, dim=-1)
    assert (torch.nn.functional.cosine_similarity(grad[near_surface], radial[near_surface]) > 0.99).all()


def test_sphere_outside_the_box_and_custom_radius():
    field = make_field(radius=0.25)
    directions = fibonacci_sphere(200).float()
    with torch.no_grad():
        on_surface, _ = field(CENTER + 0.25 * directions)
        far, _ = field(CENTER + 2.0 * directions)  # well outside the box: hash features clamped
    assert on_surface.abs().max() < 0.005
    assert ((far - 1.75).abs() < 0.04).all()  # ~1 % direction-dependent gain far out


def test_forward_with_gradient_matches_forward_and_autograd():
    field = make_field(n_hidden_layers=2, dtype=torch.float64, perturb_table=0.5)
    x = box_points(300, dtype=torch.float64).requires_grad_(True)
    sdf, feature, grad = field.forward_with_gradient(x)
    sdf_plain, feature_plain = field(x)
    assert torch.allclose(sdf, sdf_plain, atol=1e-12) and torch.allclose(feature, feature_plain, atol=1e-12)
    grad_autograd = torch.autograd.grad(sdf_plain.sum(), x)[0]
    assert torch.allclose(grad, grad_autograd, atol=1e-10, rtol=0)
    assert (grad - grad_autograd).abs().max() < 1e-10 * grad.abs().max()

    eps = 1e-7
    with torch.no_grad():
        fd = torch.stack(
            [(field(x + eps * e)[0] - field(x - eps * e)[0]) / (2 * eps) for e in torch.eye(3, dtype=torch.float64)],
            dim=-1,
        )
    # Rare points whose step crosses a hash-grid cell face are excluded by the quantile.
    per_point = (fd - grad).abs().amax(dim=1)
    assert torch.quantile(per_point, 0.95) < 1e-5


def test_eikonal_gradient_matches_double_backward():
    field = make_field(n_hidden_layers=1, dtype=torch.float64, perturb_table=0.3)
    x = box_points(400, dtype=torch.float64)
    target = torch.randn(400, dtype=torch.float64) * 0.1

    def loss_from(sdf, grad):
        eikonal = ((grad.norm(dim=-1) - 1) ** 2).mean()
        normals = torch.nn.functional.normalize(grad, dim=-1)
        smooth = (normals[1:] - normals[:-1]).norm(dim=-1).mean()  # along-"ray" neighbours
        return eikonal + smooth + ((sdf - target) ** 2).mean()

    sdf, _, grad = field.forward_with_gradient(x)
    loss_from(sdf, grad).backward()
    ours = {name: p.grad.clone() for name, p in field.named_parameters()}

    field.zero_grad()
    x_ref = x.clone().requires_grad_(True)
    sdf_ref, _ = field(x_ref)
    grad_ref = torch.autograd.grad(sdf_ref.sum(), x_ref, create_graph=True)[0]
    loss_from(sdf_ref, grad_ref).backward()
    for name, p in field.named_parameters():
        assert torch.allclose(ours[name], p.grad, atol=1e-10, rtol=1e-8), name
    assert ours["encoding.table"].abs().max() > 0


def test_eikonal_reaches_the_table_at_initialization():
    field = make_field()
    _, _, grad = field.forward_with_gradient(box_points(1000))
    ((grad.norm(dim=-1) - 1.2) ** 2).mean().backward()
    assert field.encoding.table.grad.abs().max() > 0
    assert field.layers[0].weight.grad[:, 3:].abs().max() > 0


def test_default_config_shapes():
    field = SDFField(SDFFieldConfig(), BOX_MIN, BOX_MAX)
    assert field.encoding.output_dim == 32
    assert [tuple(layer.weight.shape) for layer in field.layers] == [(64, 35), (16, 64)]
    sdf, feature, grad = field.forward_with_gradient(box_points(64))
    assert sdf.shape == (64,) and feature.shape == (64, 16) and grad.shape == (64, 3)


def test_laplace_density():
    density = LaplaceDensity(LaplaceDensityConfig(beta_init=0.1))
    beta = density.beta.item()
    assert beta == pytest.approx(0.1)
    sdf = torch.linspace(-2.0, 2.0, 4001)
    sigma = density(sdf)
    assert (sigma[1:] <= sigma[:-1]).all()  # float32 saturates at 1/beta deep inside
    sdf64 = torch.linspace(-1.0, 1.0, 4001, dtype=torch.float64)
    sigma64 = density(sdf64)
    assert (sigma64[1:] < sigma64[:-1]).all()  # strictly decreasing in the distance
    assert density(torch.zeros(1)).item() == pytest.approx(0.5 / beta)
    naive = (1 / beta) * (0.5 + 0.5 * torch.sign(-sdf) * (1 - torch.exp(-sdf.abs() / beta)))
    assert torch.allclose(sigma, naive, atol=1e-5, rtol=1e-5)
    # Limits 1/beta inside, 0 outside, finite with finite gradients for huge distances.
    extreme = torch.tensor([-1e30, -1e4, 1e4, 1e30], requires_grad=True)
    out = density(extreme)
    assert torch.isfinite(out).all()
    assert out[0].item() == pytest.approx(1 / beta) and out[-1].item() == 0.0
    out.sum().backward()
    assert torch.isfinite(extreme.grad).all() and torch.isfinite(density.beta_offset.grad).all()
    # Same shape in, same shape out; float64 stays float64.
    assert density(torch.zeros(2, 5, dtype=torch.float64)).shape == (2, 5)
    assert density(torch.zeros(3, dtype=torch.float64)).dtype == torch.float64


def test_laplace_density_beta_floor_keeps_a_gradient():
    density = LaplaceDensity(LaplaceDensityConfig(beta_init=0.1, beta_min=1e-4))
    with torch.no_grad():
        density.beta_offset.fill_(-5e-5)  # an optimizer step overshot past zero
    assert density.beta.item() >= 1e-4
    density(torch.tensor([0.0])).sum().backward()
    assert density.beta_offset.grad.abs().item() > 0
    # d sigma(0) / d beta = -0.5 / beta^2
    density.zero_grad()
    fresh = LaplaceDensity()
    fresh(torch.tensor([0.0])).sum().backward()
    assert fresh.beta_offset.grad.item() == pytest.approx(-0.5 / fresh.beta.item() ** 2, rel=1e-5)


def test_color_field_range_and_shapes():
    torch.manual_seed(0)
    color = ColorField(ColorFieldConfig())
    feature = torch.randn(500, 16) * 100.0
    normal = torch.nn.functional.normalize(torch.randn(500, 3), dim=-1)
    rgb = color(feature, normal)
    assert rgb.shape == (500, 3)
    assert (rgb >= 0).all() and (rgb <= 1).all()
    assert sum(isinstance(m, torch.nn.Linear) for m in color.mlp) == 3
    with pytest.raises(ValueError, match="feature"):
        color(torch.zeros(4, 15), torch.zeros(4, 3))


def test_fields_chain_together():
    """SDF feature + analytic normal -> color, and distance -> density, all differentiable."""
    field = make_field()
    color = ColorField(ColorFieldConfig(feature_dim=16))
    density = LaplaceDensity()
    sdf, feature, grad = field.forward_with_gradient(box_points(100))
    rgb = color(feature, torch.nn.functional.normalize(grad, dim=-1))
    (rgb.sum() + density(sdf).sum()).backward()
    assert field.encoding.table.grad is not None and color.mlp[0].weight.grad is not None
    assert math.isfinite(density.beta_offset.grad.item())


def test_config_errors_name_the_field():
    with pytest.raises(InputError, match="SDFFieldConfig.sphere_radius"):
        SDFFieldConfig(sphere_radius=0.0)
    with pytest.raises(InputError, match="SDFFieldConfig.n_hidden_layers"):
        SDFFieldConfig(n_hidden_layers=0)
    with pytest.raises(InputError, match="LaplaceDensityConfig.beta_init"):
        LaplaceDensityConfig(beta_init=1e-5, beta_min=1e-4)
    with pytest.raises(InputError, match="ColorFieldConfig.hidden_dim"):
        ColorFieldConfig(hidden_dim=0)


def test_hybrid_encoding_gradient_matches_autograd_and_levels_open_coarse_to_fine():
    """The hybrid-pe ablation's field: Fourier features + masked hash levels, analytic gradient exact."""
    from igavatar.model.fields import SDFField, SDFFieldConfig
    from igavatar.model.hashgrid import HashGridConfig

    torch.manual_seed(0)
    config = SDFFieldConfig(
        hash_grid=HashGridConfig(n_levels=4, log2_hashmap_size=10, base_resolution=4, finest_resolution=32),
        hidden_dim=16, feature_dim=4, pe_frequencies=3,
    )
    field = SDFField(config, torch.full((3,), -1.0), torch.ones(3)).double()
    with torch.no_grad():
        field.encoding.table.normal_(0, 0.1)
        field.layers[0].weight.normal_(0, 0.3)
    field.set_level_weights(0.5)
    assert field.level_weights.tolist() == [1.0, 1.0, 1.0, 0.0]
    x = (torch.rand(64, 3, dtype=torch.float64) * 1.6 - 0.8).requires_grad_(True)
    sdf, _, grad = field.forward_with_gradient(x)
    (reference,) = torch.autograd.grad(field(x)[0].sum(), x)
    torch.testing.assert_close(grad, reference, rtol=1e-9, atol=1e-9)
    # Sphere initialization is not disturbed by the (zero-initialized) positional-encoding columns.
    import dataclasses

    points = torch.nn.functional.normalize(torch.randn(256, 3), dim=-1) * 0.5
    torch.manual_seed(1)
    hybrid = SDFField(config, torch.full((3,), -1.0), torch.ones(3))
    torch.manual_seed(1)
    plain = SDFField(dataclasses.replace(config, pe_frequencies=0), torch.full((3,), -1.0), torch.ones(3))
    # Only the +-1e-4 hash features differ (other random draws); zero PE columns change nothing.
    torch.testing.assert_close(hybrid(points)[0], plain(points)[0], rtol=0, atol=1e-3)


def test_beta_ceiling_caps_beta_and_old_state_dicts_load_uncapped():
    density = LaplaceDensity(LaplaceDensityConfig(beta_init=0.05))
    assert density.beta.item() == pytest.approx(0.05)
    density.set_ceiling(0.01)
    assert density.beta.item() == pytest.approx(0.01)
    # Capped: sigma(0) = 0.5 / ceiling, and the learned offset gets no gradient from above the cap.
    assert density(torch.zeros(1)).item() == pytest.approx(50.0)
    density(torch.zeros(1)).sum().backward()
    assert density.beta_offset.grad.item() == 0.0
    state = {k: v for k, v in density.state_dict().items() if k != "beta_ceiling"}  # written before the cap
    fresh = LaplaceDensity(LaplaceDensityConfig(beta_init=0.05))
    fresh.set_ceiling(0.02)
    fresh.load_state_dict(state)
    assert math.isinf(fresh.beta_ceiling.item()) and fresh.beta.item() == pytest.approx(0.05)
    capped = LaplaceDensity(LaplaceDensityConfig(beta_init=0.05))
    capped.load_state_dict(density.state_dict())
    assert capped.beta.item() == pytest.approx(0.01)


def test_mlp_only_sdf_has_no_grid_and_an_exact_gradient():
    torch.manual_seed(0)
    config = SDFFieldConfig(hash_grid=SMALL_GRID, use_hash_grid=False, pe_frequencies=4, hidden_dim=64, n_hidden_layers=3,
                            sphere_radius=0.4)
    field = SDFField(config, BOX_MIN, BOX_MAX).double()
    assert field.encoding is None and not any("encoding" in name for name, _ in field.named_parameters())
    x = box_points(64, torch.float64)
    sdf, _, grad = field.forward_with_gradient(x)
    # Geometric initialization still gives the sphere.
    assert torch.allclose(sdf, (x - CENTER.double()).norm(dim=1) - 0.4, atol=0.025)
    with torch.no_grad():  # perturb so the positional-encoding columns matter
        field.layers[0].weight.normal_(0.0, 0.3)
    sdf, _, grad = field.forward_with_gradient(x)
    x_ad = x.clone().requires_grad_(True)
    (autograd,) = torch.autograd.grad(field(x_ad)[0].sum(), x_ad)
    assert torch.allclose(grad, autograd, atol=1e-10)


@pytest.mark.parametrize("normal_gradient", [True, False])
def test_a_detached_colour_normal_keeps_the_colour_loss_off_the_surface_normals(normal_gradient):
    """With ColorFieldConfig.normal_gradient False, the colour of a point does not depend on the
    SDF's gradient through the normal input: the colour loss cannot tilt the surface to draw a
    stripe (issue 36). The SDF features still carry colour, as they must."""
    import dataclasses

    from igavatar.model.avatar import Avatar
    from igavatar.training.config import preset

    config = preset("tiny").avatar
    config = dataclasses.replace(config, color=dataclasses.replace(config.color, normal_gradient=normal_gradient))
    box = torch.tensor([[-0.5] * 3, [0.5] * 3])
    avatar = Avatar(config, box, torch.ones(1, 4, 4, 4), box[0] - 0.2, box[1] + 0.2, pose_dim=3, init_bones=(0,))
    seen = {}
    real_forward = avatar.color_field.forward

    def forward(feature, normal, x_canonical=None):
        seen["normal_requires_grad"] = normal.requires_grad
        return real_forward(feature, normal)

    avatar.color_field.forward = forward
    x = torch.rand(64, 3) - 0.5
    out = avatar.field_at(x, torch.zeros(3))
    assert seen["normal_requires_grad"] == normal_gradient
    out.rgb.sum().backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in avatar.sdf_field.parameters())  # features
