"""Losses against closed forms (sphere, plane SDFs) and naive loop references (Eq. 9 pairing)."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from igavatar.model.fd_losses import curvature_loss, finite_difference_eikonal, finite_difference_gradient, finite_difference_terms
from igavatar.model.losses import (
    LossWeights,
    alpha_loss,
    eikonal_loss,
    linear_warmup,
    rgb_loss,
    smooth_loss_along_ray,
    smooth_loss_neighbour_rays,
    total_loss,
)
from igavatar.render.rays import rays_in_box
from igavatar.render.sampler import sample_along_rays
from igavatar.render.volume import FieldOutput, render_rays


def sphere_sdf(x: torch.Tensor, radius: float = 0.5, scale: float = 1.0) -> torch.Tensor:
    return scale * (torch.linalg.vector_norm(x, dim=-1) - radius)


def autograd_gradient(sdf_fn, x: torch.Tensor) -> torch.Tensor:
    x = x.detach().requires_grad_(True)
    (grad,) = torch.autograd.grad(sdf_fn(x).sum(), x)
    return grad


def eq9_loop(normals: torch.Tensor, valid: torch.Tensor, per: str = "samples") -> float:
    """Naive Eq. 9: walk each ray's valid samples in order, pair neighbours, average."""
    per_ray = []
    for i in range(normals.shape[0]):
        seq = [normals[i, j] / normals[i, j].norm() for j in range(normals.shape[1]) if valid[i, j]]
        if len(seq) < 2:
            continue
        total = 0.0
        for a, b in zip(seq[:-1], seq[1:]):
            mid = (a + b) / 2
            total += float((mid - a).norm() + (mid - b).norm())
        per_ray.append(total / (len(seq) if per == "samples" else len(seq) - 1))
    return sum(per_ray) / len(per_ray) if per_ray else 0.0


# -------------------------------------------------------------------------------- photometric
def test_rgb_and_alpha_losses() -> None:
    gen = torch.Generator().manual_seed(0)
    pred, target = torch.rand(10, 3, generator=gen), torch.rand(10, 3, generator=gen)
    diff = pred - target
    assert rgb_loss(pred, target) == pytest.approx(float((diff**2).mean()))
    assert rgb_loss(pred, target, kind="l1") == pytest.approx(float(diff.abs().mean()))
    huber = torch.where(diff.abs() < 0.1, 0.5 * diff**2, 0.1 * (diff.abs() - 0.05))
    assert rgb_loss(pred, target, kind="huber") == pytest.approx(float(huber.mean()))
    opacity, mask = torch.rand(10, generator=gen), torch.rand(10, generator=gen) > 0.5
    assert alpha_loss(opacity, mask) == pytest.approx(float((opacity - mask.float()).abs().mean()))
    assert alpha_loss(opacity, mask, kind="mse") == pytest.approx(float(((opacity - mask.float()) ** 2).mean()))
    with pytest.raises(ValueError):
        rgb_loss(pred, target, kind="l3")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        rgb_loss(pred, target[:5])


# ---------------------------------------------------------------------------------- eikonal
def test_eikonal_zero_for_true_sdf_positive_for_scaled() -> None:
    x = torch.randn(200, 3, generator=torch.Generator().manual_seed(1))
    assert float(eikonal_loss(autograd_gradient(sphere_sdf, x))) < 1e-10
    scaled = autograd_gradient(lambda p: sphere_sdf(p, scale=2.0), x)
    assert float(eikonal_loss(scaled)) == pytest.approx(1.0, rel=1e-5)  # (|2 n| - 1)^2 = 1


def test_eikonal_ignores_invalid_slots() -> None:
    x = torch.randn(4, 6, 3, generator=torch.Generator().manual_seed(2))
    grads = x / x.norm(dim=-1, keepdim=True)
    valid = torch.rand(4, 6, generator=torch.Generator().manual_seed(3)) > 0.5
    padded = torch.where(valid[..., None], grads, torch.zeros_like(grads))  # dummy empty slots
    assert float(eikonal_loss(padded, valid)) < 1e-10
    assert float(eikonal_loss(padded.reshape(-1, 3))) > 0.1  # what averaging the slots would do
    assert float(eikonal_loss(torch.zeros(0, 3))) == 0.0


