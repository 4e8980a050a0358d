"""Frames between refined training frames of one clip take their neighbours' pose corrections.

    carried = carry_corrections(refined_names, refined_roots, rotation, translation, names, roots)
    carried.positions          # which of `names` get a correction
    transforms = apply_corrections(bone_transforms[carried.positions], subject, joints, carried)

`train --refine-poses` corrects the training frames' poses; a held-out frame of the same video
keeps its estimate. The video fit's errors are smooth in time (it fits the clip with a smoothness
term), so a held-out frame's error is close to its neighbours' and the model's corrections of the
frames before and after it, interpolated in time, are a better estimate of its pose than the raw
one. No held-out image is used: this is not test-time refinement (eval --refine-test-poses).

Time and clip come from the frame names as in igavatar.training.pose_time. A frame gets a correction
when the clip holds a refined frame on each side no more than MAX_SPAN_STEPS of the clip's usual
spacing apart (linear weights), or one within one spacing at an end of the clip; a neighbour whose
estimated root has turned by more than MAX_ROOT_TURN_DEG from the frame's is not used.
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass

import numpy as np
import torch

from igavatar.training.pose_refine import PoseRefiner
from igavatar.training.pose_time import MAX_ROOT_TURN_DEG, frame_time, root_turn_deg

#: A frame between two refined frames more than this many of the clip's usual steps apart keeps its pose.
MAX_SPAN_STEPS = 2.0


@dataclass(frozen=True)
class CarriedCorrections:
    """Corrections for M of the frames asked about.

    Attributes:
        positions: (M,) positions in the list of names given.
        rotation: (M, K, 3) axis-angle corrections of the refined joints; translation: (M, 3) root, meters.
        neighbours: M tuples of the refined frames' names used (one or two).
    """

    positions: list[int]
    rotation: torch.Tensor
    translation: torch.Tensor
    neighbours: list[tuple[str, ...]]

    def __len__(self) -> int:
        return len(self.positions)


def _clips(names: list[str]) -> dict[str, list[tuple[int, int]]]:
    """clip -> sorted (frame number, position) of the names that carry one."""
    clips: dict[str, list[tuple[int, int]]] = {}
    for position, name in enumerate(names):
        time = frame_time(name)
        if time is not None:
            clips.setdefault(time[0], []).append((time[1], position))
    for frames in clips.values():
        frames.sort()
    return clips


def _spacing(frames: list[tuple[int, int]]) -> float:
    steps = [b[0] - a[0] for a, b in zip(frames, frames[1:]) if b[0] > a[0]]
    return float(statistics.median(steps)) if steps else 1.0


def _neighbour_weights(time: int, frames: list[tuple[int, int]], spacing: float) -> list[tuple[int, float]]:
    """(refined position, weight) pairs for a frame at `time` among a clip's refined `frames`; [] for none."""
    before = [f for f in frames if f[0] < time]
    after = [f for f in frames if f[0] > time]
    if before and after:
        (t0, p0), (t1, p1) = before[-1], after[0]
        if t1 - t0 > MAX_SPAN_STEPS * spacing:
            return []  # a gap in the clip's refined frames: nothing to interpolate between
        return [(p0, (t1 - time) / (t1 - t0)), (p1, (time - t0) / (t1 - t0))]
    end = before[-1:] or after[:1]
    if end and abs(end[0][0] - time) <= spacing:
        return [(end[0][1], 1.0)]
    return []


def carry_corrections(refined_names: list[str], refined_roots: torch.Tensor, rotation: torch.Tensor,
                      translation: torch.Tensor, names: list[str], roots: torch.Tensor) -> CarriedCorrections:
    """The corrections that the frames `names` take from the refined frames of their clips.

    Args:
        refined_names: T names of the refined frames; refined_roots: (T, 3, 3) their root rotations.
        rotation: (T, K, 3) and translation: (T, 3) their corrections.
        names: N names of the frames to correct (a refined frame among them is left out: it has its own);
            roots: (N, 3, 3) their estimated root rotations.
    """
    clips = _clips(list(refined_names))
    spacings = {clip: _spacing(frames) for clip, frames in clips.items()}
    refined = set(refined_names)
    positions, rotations, translations, neighbours = [], [], [], []
    for position, name in enumerate(names):
        time = frame_time(name)
        if name in refined or time is None or time[0] not in clips:
            continue
        pairs = _neighbour_weights(time[1], clips[time[0]], spacings[time[0]])
        if not pairs:
            continue
        sources = torch.tensor([p for p, _ in pairs])
        turns = root_turn_deg(torch.cat((roots[position:position + 1].double(), refined_roots[sources].double())),
                          torch.zeros(len(pairs), dtype=torch.long), torch.arange(1, len(pairs) + 1))
        if bool((turns > MAX_ROOT_TURN_DEG).any()):
            continue
        weights = torch.tensor([w for _, w in pairs], dtype=rotation.dtype)
        positions.append(position)
        rotations.append((weights[:, None, None] * rotation[sources]).sum(0))
        translations.append((weights[:, None] * translation[sources]).sum(0))
        neighbours.append(tuple(refined_names[p] for p, _ in pairs))
    k = rotation.shape[1]
    return CarriedCorrections(positions, torch.stack(rotations) if rotations else rotation.new_zeros((0, k, 3)),
                              torch.stack(translations) if translations else translation.new_zeros((0, 3)), neighbours)


def apply_corrections(bone_transforms: torch.Tensor, parents: np.ndarray, rest_joints: np.ndarray,
                      canonical_rotations: np.ndarray, joints: np.ndarray, rotation: torch.Tensor,
                      translation: torch.Tensor) -> torch.Tensor:
    """(M, J, 4, 4) float32 transforms of M frames (M, J, 4, 4) with their corrections applied as
    training applies them (igavatar.training.pose_refine): rotation (M, K, 3) of `joints` (K,), translation (M, 3)."""
    frames = torch.arange(int(bone_transforms.shape[0]))
    refiner = PoseRefiner(bone_transforms, parents, rest_joints, canonical_rotations, frames, joints)
    with torch.no_grad():
        refiner.rotation.copy_(rotation)
        refiner.translation.copy_(translation)
    return refiner.all_bone_transforms().float()
