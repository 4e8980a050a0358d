"""A pattern's edges pass none of the colour's pull through the weights (`--color-weights-edge-contrast`):
the edge rays are where a brute-force window says, the scale rule keeps the band's whole pull, and the
trainer and the options pass it on."""

from __future__ import annotations

import pytest
import torch

from igavatar.training.outline import LUMA_RGB, outline_band, texture_edge_rays, weights_gradient_scale


def _striped_person(height: int = 30, width: int = 40) -> tuple[torch.Tensor, torch.Tensor]:
    """(H, W, 3) uint8 and (H, W) bool: a disc of horizontal stripes (4 px dark green, 4 px white)
    on a black background, cut by the image's right edge, with a flat grey patch in it."""
    ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    mask = (ys - 15) ** 2 + (xs - 30) ** 2 < 13 ** 2
    image = torch.zeros(height, width, 3, dtype=torch.uint8)
    stripe = (ys // 4) % 2 == 0
    image[mask & stripe] = torch.tensor([20, 110, 40], dtype=torch.uint8)
    image[mask & ~stripe] = torch.tensor([240, 240, 240], dtype=torch.uint8)
    image[8:22, 24:34] = torch.tensor([128, 128, 128], dtype=torch.uint8)   # flat: no edge inside it
    return image, mask


def _edge_reference(image: torch.Tensor, mask: torch.Tensor, width: int, contrast: float) -> torch.Tensor:
    """(H, W) bool, pixel by pixel: the luma range over the person's pixels of the clipped window."""
    luma = (image.double() @ torch.tensor(LUMA_RGB, dtype=torch.float64)) / 255.0
    height, w_img = mask.shape
    out = torch.zeros_like(mask)
    for y in range(height):
        for x in range(w_img):
            window = (slice(max(0, y - width), y + width + 1), slice(max(0, x - width), x + width + 1))
            values = luma[window][mask[window]]
            out[y, x] = values.numel() > 0 and float(values.max() - values.min()) > contrast
    return out


@pytest.mark.parametrize("width,contrast", [(1, 0.2), (2, 0.2), (2, 0.6)])
def test_the_edge_rays_are_the_windows_spanning_the_contrast_on_the_person(width, contrast):
    image, mask = _striped_person()
    ys, xs = torch.meshgrid(torch.arange(mask.shape[0]), torch.arange(mask.shape[1]), indexing="ij")
    pixels_xy = torch.stack([xs.flatten(), ys.flatten()], dim=1)
    on_edge = texture_edge_rays(image, mask, pixels_xy, width, contrast).reshape(mask.shape)
    assert torch.equal(on_edge, _edge_reference(image, mask, width, contrast))
    assert on_edge.any() and not on_edge[mask].all()
    assert not on_edge[15, 29]            # inside the flat patch
    assert not on_edge[0, 0]              # background far from the person: no person pixel in its window
    # The float image in [0, 1] gives the same rays as its uint8.
    assert torch.equal(texture_edge_rays(image.float() / 255.0, mask, pixels_xy, width, contrast).reshape(mask.shape), on_edge)


def test_the_outline_of_a_flat_person_is_no_texture_edge():
    """A white disc on black: the mask's outline has all the contrast there is, and none of it is a pattern's."""
    image, mask = _striped_person()
    flat = torch.where(mask[..., None], torch.tensor(240, dtype=torch.uint8), torch.tensor(0, dtype=torch.uint8)).expand(*mask.shape, 3)
    ys, xs = torch.nonzero(outline_band(mask, 2), as_tuple=True)
    assert not texture_edge_rays(flat, mask, torch.stack([xs, ys], dim=1), 2, 0.05).any()


def test_the_band_keeps_its_whole_pull_an_edge_gets_none_and_the_rest_the_inside_share():
    on_band = torch.tensor([True, True, False, False])
    on_edge = torch.tensor([True, False, True, False])
    torch.testing.assert_close(weights_gradient_scale(on_band, 0.3, on_edge), torch.tensor([1.0, 1.0, 0.0, 0.3]))
    torch.testing.assert_close(weights_gradient_scale(on_band, 0.3), torch.tensor([1.0, 1.0, 0.3, 0.3]))


def test_bad_windows_and_contrasts_are_refused():
    image, mask = _striped_person()
    pixels = torch.tensor([[3, 4]])
    with pytest.raises(ValueError, match="window 0"):
        texture_edge_rays(image, mask, pixels, 0, 0.2)
    with pytest.raises(ValueError, match=r"\(30, 40, 3\)"):
        texture_edge_rays(image[..., :1], mask, pixels, 1, 0.2)
    for contrast in (0.0, 1.5):
        with pytest.raises(ValueError, match="contrast"):
            texture_edge_rays(image, mask, pixels, 1, contrast)


def test_the_trainer_zeroes_the_edge_rays_off_the_band(small_run):
    """With the option: 1 on the frame's outline band, 0 on a pattern's edge off it, the share elsewhere,
    ray by ray against the plain references; without it, the band's rule alone."""
    from tests.test_train import _trainer

    trainer = _trainer(small_run / "dataset", color_weights_gradient=0.5, color_weights_outline_px=1,
                       color_weights_edge_contrast=0.05)
    seen = []
    for draw in range(4):
        index = draw % len(trainer.data.masks)
        pixels = trainer._draw_pixels(index)
        mask, image = trainer.data.masks[index], trainer.data.images[index]
        band = outline_band(mask, 1)[pixels[:, 1], pixels[:, 0]]
        edge = _edge_reference(image, mask, 1, 0.05)[pixels[:, 1], pixels[:, 0]]
        expected = torch.where(band, 1.0, torch.where(edge, 0.0, 0.5))
        torch.testing.assert_close(trainer._weights_gradient_scale(index, pixels), expected)
        seen.append(expected)
    seen = torch.cat(seen)
    assert (seen == 0).any() and (seen == 1).any()   # the tiny subject's texture has edges off its band


def test_the_edge_option_is_checked_and_needs_the_band(tmp_path):
    from igavatar.errors import InputError
    from stages.train import TrainOptions, resolve_config

    def options(preset="cpu", **extra):
        return TrainOptions(dataset=tmp_path, out=tmp_path / "m", preset=preset, **extra)

    assert resolve_config(options()).color_weights_edge_contrast == 0.0
    assert resolve_config(options(color_weights_edge_contrast=0.2)).color_weights_edge_contrast == 0.2
    with pytest.raises(InputError, match="--color-weights-edge-contrast 1.5"):
        resolve_config(options(color_weights_edge_contrast=1.5))
    with pytest.raises(InputError, match="needs the outline band"):
        resolve_config(options("paper", color_weights_edge_contrast=0.2))
    assert resolve_config(options("paper", color_weights_edge_contrast=0.2,
                                  color_weights_outline_px=2)).color_weights_edge_contrast == 0.2