# ------------------------------------------------------------------------------- smoothness
def straight_rays_through(sdf_fn, r: int, s: int, gen: torch.Generator) -> torch.Tensor:
    """Gradients (R, S, 3) of the SDF at S points along R random straight rays."""
    origins = torch.randn(r, 3, generator=gen)
    directions = torch.nn.functional.normalize(torch.randn(r, 3, generator=gen), dim=-1)
    t = torch.linspace(0.0, 1.0, s)
    points = origins[:, None] + t[None, :, None] * directions[:, None]
    return autograd_gradient(sdf_fn, points.reshape(-1, 3)).reshape(r, s, 3)


def test_smooth_loss_zero_on_a_plane_positive_on_noisy_sdf() -> None:
    gen = torch.Generator().manual_seed(4)
    normal = torch.nn.functional.normalize(torch.tensor([0.3, -1.0, 0.5]), dim=0)

    def plane(x: torch.Tensor) -> torch.Tensor:
        return x @ normal - 0.2

    def noisy(x: torch.Tensor) -> torch.Tensor:
        return plane(x) + 0.05 * torch.sin(25 * x).prod(-1)

    valid = torch.rand(16, 32, generator=gen) > 0.3
    grads = straight_rays_through(plane, 16, 32, gen)
    loss = smooth_loss_along_ray(grads, valid)
    assert float(loss) < 1e-6
    noisy_grads = straight_rays_through(noisy, 16, 32, gen)
    assert float(smooth_loss_along_ray(noisy_grads, valid)) > 1e-2
    # Zero differences must still give finite gradients (norm at 0).
    leaf = grads.detach().requires_grad_(True)
    smooth_loss_along_ray(leaf, valid).backward()
    assert torch.isfinite(leaf.grad).all()


def test_smooth_loss_pairs_consecutive_valid_samples_across_gaps() -> None:
    gen = torch.Generator().manual_seed(5)
    normals = torch.randn(6, 7, 3, generator=gen) * torch.rand(6, 7, 1, generator=gen) * 3
    valid = torch.tensor(
        [
            [1, 1, 1, 1, 1, 1, 1],  # full ray
            [1, 0, 0, 1, 0, 1, 0],  # pairs (0,3) and (3,5) across gaps
            [0, 0, 0, 0, 0, 0, 1],  # one sample: no pair, not counted
            [0, 0, 0, 0, 0, 0, 0],  # empty ray
            [0, 1, 1, 0, 0, 0, 1],
            [1, 0, 1, 1, 0, 0, 0],
        ],
        dtype=torch.bool,
    )
    # Garbage in invalid slots must not matter.
    garbled = torch.where(valid[..., None], normals, torch.randn(6, 7, 3, generator=gen) * 50)
    for per in ("samples", "pairs"):
        got = float(smooth_loss_along_ray(garbled, valid, normalization=per))
        assert got == pytest.approx(eq9_loop(normals, valid, per), rel=1e-5)
    # Hand value for ray 1 alone: normals a, b, c; (|a-b| + |b-c|) / 3 (Eq. 9 term = |n_j - n_{j+1}|).
    n = torch.nn.functional.normalize(normals[1], dim=-1)
    hand = (float((n[0] - n[3]).norm()) + float((n[3] - n[5]).norm())) / 3
    only_ray_1 = torch.zeros_like(valid)
    only_ray_1[1] = valid[1]
    assert float(smooth_loss_along_ray(normals, only_ray_1)) == pytest.approx(hand, rel=1e-5)


