"""Rays and the volume renderer against closed forms: pinhole projection, slab test, a sphere."""

from __future__ import annotations

import math

import pytest
import torch

from igavatar.render.rays import RayBundle, pixel_grid, pixel_rays, ray_box_intersection, rays_in_box
from igavatar.render.sampler import compact_samples, sample_along_rays
from igavatar.render.volume import FieldOutput, march_rays, render_image, render_rays

RADIUS = 0.5
BETA = 0.002
COLOR = torch.tensor([0.2, 0.4, 0.6])


def random_rotation(gen: torch.Generator) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    if torch.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def laplace_density(sdf: torch.Tensor, beta: float) -> torch.Tensor:
    """VolSDF density (1/beta) * Psi_beta(-sdf), the form the model uses."""
    return (0.5 + 0.5 * torch.sign(-sdf) * (1.0 - torch.exp(-sdf.abs() / beta))) / beta


def sphere_field(x: torch.Tensor) -> FieldOutput:
    """Analytic sphere of RADIUS at the origin: SDF |x| - r, gradient x / |x|, constant color."""
    norm = torch.linalg.vector_norm(x, dim=-1)
    sdf = norm - RADIUS
    gradient = x / norm.clamp_min(1e-9)[:, None]
    return FieldOutput(
        sigma=laplace_density(sdf, BETA),
        rgb=COLOR.to(x).expand(x.shape[0], 3),
        gradient=gradient,
        sdf=sdf,
    )


