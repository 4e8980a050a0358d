"""Which training frames are neighbours in time, read from their names, and the posed joints'
acceleration over them: the temporal term of the training poses' fit to the masks.

    triplets = time_triplets(["frame_000000", "frame_000001", "frame_000003"])
    triplets.middle            # (M,) positions, in the list given, of frames with a neighbour on each side
    acceleration = triplets.acceleration(joints_world)   # (M, K, 3) m per source frame^2

A silhouette pins a body in the image plane but hardly in depth: after the fit to the masks, the
joints of poses with 5 degrees of noise a joint were still 2-3 cm off, most of it along the view
(tests/benchmarks/results/pose-noise-temporal.md). A pose estimator's errors differ from frame to
frame while the person moves smoothly, so the acceleration of the posed joints between neighbouring
frames says what the masks cannot.

Time is the frame number in each name (its trailing digits): the video path, ZJU-MoCap,
PeopleSnapshot and the captures igavatar writes name frames by their index in the source. Frames
whose names share the text before the number belong to one clip ("test_walk_0003" and
"test_squat_0003" do not). The acceleration is per source frame squared, so a clip sampled every
6th frame (ZJU-MoCap's training frames) gets 1/36 of the step's second difference and, squared in
the term, almost no smoothing: between samples that far apart the estimate's error cannot be told
from the person's motion. Frames without a number in their name get no term, nor do neighbours
whose estimated root turns by more than MAX_ROOT_TURN_DEG a step.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import torch

from igavatar.body.rotations import matrix_to_axis_angle

_NUMBERED = re.compile(r"^(.*?)(\d+)$")
#: Neighbours whose estimated root turns by more than this are not a video's neighbouring frames
#: (a 360-degree turn in a few frames, 90 degrees a step): a smooth path through them is not the
#: person's. A 60-frame turn steps 6 degrees, plus an estimate's few degrees of noise.
MAX_ROOT_TURN_DEG = 20.0


@dataclass(frozen=True)
class TimeTriplets:
    """Frames with a neighbour on each side in the same clip, as positions in the list given.

    Attributes:
        previous, middle, following: (M,) long.
        gap_before, gap_after: (M,) float64 source frames between the middle frame and each neighbour.
    """

    previous: torch.Tensor
    middle: torch.Tensor
    following: torch.Tensor
    gap_before: torch.Tensor
    gap_after: torch.Tensor

    def __len__(self) -> int:
        return int(self.middle.numel())

    def acceleration(self, points: torch.Tensor) -> torch.Tensor:
        """(M, ..., 3) second divided difference of points (T, ..., 3) at the middle frames, in
        units of points per source frame squared (an even step g: (p[t-g] - 2 p[t] + p[t+g]) / g^2)."""
        a, b = self.gap_before.to(points.dtype), self.gap_after.to(points.dtype)
        shape = (-1,) + (1,) * (points.dim() - 1)
        slope_after = (points[self.following] - points[self.middle]) / b.view(shape)
        slope_before = (points[self.middle] - points[self.previous]) / a.view(shape)
        return 2.0 * (slope_after - slope_before) / (a + b).view(shape)

    def subset(self, keep: torch.Tensor) -> "TimeTriplets":
        """The triplets where keep (M,) bool is true."""
        return TimeTriplets(self.previous[keep], self.middle[keep], self.following[keep], self.gap_before[keep],
                            self.gap_after[keep])


def frame_time(name: str) -> tuple[str, int] | None:
    """(clip, frame number) of a frame's name, or None if it ends in no number."""
    match = _NUMBERED.match(str(name))
    return None if match is None else (match.group(1), int(match.group(2)))


def time_triplets(frame_names: list[str], root_rotations: torch.Tensor | None = None) -> TimeTriplets:
    """The triplets of neighbouring frames of each clip among `frame_names` (any order).

    Args:
        root_rotations: (T, 3, 3) the frames' estimated root orientations, or None: a triplet whose
            root turns by more than MAX_ROOT_TURN_DEG a step is left out (frames far apart in time).
    """
    clips: dict[str, list[tuple[int, int]]] = {}
    for position, name in enumerate(frame_names):
        time = frame_time(name)
        if time is not None:
            clips.setdefault(time[0], []).append((time[1], position))
    rows = []
    for frames in clips.values():
        frames.sort()
        for (t0, p0), (t1, p1), (t2, p2) in zip(frames, frames[1:], frames[2:]):
            if t0 < t1 < t2:  # a repeated number is no time step
                rows.append((p0, p1, p2, t1 - t0, t2 - t1))
    table = torch.tensor(rows, dtype=torch.float64).reshape(-1, 5)
    positions = table[:, :3].long()
    triplets = TimeTriplets(positions[:, 0], positions[:, 1], positions[:, 2], table[:, 3], table[:, 4])
    if root_rotations is None or len(triplets) == 0:
        return triplets
    turns = torch.stack((root_turn_deg(root_rotations, triplets.previous, triplets.middle),
                         root_turn_deg(root_rotations, triplets.middle, triplets.following))).amax(0)
    return triplets.subset(turns <= MAX_ROOT_TURN_DEG)


def root_turn_deg(rotations: torch.Tensor, first: torch.Tensor, second: torch.Tensor) -> torch.Tensor:
    """(M,) angle in degrees between rotations (T, 3, 3) at positions first and second (M,)."""
    relative = rotations[first].double().transpose(-1, -2) @ rotations[second].double()
    return torch.rad2deg(matrix_to_axis_angle(relative).norm(dim=-1))