def test_smooth_loss_band_keeps_only_samples_near_the_zero_level() -> None:
    # One ray under a crease: the distance field's normals turn along it in empty space (sdf 2-5
    # cm) while the samples at the surface it ends on (|sdf| < 1 cm) agree.
    gen = torch.Generator().manual_seed(3)
    turning = torch.nn.functional.normalize(torch.randn(1, 5, 3, generator=gen), dim=-1)
    surface = torch.tensor([0.0, 0.0, 1.0]).expand(1, 3, 3)
    normals = torch.cat((turning, surface), dim=1)
    sdf = torch.tensor([[0.05, 0.04, 0.03, 0.025, 0.02, 0.008, 0.0, -0.006]])
    valid = torch.ones(1, 8, dtype=torch.bool)
    assert float(smooth_loss_along_ray(normals, valid)) > 0.1
    banded = smooth_loss_along_ray(normals, valid, sdf=sdf, band=0.01)
    assert float(banded) == 0.0
    # The band is the same as marking the far samples invalid.
    near = sdf.abs() < 0.015
    assert float(smooth_loss_along_ray(normals, valid, sdf=sdf, band=0.015)) == pytest.approx(
        float(smooth_loss_along_ray(normals, valid & near)), rel=1e-6)
    with pytest.raises(ValueError, match="band needs sdf"):
        smooth_loss_along_ray(normals, valid, band=0.01)


def test_smooth_loss_is_invariant_to_compaction() -> None:
    gen = torch.Generator().manual_seed(6)
    normals = torch.randn(8, 12, 3, generator=gen)
    valid = torch.rand(8, 12, generator=gen) > 0.5
    order = torch.sort((~valid).to(torch.uint8), dim=1, stable=True).indices
    packed = torch.gather(normals, 1, order[..., None].expand(8, 12, 3))
    packed_valid = torch.gather(valid, 1, order)
    a = smooth_loss_along_ray(normals, valid)
    b = smooth_loss_along_ray(packed[:, : int(valid.sum(1).max())], packed_valid[:, : int(valid.sum(1).max())])
    assert float(a) == pytest.approx(float(b), rel=1e-6)
    assert float(smooth_loss_along_ray(normals, torch.zeros_like(valid))) == 0.0


def test_adjacent_pairs_skip_gaps_and_match_a_loop_before_and_after_compaction() -> None:
    gen = torch.Generator().manual_seed(8)
    r, s = 6, 10
    normals = torch.randn(r, s, 3, generator=gen)
    valid = torch.rand(r, s, generator=gen) > 0.4
    valid[0] = torch.tensor([1, 1, 0, 0, 1, 1, 1, 0, 0, 1], dtype=torch.bool)  # two runs and a lone sample
    edges = torch.linspace(0.5, 2.5, s + 1).expand(r, s + 1)
    starts, ends = edges[:, :-1].contiguous(), edges[:, 1:].contiguous()

    def loop() -> float:
        per_ray = []
        for i in range(r):
            idx = [j for j in range(s) if valid[i, j]]
            if len(idx) < 2:
                continue
            n = torch.nn.functional.normalize(normals[i], dim=-1)
            total = sum(float((n[a] - n[b]).norm()) for a, b in zip(idx[:-1], idx[1:]) if b == a + 1)
            per_ray.append(total / len(idx))  # Eq. 9's 1 / N_s^i
        return sum(per_ray) / len(per_ray)

    got = smooth_loss_along_ray(normals, valid, pairs="adjacent", t_starts=starts, t_ends=ends)
    assert float(got) == pytest.approx(loop(), rel=1e-5)
    # Ray 0 alone by hand: pairs (0,1), (4,5), (5,6); the pair (1,4) and (6,9) cross gaps.
    n0 = torch.nn.functional.normalize(normals[0], dim=-1)
    hand = sum(float((n0[a] - n0[b]).norm()) for a, b in ((0, 1), (4, 5), (5, 6))) / 6
    only_0 = torch.zeros_like(valid)
    only_0[0] = valid[0]
    assert float(smooth_loss_along_ray(normals, only_0, pairs="adjacent", t_starts=starts, t_ends=ends)) == pytest.approx(hand, rel=1e-5)
    # "valid" also pairs across the gaps, (1, 4) and (6, 9), so it is larger on this ray.
    assert float(smooth_loss_along_ray(normals, only_0)) > hand
    # The same value in the compacted layout (valid samples moved to the front with their intervals).
    order = torch.sort((~valid).to(torch.uint8), dim=1, stable=True).indices
    width = int(valid.sum(1).max())

    def pack(x: torch.Tensor) -> torch.Tensor:
        index = order if x.ndim == 2 else order[..., None].expand_as(x)
        return torch.gather(x, 1, index)[:, :width]

    packed = smooth_loss_along_ray(
        pack(normals), pack(valid), pairs="adjacent", t_starts=pack(starts), t_ends=pack(ends)
    )
    assert float(packed) == pytest.approx(float(got), rel=1e-6)
    with pytest.raises(ValueError, match="t_starts"):
        smooth_loss_along_ray(normals, valid, pairs="adjacent")