def sphere_hit(origins: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """First ray-sphere intersection distance (nan on a miss) and impact parameter of each ray."""
    b = -(origins * directions).sum(-1)
    closest = origins + b[:, None] * directions
    impact = torch.linalg.vector_norm(closest, dim=-1)
    t_hit = b - torch.sqrt(RADIUS**2 - impact**2)
    return t_hit, impact


def look_at_camera(height: int, width: int, focal: float, distance: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera on the -z axis looking at the origin (camera axes = world axes)."""
    K = torch.tensor([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]])
    w2c = torch.eye(4)
    w2c[2, 3] = distance  # x_camera = x_world + (0, 0, distance)
    return K, w2c


# ---------------------------------------------------------------------------------------- rays
def test_pixel_rays_reproject_to_their_pixels() -> None:
    gen = torch.Generator().manual_seed(0)
    K = torch.tensor([[500.0, 0.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = random_rotation(gen)
    w2c[:3, 3] = torch.randn(3, generator=gen, dtype=torch.float64)
    pixels = torch.rand(50, 2, generator=gen, dtype=torch.float64) * torch.tensor([640.0, 480.0])
    origins, directions = pixel_rays(K, w2c, pixels)
    assert torch.allclose(torch.linalg.vector_norm(directions, dim=-1), torch.ones(50, dtype=torch.float64))
    # All origins are the camera center, which w2c maps to the camera origin.
    center_camera = w2c[:3, :3] @ origins[0] + w2c[:3, 3]
    assert torch.allclose(center_camera, torch.zeros(3, dtype=torch.float64), atol=1e-10)
    for t in (0.5, 3.0):
        x_world = origins + t * directions
        x_camera = x_world @ w2c[:3, :3].T + w2c[:3, 3]
        assert (x_camera[:, 2] > 0).all()  # in front of the camera (OpenCV z forward)
        projected = x_camera @ K.T
        assert torch.allclose(projected[:, :2] / projected[:, 2:], pixels, atol=1e-8)


def test_principal_point_ray_is_optical_axis_and_pixel_grid_is_row_major() -> None:
    K, w2c = look_at_camera(4, 6, focal=10.0, distance=2.0)
    pixels = pixel_grid(4, 6)
    assert pixels.shape == (24, 2)
    assert pixels[7].tolist() == [1.0, 1.0]  # index y * W + x
    _, directions = pixel_rays(K, w2c, torch.tensor([[2.5, 1.5]]))
    assert torch.allclose(directions[0], torch.tensor([0.0, 0.0, 1.0]))


def test_ray_box_intersection_matches_dense_marching() -> None:
    gen = torch.Generator().manual_seed(1)
    box_min, box_max = torch.tensor([-0.5, -1.0, -0.3]), torch.tensor([0.7, 0.4, 0.9])
    origins = torch.randn(200, 3, generator=gen) * 1.5
    directions = torch.nn.functional.normalize(torch.randn(200, 3, generator=gen), dim=-1)
    t_near, t_far, hit = ray_box_intersection(origins, directions, box_min, box_max)
    ts = torch.linspace(0.0, 8.0, 16001)
    points = origins[:, None] + ts[None, :, None] * directions[:, None]
    inside = ((points >= box_min) & (points <= box_max)).all(-1)
    step = float(ts[1] - ts[0])
    assert torch.equal(hit, inside.any(1))
    for i in torch.nonzero(hit).flatten():
        t_in = ts[inside[i]]
        assert abs(float(t_in.min()) - float(t_near[i])) <= step * 1.01
        assert abs(float(t_in.max()) - float(t_far[i])) <= step * 1.01
    assert (t_near[~hit] == 0).all() and (t_far[~hit] == 0).all()


def test_ray_box_intersection_inside_and_axis_parallel() -> None:
    box_min, box_max = -torch.ones(3), torch.ones(3)
    origins = torch.tensor([[0.0, 0.0, 0.0], [-3.0, 1.0, 0.0], [-3.0, 1.5, 0.0]])
    directions = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    t_near, t_far, hit = ray_box_intersection(origins, directions, box_min, box_max)
    assert torch.isfinite(t_near).all() and torch.isfinite(t_far).all()
    assert hit.tolist() == [True, True, False]
    assert t_near[0] == 0.0 and t_far[0] == pytest.approx(1.0)
    assert t_near[1] == pytest.approx(2.0) and t_far[1] == pytest.approx(4.0)  # ray grazing a face


def test_ray_bundle_checks_shapes() -> None:
    with pytest.raises(ValueError, match="near"):
        RayBundle(torch.zeros(4, 3), torch.zeros(4, 3), torch.zeros(3), torch.zeros(4))


# ------------------------------------------------------------------------------- compositing
def uniform_medium_rays(r: int, gen: torch.Generator) -> RayBundle:
    origins = torch.randn(r, 3, generator=gen)
    directions = torch.nn.functional.normalize(torch.randn(r, 3, generator=gen), dim=-1)
    near = torch.rand(r, generator=gen)
    far = near + 0.2 + torch.rand(r, generator=gen)
    return RayBundle(origins, directions, near, far)


def test_uniform_medium_opacity_color_and_gradient_closed_form() -> None:
    """Constant density c on [near, far]: opacity = 1 - exp(-c L) whatever the sampling."""
    gen = torch.Generator().manual_seed(2)
    rays = uniform_medium_rays(16, gen)
    log_c = torch.tensor(math.log(1.7), requires_grad=True)
    color = torch.tensor([0.9, 0.1, 0.3])

    def field(x: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"sigma": log_c.exp().expand(x.shape[0]), "rgb": color.expand(x.shape[0], 3)}

    samples = sample_along_rays(rays, 37, generator=gen)
    background = torch.rand(16, 3, generator=gen)
    out = render_rays(samples, field, background)
    length = rays.far - rays.near
    expected_opacity = 1.0 - torch.exp(-1.7 * length)
    assert torch.allclose(out.opacity, expected_opacity, atol=1e-5)
    expected_rgb = color * expected_opacity[:, None] + background * (1 - expected_opacity)[:, None]
    assert torch.allclose(out.rgb, expected_rgb, atol=1e-5)
    # d opacity / d log c = c L exp(-c L)
    out.opacity.sum().backward()
    expected_grad = (1.7 * length * torch.exp(-1.7 * length)).sum()
    assert log_c.grad is not None and float(log_c.grad) == pytest.approx(float(expected_grad), rel=1e-4)
    assert out.gradient is None and out.sdf is None


def test_colour_on_fixed_weights_is_the_same_picture_with_no_gradient_to_the_density() -> None:
    gen = torch.Generator().manual_seed(3)
    rays = uniform_medium_rays(8, gen)
    log_c = torch.tensor(math.log(1.3), requires_grad=True)
    color = torch.tensor([0.2, 0.7, 0.4], requires_grad=True)

    def field(x: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"sigma": log_c.exp().expand(x.shape[0]), "rgb": color.expand(x.shape[0], 3)}

    background = torch.rand(8, 3, generator=gen)
    out = render_rays(sample_along_rays(rays, 21, generator=gen), field, background)
    fixed = out.rgb_on_fixed_weights(background)
    assert torch.allclose(fixed, out.rgb, atol=1e-6)
    (grad_c_fixed, grad_color_fixed) = torch.autograd.grad(fixed.sum(), (log_c, color), allow_unused=True,
                                                           retain_graph=True)
    (grad_c, grad_color) = torch.autograd.grad(out.rgb.sum(), (log_c, color))
    assert grad_c_fixed is None and float(grad_c.abs()) > 0  # the density gets nothing from it
    assert torch.allclose(grad_color_fixed, grad_color, atol=1e-6)  # the colours get the same


def test_huge_density_is_stable() -> None:
    gen = torch.Generator().manual_seed(3)
    rays = uniform_medium_rays(4, gen)

    def field(x: torch.Tensor) -> FieldOutput:
        return FieldOutput(sigma=torch.full((x.shape[0],), 1e30), rgb=torch.ones(x.shape[0], 3))

    out = render_rays(sample_along_rays(rays, 16, generator=gen), field, torch.zeros(3))
    assert torch.isfinite(out.weights).all()
    assert torch.allclose(out.opacity, torch.ones(4))
    assert torch.allclose(out.weights[:, 0], torch.ones(4))  # all weight on the first sample


def test_invalid_samples_contribute_nothing_and_are_not_evaluated() -> None:
    gen = torch.Generator().manual_seed(4)
    rays = uniform_medium_rays(8, gen)
    samples = sample_along_rays(rays, 20, generator=gen, compact=False)
    drop = torch.rand(8, 20, generator=gen) < 0.4
    valid = samples.valid & ~drop
    seen_counts: list[int] = []

    def field(x: torch.Tensor) -> FieldOutput:
        seen_counts.append(x.shape[0])
        sigma = 3.0 + torch.sin(7 * x).sum(-1)  # varies in space, positive
        return FieldOutput(sigma=sigma, rgb=torch.sigmoid(x))

    base = type(samples)(samples.positions, samples.t, samples.t_starts, samples.t_ends, valid, samples.directions)
    # Garbage in the invalid slots (positions, intervals) must not change anything.
    noise = torch.randn(8, 20, 3, generator=gen) * 100
    garbled = type(samples)(
        torch.where(valid[..., None], samples.positions, noise),
        torch.where(valid, samples.t, -5.0),
        torch.where(valid, samples.t_starts, -9.0),
        torch.where(valid, samples.t_ends, 9.0),
        valid,
        samples.directions,
    )
    background = torch.rand(8, 3, generator=gen)
    out_a = render_rays(base, field, background)
    out_b = render_rays(garbled, field, background)
    out_c = render_rays(compact_samples(base), field, background)
    assert seen_counts == [int(valid.sum())] * 3
    for other in (out_b, out_c):
        assert torch.allclose(out_a.rgb, other.rgb, atol=1e-6)
        assert torch.allclose(out_a.opacity, other.opacity, atol=1e-6)
        assert torch.allclose(out_a.depth, other.depth, atol=1e-5)
    assert (out_a.weights[~valid] == 0).all() and (out_a.sigma[~valid] == 0).all()

    # Reference: composite each ray's valid samples alone with an explicit product.
    for i in range(8):
        idx = torch.nonzero(valid[i]).flatten()
        f = field(samples.positions[i, idx])
        deltas = samples.t_ends[i, idx] - samples.t_starts[i, idx]
        alpha = 1 - torch.exp(-f.sigma * deltas)
        trans = torch.cumprod(torch.cat([torch.ones(1), 1 - alpha[:-1]]), 0)
        w = alpha * trans
        rgb = (w[:, None] * f.rgb).sum(0) + (1 - w.sum()) * background[i]
        assert torch.allclose(out_a.rgb[i], rgb, atol=1e-6)
        assert torch.allclose(out_a.weights[i, idx], w, atol=1e-6)


def test_no_valid_sample_shows_background_without_calling_the_field() -> None:
    rays = RayBundle(torch.zeros(3, 3), torch.tensor([[0.0, 0.0, 1.0]] * 3), torch.zeros(3), torch.zeros(3))
    samples = sample_along_rays(rays, 8)

    def field(x: torch.Tensor) -> FieldOutput:
        raise AssertionError("field called on no samples")

    background = torch.tensor([0.3, 0.5, 0.7])
    out = render_rays(samples, field, background)
    assert torch.equal(out.rgb, background.expand(3, 3)) and (out.opacity == 0).all()
    assert out.gradient is not None and out.gradient[out.valid].shape == (0, 3)


def test_field_output_shapes_are_checked() -> None:
    rays = RayBundle(torch.zeros(2, 3), torch.tensor([[0.0, 0.0, 1.0]] * 2), torch.zeros(2), torch.ones(2))
    samples = sample_along_rays(rays, 4)
    with pytest.raises(ValueError, match="rgb"):
        render_rays(samples, lambda x: {"sigma": torch.ones(x.shape[0]), "rgb": torch.ones(x.shape[0])}, torch.ones(3))
    with pytest.raises(ValueError, match="keys"):
        render_rays(samples, lambda x: {"density": torch.ones(x.shape[0])}, torch.ones(3))


# ------------------------------------------------------------------------------------ sphere
@pytest.fixture(scope="module")
def sphere_render() -> dict[str, torch.Tensor]:
    height = width = 24
    K, w2c = look_at_camera(height, width, focal=36.0, distance=2.0)
    box_min, box_max = torch.full((3,), -0.6), torch.full((3,), 0.6)
    origins, directions = pixel_rays(K, w2c, pixel_grid(height, width))
    rays = rays_in_box(origins, directions, box_min, box_max)
    samples = sample_along_rays(rays, 256, stratified=False)
    out = render_rays(samples, sphere_field, torch.ones(3))
    t_hit, impact = sphere_hit(origins, directions)
    image = render_image(K, w2c, height, width, sphere_field, box_min, box_max, num_samples=256, chunk_rays=200)
    return {
        "out": out,
        "origins": origins,
        "directions": directions,
        "t_hit": t_hit,
        "impact": impact,
        "image": image,
    }


@pytest.mark.parametrize("num_samples", [64, 256])
def test_sphere_depth_and_normals_match_ray_sphere_intersection(num_samples: int) -> None:
    K, w2c = look_at_camera(24, 24, focal=36.0, distance=2.0)
    origins, directions = pixel_rays(K, w2c, pixel_grid(24, 24))
    rays = rays_in_box(origins, directions, torch.full((3,), -0.6), torch.full((3,), 0.6))
    out = render_rays(sample_along_rays(rays, num_samples, stratified=False), sphere_field, torch.ones(3))
    t_hit, impact = sphere_hit(origins, directions)
    hits = impact < 0.9 * RADIUS  # away from grazing rays, where the depth is ill-conditioned
    assert hits.sum() > 100
    depth = out.depth[hits] / out.opacity[hits]
    # Quadrature error of one bin plus the Laplace-density shift of order beta.
    tolerance = (rays.far - rays.near)[hits] / num_samples + 2 * BETA
    assert ((depth - t_hit[hits]).abs() <= tolerance).all()
    x_hit = origins[hits] + t_hit[hits, None] * directions[hits]
    n_true = x_hit / RADIUS
    n_rendered = torch.nn.functional.normalize(out.normal[hits], dim=-1)
    assert ((n_rendered * n_true).sum(-1) > 0.9995).all()


def test_sphere_opacity_and_background(sphere_render: dict) -> None:
    out, impact = sphere_render["out"], sphere_render["impact"]
    hits, misses = impact < 0.9 * RADIUS, impact > 1.1 * RADIUS
    assert misses.sum() > 50
    assert (out.opacity[hits] > 0.999).all()
    assert (out.opacity[misses] < 1e-3).all()
    assert torch.allclose(out.rgb[hits], COLOR.expand(int(hits.sum()), 3), atol=1e-3)
    assert torch.allclose(out.rgb[misses], torch.ones(int(misses.sum()), 3), atol=1e-3)
    # Per-sample extras for the losses: analytic SDF gradients are unit on valid samples.
    grads = out.gradient[out.valid]
    assert torch.allclose(torch.linalg.vector_norm(grads, dim=-1), torch.ones(grads.shape[0]), atol=1e-5)
    assert out.sdf is not None and out.sdf.shape == out.valid.shape


def test_render_image_with_early_termination_matches_full_render(sphere_render: dict) -> None:
    out, image = sphere_render["out"], sphere_render["image"]
    assert image.rgb.shape == (24, 24, 3) and image.depth.shape == (24, 24)
    assert (image.rgb.reshape(-1, 3) - out.rgb).abs().max() < 2e-4
    assert (image.opacity.reshape(-1) - out.opacity).abs().max() < 2e-4
    seen = out.opacity > 0.5
    full_depth = out.depth[seen] / out.opacity[seen]
    assert (image.depth.reshape(-1)[seen] - full_depth).abs().max() < 1e-3
    normals = image.normal.reshape(-1, 3)[seen]
    assert torch.allclose(torch.linalg.vector_norm(normals, dim=-1), torch.ones(int(seen.sum())), atol=1e-5)


def test_early_termination_skips_samples_behind_the_surface() -> None:
    K, w2c = look_at_camera(8, 8, focal=12.0, distance=2.0)
    origins, directions = pixel_rays(K, w2c, pixel_grid(8, 8))
    rays = rays_in_box(origins, directions, torch.full((3,), -0.6), torch.full((3,), 0.6))
    samples = sample_along_rays(rays, 128, stratified=False)
    counts: list[int] = []

    def field(x: torch.Tensor) -> FieldOutput:
        counts.append(x.shape[0])
        return sphere_field(x)

    full = render_rays(samples, field, torch.ones(3))
    n_full = sum(counts)
    counts.clear()
    early = march_rays(samples, field, torch.ones(3), early_stop_transmittance=1e-4, march_chunk=16)
    assert sum(counts) < 0.8 * n_full
    assert (early.rgb - full.rgb).abs().max() < 2e-4
    assert int(early.valid.sum()) == sum(counts)
