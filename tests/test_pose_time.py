"""Which training frames are neighbours in time (igavatar.training.pose_time): read from the names'
frame numbers, clip by clip, with the gaps kept; the acceleration is exact on a quadratic path; and
neighbours whose root turns fast are left out."""

from __future__ import annotations

import math

import pytest
import torch

from igavatar.training.pose_time import MAX_ROOT_TURN_DEG, frame_time, time_triplets


def _rows(triplets) -> list[tuple[int, int, int, float, float]]:
    return sorted(zip(triplets.previous.tolist(), triplets.middle.tolist(), triplets.following.tolist(),
                      triplets.gap_before.tolist(), triplets.gap_after.tolist()))


def test_neighbours_come_from_the_frame_numbers_in_any_order():
    """A held-out frame leaves a gap of 2; the names given out of order still pair by number."""
    names = ["frame_000004", "frame_000000", "frame_000003", "frame_000001"]
    # in time: 000000 (pos 1), 000001 (pos 3), 000003 (pos 2), 000004 (pos 0)
    assert _rows(time_triplets(names)) == [(1, 3, 2, 1.0, 2.0), (3, 2, 0, 2.0, 1.0)]


def test_clips_apart_and_names_without_numbers_get_no_neighbours():
    names = ["test_walk_0000", "test_walk_0001", "test_walk_0002", "test_squat_0003", "test_squat_0004",
             "front", "side", "back"]
    assert _rows(time_triplets(names)) == [(0, 1, 2, 1.0, 1.0)]
    assert frame_time("test_squat_0004") == ("test_squat_", 4) and frame_time("front") is None
    assert len(time_triplets(["a_1", "a_1", "a_1"])) == 0  # a repeated number is no time step
    assert len(time_triplets([])) == 0


def test_the_acceleration_is_exact_on_a_quadratic_path_with_uneven_gaps():
    """p(t) = c + v t + a t^2 has acceleration 2a per frame squared, however the frames are spaced,
    and a straight path at constant speed none."""
    times = [0, 1, 3, 4, 9]
    names = [f"frame_{t:06d}" for t in times]
    t = torch.tensor(times, dtype=torch.float64)[:, None, None]
    a = torch.tensor([[0.01, -0.02, 0.005], [0.0, 0.03, 0.0]], dtype=torch.float64)  # (K=2, 3)
    v = torch.tensor([[0.1, 0.0, -0.2], [0.05, 0.05, 0.05]], dtype=torch.float64)
    triplets = time_triplets(names)
    assert len(triplets) == 3
    quadratic = 1.0 + v * t + a * t**2  # (T, K, 3)
    torch.testing.assert_close(triplets.acceleration(quadratic), (2 * a).expand(3, 2, 3))
    assert float(triplets.acceleration(1.0 + v * t).abs().max()) < 1e-12


def _turns(step_deg: float, frames: int) -> torch.Tensor:
    """(frames, 3, 3) rotations about the vertical by step_deg a frame."""
    angles = torch.arange(frames, dtype=torch.float64) * math.radians(step_deg)
    rotations = torch.zeros(frames, 3, 3, dtype=torch.float64)
    rotations[:, 0, 0], rotations[:, 0, 2] = angles.cos(), angles.sin()
    rotations[:, 2, 0], rotations[:, 2, 2] = -angles.sin(), angles.cos()
    rotations[:, 1, 1] = 1.0
    return rotations


@pytest.mark.parametrize("step_deg, kept", [(6.0, 3), (MAX_ROOT_TURN_DEG - 1.0, 3), (90.0, 0)])
def test_neighbours_whose_root_turns_fast_are_left_out(step_deg, kept):
    """A 60-frame turn (6 degrees a step) is a clip; a turn in 4 frames (90 degrees) is not."""
    names = [f"frame_{i:06d}" for i in range(5)]
    assert len(time_triplets(names, _turns(step_deg, 5))) == kept
