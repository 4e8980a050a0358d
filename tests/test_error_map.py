"""The error map steers draws in proportion to its cells, follows the renders' errors and trains
(its exact resume: test_train.test_resume_continues_exactly)."""

from __future__ import annotations


import numpy as np
import torch

from igavatar.training.error_map import ErrorMap
from tests.test_train import _trainer


def _all_pixels(height: int, width: int) -> torch.Tensor:
    ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    return torch.stack((xs.reshape(-1), ys.reshape(-1)), dim=-1)


def test_centres_are_drawn_in_proportion_to_the_cells_errors():
    errors = ErrorMap(2, (64, 64), cell_px=16, floor=0.25)
    cells = torch.full((4, 4), 0.1)
    cells[1, 2], cells[3, 0] = 1.0, 0.5
    errors.cells[1] = cells
    # The subject covers the left 3/4 of the image: cell (3, 3) column has no subject pixels.
    pixels = _all_pixels(64, 64)
    pixels = pixels[pixels[:, 0] < 48]
    centres = errors.draw_centres(1, pixels, 60000, torch.Generator().manual_seed(0))
    drawn = torch.zeros(4, 4).index_put_((centres[:, 1].long() // 16, centres[:, 0].long() // 16),
                                         torch.ones(len(centres)), accumulate=True) / len(centres)
    expected = (cells + 0.25 * cells.mean())
    expected[:, 3] = 0  # no subject pixel there
    expected /= expected.sum()
    assert torch.allclose(drawn, expected, atol=0.006), (drawn, expected)
    assert drawn[1, 2] > 5 * drawn[0, 0]


def test_frames_are_drawn_by_their_mean_error_with_the_given_share():
    errors = ErrorMap(4, (32, 32), cell_px=16)
    errors.cells[:] = torch.tensor([0.1, 0.1, 0.6, 0.2])[:, None, None]
    frames = torch.tensor([0, 2, 3])
    generator = torch.Generator().manual_seed(1)
    for share, expected in ((1.0, [0.1 / 0.9, 0.6 / 0.9, 0.2 / 0.9]), (0.0, [1 / 3] * 3)):
        draws = [errors.draw_frame(frames, generator, share) for _ in range(9000)]
        counts = np.array([draws.count(int(f)) for f in frames]) / len(draws)
        assert np.allclose(counts, expected, atol=0.02), (share, counts)


def test_recorded_errors_move_only_the_cells_they_fell_in():
    errors = ErrorMap(1, (32, 48), cell_px=16, rate=0.3, initial=1.0)
    pixels = torch.tensor([[1, 1], [5, 9], [40, 20]])
    errors.record(0, pixels, torch.tensor([0.2, 0.4, 0.0]))
    assert errors.cells.shape == (1, 2, 3)
    assert torch.isclose(errors.cells[0, 0, 0], torch.tensor(0.7 + 0.3 * 0.3))  # mean 0.3 of its two rays
    assert torch.isclose(errors.cells[0, 1, 2], torch.tensor(0.7))
    assert (errors.cells[0][[0, 0, 1, 1], [1, 2, 0, 1]] == 1.0).all()


def test_steered_training_learns_its_map(small_run):
    """(Exact resume with the map: test_train.test_resume_continues_exactly[error-map].)"""
    trainer = _trainer(small_run / "dataset", steps=4, error_sampling=1.0)
    logs = [trainer.train_step() for _ in range(4)]
    assert all(np.isfinite(log["loss"]) for log in logs)
    assert (trainer.error_map.cells < 1.0).any()  # the renders' errors replaced the initial value
