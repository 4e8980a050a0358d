"""The colour's pull on the surface only near the mask's outline (`--color-weights-outline-px`):
the band is where it should be, each ray gets its scale, and the trainer passes it on."""

from __future__ import annotations

import pytest
import torch

from igavatar.training.outline import outline_band, outline_rays, weights_gradient_scale


def _chebyshev_to_outline(mask: torch.Tensor) -> torch.Tensor:
    """(H, W) the brute-force reference: each pixel's Chebyshev distance to the nearest pixel of the
    other class (inside: to the background; outside: to the person)."""
    ys, xs = torch.meshgrid(torch.arange(mask.shape[0]), torch.arange(mask.shape[1]), indexing="ij")
    yx = torch.stack([ys.flatten(), xs.flatten()], dim=1)
    flat = mask.flatten()
    gap = (yx[:, None, :] - yx[None, :, :]).abs().amax(dim=-1)          # (P, P) Chebyshev
    other = flat[:, None] != flat[None, :]
    return torch.where(other, gap, torch.full_like(gap, 10**6)).amin(dim=1).reshape(mask.shape)


@pytest.mark.parametrize("width", [1, 2, 3])
def test_the_band_holds_the_pixels_within_its_width_of_the_outline_on_both_sides(width):
    """A disc and a notched square: a pixel is on the band exactly when the other class lies within
    `width` pixels of it (the brute-force distance above)."""
    ys, xs = torch.meshgrid(torch.arange(24), torch.arange(24), indexing="ij")
    disc = (ys - 11.5) ** 2 + (xs - 11.5) ** 2 < 7.5 ** 2
    square = (ys >= 5) & (ys < 19) & (xs >= 5) & (xs < 19) & ~((ys >= 10) & (ys < 13) & (xs >= 12))
    for mask in (disc, square):
        band = outline_band(mask, width)
        assert torch.equal(band, _chebyshev_to_outline(mask) <= width)
        assert band.any() and not band.all()
    assert not outline_band(disc, 3)[11, 11]   # the disc's centre is more than 3 px inside


def test_the_image_border_is_no_outline():
    """A person cut by the frame's bottom edge: the rows along that edge away from the sides are not on the band."""
    mask = torch.zeros(16, 16, dtype=torch.bool)
    mask[6:, 4:12] = True
    band = outline_band(mask, 2)
    assert not band[15, 6:10].any()          # inside, on the image's edge
    assert band[15, 4] and band[15, 2]       # the sides still are


@pytest.mark.parametrize("width", [1, 2, 4])
def test_the_summed_area_lookup_matches_the_pooled_band_on_every_pixel(width):
    """outline_rays (what training uses) against outline_band (the plain reference), at every pixel of
    random blobs, one cut by the image's edges."""
    generator = torch.Generator().manual_seed(width)
    for _ in range(3):
        blobs = torch.nn.functional.avg_pool2d(torch.rand(1, 1, 40, 56, generator=generator), 9, stride=1, padding=4)[0, 0]
        mask = blobs > blobs.median()
        ys, xs = torch.meshgrid(torch.arange(40), torch.arange(56), indexing="ij")
        pixels_xy = torch.stack([xs.flatten(), ys.flatten()], dim=1)
        on_band = outline_rays(mask, pixels_xy, width)
        assert torch.equal(on_band, outline_band(mask, width).flatten())
        assert on_band.any() and not on_band.all()


def test_each_ray_gets_one_on_the_band_and_the_inside_value_elsewhere():
    torch.testing.assert_close(weights_gradient_scale(torch.tensor([True, False, False]), 0.25), torch.tensor([1.0, 0.25, 0.25]))


def test_a_per_ray_scale_scales_each_rays_weights_gradient_and_keeps_the_picture():
    """rgb_with_weights_gradient with (R,) scales: the picture and the colour gradient are `rgb`'s,
    and each ray's weights get its own share of `rgb`'s weights gradient (one ray 0, one 1, one 0.3)."""
    from tests.test_color_decoupling import composite_gradients, random_composite

    case = random_composite(3, 6)
    background, scale = case[2], torch.tensor([0.0, 1.0, 0.3])
    full_picture, full_weights, full_colours = composite_gradients(*case, lambda out: out.rgb)
    picture, weights_grad, colours_grad = composite_gradients(*case, lambda out: out.rgb_with_weights_gradient(background, scale))
    torch.testing.assert_close(picture, full_picture)
    torch.testing.assert_close(colours_grad, full_colours)
    torch.testing.assert_close(weights_grad, scale[:, None] * full_weights)
    assert full_weights[0].abs().sum() > 0   # the zero on ray 0 is the scale's, not the loss's


def test_the_trainer_scales_per_ray_only_with_the_option(small_run):
    """Off: one number (the preset's share). On: ones on the frame's outline band, the share elsewhere."""
    from tests.test_train import _trainer

    dataset = small_run / "dataset"
    pixels = _trainer(dataset)._draw_pixels(0)
    assert _trainer(dataset, color_weights_gradient=0.3)._weights_gradient_scale(0, pixels) == 0.3
    assert _trainer(dataset, color_shapes_geometry=False, color_weights_outline_px=2)._weights_gradient_scale(0, pixels) == 0.0
    trainer = _trainer(dataset, color_weights_gradient=0.0, color_weights_outline_px=1)
    on_band = []
    for draw in range(4):   # the tiny frames' person is a few pixels wide: several draws hold rays on and off the band
        index = draw % len(trainer.data.masks)
        pixels = trainer._draw_pixels(index)
        expected = outline_band(trainer.data.masks[index], 1)[pixels[:, 1], pixels[:, 0]].float()
        torch.testing.assert_close(trainer._weights_gradient_scale(index, pixels), expected)
        on_band.append(expected)
    on_band = torch.cat(on_band)
    assert 0 < on_band.sum() < len(on_band)