def _analytic_ray(sdf_fn, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Positions (1, S, 3) on the z axis (slightly off it) and the SDF's autograd gradients there."""
    x = torch.stack([torch.full_like(z, 0.003), torch.full_like(z, -0.002), z], dim=-1).requires_grad_(True)
    (grad,) = torch.autograd.grad(sdf_fn(x).sum(), x)
    return x.detach()[None], grad[None]


def test_monotone_pairs_drop_the_flip_at_a_distance_ridge_and_keep_surface_noise() -> None:
    z = torch.linspace(-0.1, 0.1, 41)  # 5 mm apart along one ray
    valid = torch.ones(1, 41, dtype=torch.bool)

    def finger(x: torch.Tensor) -> torch.Tensor:  # a slab 1.6 cm thick: its medial plane is z = 0
        return x[..., 2].abs() - 0.008

    def two_fingers(x: torch.Tensor) -> torch.Tensor:  # two slabs with a 4 cm gap: a ridge outside, at z = 0
        return torch.minimum((x[..., 2] - 0.04).abs(), (x[..., 2] + 0.04).abs()) - 0.008

    for sdf_fn in (finger, two_fingers):
        positions, gradients = _analytic_ray(sdf_fn, z)
        every = smooth_loss_along_ray(gradients, valid, normalization="released")
        monotone = smooth_loss_along_ray(gradients, valid, normalization="released", pairs="monotone", positions=positions)
        # The distance field's normals flip at the ridge: every pair counts it, monotone pairs do not.
        assert float(every) > 1e-3
        assert float(monotone) == pytest.approx(0.0, abs=1e-9)

    def rippled_wall(x: torch.Tensor) -> torch.Tensor:  # a surface at z = 0 with bumps (texture printed into geometry)
        return x[..., 2] + 0.004 * torch.sin(400.0 * x[..., 2]) * torch.sin(300.0 * x[..., 0] + 5.0)

    positions, gradients = _analytic_ray(rippled_wall, z)
    every = smooth_loss_along_ray(gradients, valid, normalization="released")
    monotone = smooth_loss_along_ray(gradients, valid, normalization="released", pairs="monotone", positions=positions)
    # The SDF runs one way along this ray: every pair is monotone and the noise is penalised as before.
    assert float(every) > 1e-3
    assert float(monotone) == pytest.approx(float(every), rel=1e-6)
    with pytest.raises(ValueError, match="positions"):
        smooth_loss_along_ray(gradients, valid, pairs="monotone")


def test_neighbour_ray_variant_masks_row_and_patch_boundaries() -> None:
    gen = torch.Generator().manual_seed(7)
    p, hp, wp, s = 2, 3, 4, 5
    normals = torch.randn(p, hp, wp, s, 3, generator=gen)
    valid = torch.rand(p, hp, wp, s, generator=gen) > 0.3

    def loop(include_vertical: bool) -> float:
        total, count = 0.0, 0
        n = torch.nn.functional.normalize(normals, dim=-1)
        for b in range(p):
            for y in range(hp):
                for x in range(wp):
                    neighbours = [(y, x + 1)] + ([(y + 1, x)] if include_vertical else [])
                    for yy, xx in neighbours:
                        if yy >= hp or xx >= wp:
                            continue  # no pair across a row end or out of the patch
                        for k in range(s):
                            if valid[b, y, x, k] and valid[b, yy, xx, k]:
                                mid = (n[b, y, x, k] + n[b, yy, xx, k]) / 2
                                total += float((mid - n[b, y, x, k]).norm() + (mid - n[b, yy, xx, k]).norm())
                                count += 1
        return total / count

    for include_vertical in (False, True):
        got = float(smooth_loss_neighbour_rays(normals, valid, include_vertical=include_vertical))
        assert got == pytest.approx(loop(include_vertical), rel=1e-5)
    # Flat normals everywhere give zero.
    flat = torch.tensor([0.0, 0.0, 1.0]).expand(p, hp, wp, s, 3)
    assert float(smooth_loss_neighbour_rays(flat, valid, include_vertical=True)) < 1e-7


# ------------------------------------------------------------------- finite-difference terms
def test_finite_difference_gradient_eikonal_and_curvature_on_a_sphere() -> None:
    gen = torch.Generator().manual_seed(8)
    x = torch.randn(100, 3, generator=gen, dtype=torch.float64)
    x = x / x.norm(dim=-1, keepdim=True) * (0.3 + torch.rand(100, 1, generator=gen, dtype=torch.float64))
    eps = 1e-3
    grad_fd = finite_difference_gradient(sphere_sdf, x, eps)
    assert torch.allclose(grad_fd, x / x.norm(dim=-1, keepdim=True), atol=1e-5)
    assert float(finite_difference_eikonal(sphere_sdf, x, eps)) < 1e-9
    assert float(finite_difference_eikonal(lambda p: sphere_sdf(p, scale=2.0), x, eps)) == pytest.approx(1.0, rel=1e-5)
    # Laplacian of |x| - r is 2 / |x|.
    expected = float((2.0 / x.norm(dim=-1)).mean())
    assert float(curvature_loss(sphere_sdf, x, eps)) == pytest.approx(expected, rel=1e-4)
    eik, curv = finite_difference_terms(sphere_sdf, x, eps, sdf_at_x=sphere_sdf(x))
    assert float(curv) == pytest.approx(expected, rel=1e-4) and float(eik) < 1e-9


def test_curvature_zero_on_a_plane_and_uses_six_neighbours() -> None:
    calls: list[int] = []

    def plane(x: torch.Tensor) -> torch.Tensor:
        calls.append(x.shape[0])
        return x @ torch.tensor([0.6, 0.0, 0.8], dtype=x.dtype) + 0.1

    x = torch.randn(50, 3, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    assert float(curvature_loss(plane, x, 1e-2, sdf_at_x=plane(x))) < 1e-9
    assert calls == [50, 300]  # d(x) given, then one batched call for the 6 neighbours


# ------------------------------------------------------------------------------ weighting
def test_loss_weights_defaults_and_total() -> None:
    w = LossWeights()
    assert (w.rgb, w.alpha, w.eikonal, w.smooth) == (10.0, 0.1, 0.1, 1.0)
    assert w.curvature == 5e-4
    with pytest.raises(dataclasses.FrozenInstanceError):
        w.rgb = 1.0  # type: ignore[misc]
    total = total_loss({"rgb": torch.tensor(0.5), "smooth": torch.tensor(2.0)}, w)
    assert float(total) == pytest.approx(10.0 * 0.5 + 2.0)
    with pytest.raises(ValueError, match="unknown"):
        total_loss({"lpips": torch.tensor(1.0)}, w)
    assert [linear_warmup(s, 100) for s in (0, 50, 100, 500)] == [0.0, 0.5, 1.0, 1.0]
    assert math.isclose(linear_warmup(3, 0), 1.0)


# ------------------------------------------------------------------ wired through the renderer
def test_losses_on_rendered_samples_backpropagate_to_field_parameters() -> None:
    """The training wiring: analytic gradients with create_graph, renderer extras, all losses."""
    gen = torch.Generator().manual_seed(10)
    radius = torch.tensor(0.45, requires_grad=True)
    wobble = torch.tensor(0.05, requires_grad=True)
    beta = 0.02

    def field(x_posed: torch.Tensor) -> FieldOutput:
        with torch.enable_grad():
            x = x_posed.detach().requires_grad_(True)
            sdf = x.norm(dim=-1) - radius + wobble * torch.sin(9 * x).prod(-1)
            (grad,) = torch.autograd.grad(sdf.sum(), x, create_graph=True)
        sigma = (0.5 + 0.5 * torch.sign(-sdf) * (1 - torch.exp(-sdf.abs() / beta))) / beta
        return FieldOutput(sigma=sigma, rgb=torch.sigmoid(x * 3), gradient=grad, sdf=sdf)

    origins = torch.tensor([[0.0, 0.0, -2.0]]).expand(64, 3) + torch.rand(64, 3, generator=gen) * 0.2
    targets = (torch.rand(64, 3, generator=gen) - 0.5) * 1.2
    directions = torch.nn.functional.normalize(targets - origins, dim=-1)
    rays = rays_in_box(origins, directions, -0.6 * torch.ones(3), 0.6 * torch.ones(3))
    samples = sample_along_rays(rays, 64, generator=gen)
    background = torch.rand(64, 3, generator=gen)
    out = render_rays(samples, field, background)
    assert out.gradient is not None
    terms = {
        "rgb": rgb_loss(out.rgb, background),
        "alpha": alpha_loss(out.opacity, torch.ones(64)),
        "eikonal": eikonal_loss(out.gradient[out.valid]),
        "smooth": smooth_loss_along_ray(out.gradient, out.valid),
    }
    assert float(terms["smooth"].detach()) > 0 and float(terms["eikonal"].detach()) > 0
    total_loss(terms, LossWeights()).backward()
    for p in (radius, wobble):
        assert p.grad is not None and torch.isfinite(p.grad) and float(p.grad) != 0.0
    # The smoothness term alone pushes the wobble (the only source of curvature change) down.
    wobble.grad = None
    smooth_loss_along_ray(render_rays(samples, field, background).gradient, out.valid).backward()
    assert float(wobble.grad) > 0


def test_smooth_loss_released_normalization_squares_and_divides_by_every_slot() -> None:
    # One ray of 4 slots with 3 valid samples: normals +x, +x, +y (one change of 90 degrees).
    gradients = torch.tensor([[[1.0, 0, 0], [2.0, 0, 0], [0, 3.0, 0], [0, 0, 1.0]]])
    valid = torch.tensor([[True, True, True, False]])
    released = smooth_loss_along_ray(gradients, valid, normalization="released")
    # |n_bar - n_a|^2 + |n_bar - n_b|^2 = |n_b - n_a|^2 / 2 = 1 for the 90-degree pair, over 3 slots.
    assert math.isclose(float(released), 1.0 / 3.0, rel_tol=1e-6)
    eq9 = smooth_loss_along_ray(gradients, valid)
    assert math.isclose(float(eq9), math.sqrt(2.0) / 3.0, rel_tol=1e-6)  # unsquared, over N_s = 3
    # Twice the rays with nothing valid halves the released value (every slot counts), not Eq. 9's.
    padded_g = torch.cat([gradients, torch.zeros_like(gradients)])
    padded_v = torch.cat([valid, torch.zeros_like(valid)])
    assert math.isclose(float(smooth_loss_along_ray(padded_g, padded_v, normalization="released")), 1.0 / 6.0, rel_tol=1e-6)
    assert math.isclose(float(smooth_loss_along_ray(padded_g, padded_v)), float(eq9), rel_tol=1e-6)