def test_the_outline_option_is_checked_and_reaches_the_config(tmp_path):
    from igavatar.errors import InputError
    from stages.train import TrainOptions, resolve_config

    def options(**extra):
        return TrainOptions(dataset=tmp_path, out=tmp_path / "m", preset="cpu", **extra)

    assert resolve_config(options(color_weights_outline_px=4)).color_weights_outline_px == 4
    with pytest.raises(InputError, match="--color-weights-outline-px -1"):
        resolve_config(options(color_weights_outline_px=-1))


def test_the_cpu_preset_scales_the_band_with_the_images_and_a_given_width_wins(tmp_path):
    """cpu: the longer side / 128 (the widths measured: 2 px at 256, 4 at 512); paper: off; an
    explicit --color-weights-outline-px is kept as given."""
    from igavatar.training.config import OUTLINE_AUTO, outline_px_for
    from stages.train import TrainOptions, resolve_config
    from stages.train_options import with_outline_px

    def resolved(preset="cpu", size=(512, 384), **extra):
        options = TrainOptions(dataset=tmp_path, out=tmp_path / "m", preset=preset, **extra)
        return with_outline_px(resolve_config(options), size).color_weights_outline_px

    assert resolve_config(TrainOptions(dataset=tmp_path, out=tmp_path / "m")).color_weights_outline_px == OUTLINE_AUTO
    assert (outline_px_for((256, 256)), outline_px_for((384, 512)), outline_px_for((1024, 1024)), outline_px_for((64, 48))) == (2, 4, 8, 1)
    assert resolved() == 4 and resolved(size=(256, 192)) == 2
    assert resolved("paper") == 0 and resolved("tiny") == 0
    assert resolved(color_weights_outline_px=3) == 3 and resolved(color_weights_outline_px=0) == 0


def test_an_unresolved_automatic_band_is_refused_by_the_trainer(small_run):
    from igavatar.training.config import OUTLINE_AUTO
    from tests.test_train import _trainer

    trainer = _trainer(small_run / "dataset", color_weights_outline_px=OUTLINE_AUTO)
    with pytest.raises(ValueError, match="with_outline_px"):
        trainer._weights_gradient_scale(0, trainer._draw_pixels(0))


def test_the_edge_pixels_are_the_persons_pixels_next_to_the_background():
    """A disc cut by the image's left edge: the edge pixels are exactly the person's pixels with a
    background pixel among their 8 neighbours (brute force), none on the image's border."""
    from igavatar.training.outline import outline_pixels

    ys, xs = torch.meshgrid(torch.arange(20), torch.arange(24), indexing="ij")
    mask = (ys - 10) ** 2 + (xs - 2) ** 2 < 8 ** 2
    expected = mask & (_chebyshev_to_outline(mask) <= 1)
    edge = outline_pixels(mask)
    got = torch.zeros_like(mask)
    got[edge[:, 1], edge[:, 0]] = True
    assert torch.equal(got, expected)
    assert not got[:, 0][4:17].any()          # the frame's edge is no outline
    assert got.sum() < mask.sum() / 2


def test_outline_sampling_centres_the_subjects_patches_on_the_edge(small_run):
    """With --outline-sampling 1 each subject-centred patch is centred on an edge pixel of its frame's
    mask (where the image's border does not clamp it); the centres spread over the edge; a share out
    of [0, 1] is refused."""
    from igavatar.errors import InputError
    from igavatar.training.outline import outline_pixels
    from stages.train import TrainOptions, resolve_config
    from tests.test_train import _trainer

    dataset = small_run / "dataset"
    trainer = _trainer(dataset, outline_sampling=1.0)
    size, (height, width) = trainer.config.patch_size, trainer.data.image_size
    n_in = int(round(trainer._patches_per_step * trainer.config.patch_centres_in_mask))
    index = int(trainer.data.train_indices[0])
    edge = outline_pixels(trainer.data.masks[index])
    edge_set = {tuple(p) for p in edge.tolist()}
    drawn = trainer._outline_centres(index, 400)
    assert {tuple(p) for p in drawn.tolist()} <= edge_set
    assert len({tuple(p) for p in drawn.tolist()}) > 0.8 * len(edge_set)     # uniform over the edge, not one spot
    checked = 0
    for _ in range(10):
        patches = trainer._draw_pixels(index).reshape(-1, size * size, 2)[:n_in]
        for patch in patches:
            centre = patch[0] + size // 2                                     # top-left + half the edge
            if patch[0, 0] > 0 and patch[0, 1] > 0 and patch[-1, 0] < width - 1 and patch[-1, 1] < height - 1:
                assert tuple(centre.tolist()) in edge_set
                checked += 1
    assert checked > 0
    with pytest.raises(InputError, match="--outline-sampling 1.5"):
        resolve_config(TrainOptions(dataset=dataset, out=dataset / "m", preset="cpu", outline_sampling=1.5))
    with pytest.raises(InputError, match="sum must be <= 1"):
        resolve_config(TrainOptions(dataset=dataset, out=dataset / "m", preset="cpu", outline_sampling=0.6, error_sampling=0.6))


def test_the_cpu_preset_centres_half_the_subjects_patches_on_the_edge_and_the_paper_none():
    from igavatar.training.config import preset

    assert preset("cpu").outline_sampling == 0.5
    assert preset("paper").outline_sampling == 0.0 and preset("tiny").outline_sampling == 0.0
