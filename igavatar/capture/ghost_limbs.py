"""Ghost limbs of a canonical visual hull: cells that skinning lands inside another limb.

    bones = PosedBones.from_skeleton(skeleton, joints_canonical, bone_transforms)
    votes = misplaced_votes(points_canonical, weights, skin, frames, bones)   # (P,) int32 views
    hull_cells(..., ghost_test=GhostTest(bones, weights_fn))                  # igavatar.capture.visual_hull
    ghost = votes > 0.5 * len(frames)

With the legs spread in canonical space and together in every training frame, the canonical
space beside each leg (between the legs) rides with that leg and lands exactly inside the other
leg: inside every mask, so no silhouette carves it, and LBS moves it almost rigidly, so the
crushed-space rule of igavatar.capture.visual_hull does not see it either. The hull then keeps a
second pair of legs, and training keeps them, since they render nowhere the real legs do not.

The skeleton tells them apart. A point moves with the joints that weigh on it ("its own"); near
the body, its own bones are (nearly) the closest ones in canonical space. The ghost keeps its
distance to its own bones (it moves rigidly with them), ~30 cm, but in the posed frame it lies
a few centimeters from another limb's bone: its own bones are far farther than the nearest
bone. A real point keeps its own bones (nearly) the closest in every pose. The test is that
excess, posed minus canonical, above a margin that a real body does not reach: a heavy torso's
flank against an arm hanging at its side reaches ~0.1-0.15 m (measured below 0.15 in a squat).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from igavatar.body.bones import BoneSegments, bone_segments, leaf_lengths, skeleton_kind
from igavatar.body.skeleton import Skeleton

#: How much farther (meters) than in canonical space a point's own bones may lie, beyond the
#: nearest bone, before the point counts as landed inside another limb in that frame.
GHOST_MARGIN_M = 0.15
#: A joint is one of a point's own when it carries at least this weight there (or the most).
MIN_OWN_WEIGHT = 0.2

#: (frame index, (P, 3) canonical points) -> (P, 3) world points of that frame.
SkinFn = Callable[[int, torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class PosedBones:
    """A skeleton's bone segments in canonical space and each frame's joint transforms.

    Attributes:
        joint: (B,) int64 joint that moves segment b.
        start, end: (B, 3) float32 canonical segment ends.
        bone_transforms: (N, J, 4, 4) float32 canonical -> posed world, per frame.
    """

    joint: torch.Tensor
    start: torch.Tensor
    end: torch.Tensor
    bone_transforms: torch.Tensor

    @property
    def num_joints(self) -> int:
        return int(self.bone_transforms.shape[1])

    @classmethod
    def from_skeleton(cls, skeleton: Skeleton, joints_canonical: torch.Tensor | np.ndarray,
                      bone_transforms: torch.Tensor) -> PosedBones:
        """Segments as igavatar.body.bones makes them (one per joint-child pair, leaves extended)."""
        joints = np.asarray(torch.as_tensor(joints_canonical).detach().cpu().double())
        segments: BoneSegments = bone_segments(joints, skeleton.parents, leaf_lengths(skeleton, skeleton_kind(skeleton)))
        return cls(
            joint=torch.from_numpy(segments.joint),
            start=torch.from_numpy(segments.start).float(),
            end=torch.from_numpy(segments.end).float(),
            bone_transforms=torch.as_tensor(bone_transforms).detach().cpu().float(),
        )

    def segments_in_frame(self, frame: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, 3) starts and ends moved rigidly by their joint's transform in `frame`."""
        transforms = self.bone_transforms[frame][self.joint]  # (B, 4, 4)
        rotation, translation = transforms[:, :3, :3], transforms[:, :3, 3]
        move = lambda p: torch.einsum("bij,bj->bi", rotation, p) + translation  # noqa: E731
        return move(self.start), move(self.end)


@dataclass(frozen=True)
class GhostTest:
    """What the ghost-limb rule of `visual_hull.hull_prior_mesh` needs.

    Attributes:
        bones: segments and per-frame transforms (indexed by the views' frame numbers).
        weights: (P, 3) canonical points -> (P, J) the skinning weights that `skin` blends.
    """

    bones: PosedBones
    weights: Callable[[torch.Tensor], torch.Tensor]


def joint_distances(points: torch.Tensor, start: torch.Tensor, end: torch.Tensor, joint: torch.Tensor,
                    num_joints: int) -> torch.Tensor:
    """(P, J) distance from each point to each joint's nearest segment (inf: a joint with none).

    Args:
        points: (P, 3); start, end: (B, 3) segments; joint: (B,) their joints.
    """
    axis = end - start  # (B, 3)
    length2 = (axis * axis).sum(-1).clamp_min(1e-18)
    offset = points[:, None, :] - start[None]  # (P, B, 3)
    t = ((offset * axis[None]).sum(-1) / length2).clamp(0.0, 1.0)
    distance = (offset - t[..., None] * axis[None]).norm(dim=-1)  # (P, B)
    out = torch.full((points.shape[0], num_joints), float("inf"), dtype=distance.dtype)
    return out.scatter_reduce(1, joint.expand(points.shape[0], -1), distance, reduce="amin")


def _own_excess(distances: torch.Tensor, own: torch.Tensor) -> torch.Tensor:
    """(P,) how much farther a point's nearest own bone is than its nearest bone (>= 0)."""
    nearest_own = torch.where(own, distances, torch.full_like(distances, float("inf"))).amin(1)
    return nearest_own - distances.amin(1)


@torch.no_grad()
def misplaced_votes(
    points_canonical: torch.Tensor,
    weights: torch.Tensor,
    skin: SkinFn,
    frames: Sequence[int],
    bones: PosedBones,
    margin_m: float = GHOST_MARGIN_M,
    min_own_weight: float = MIN_OWN_WEIGHT,
    chunk_size: int = 16384,
) -> torch.Tensor:
    """Count, for every canonical point, the frames in which skinning lands it inside another limb.

    Args:
        points_canonical: (P, 3) canonical points (CPU).
        weights: (P, J) their skinning weights (those `skin` blends).
        skin: forward skinning into a frame's world space.
        frames: the frames to test (indices into `bones.bone_transforms` and for `skin`).
        bones: the skeleton's segments and transforms.
        margin_m: see GHOST_MARGIN_M; min_own_weight: see MIN_OWN_WEIGHT.
        chunk_size: points at once (the (P, B, 3) intermediates stay ~30 MB for 150 segments).
    Returns:
        (P,) int32 frames in which the point's own bones lie more than `margin_m` farther, beyond
        the nearest bone, than they do in canonical space. All zero for a lone root.
    """
    count = points_canonical.shape[0]
    votes = torch.zeros(count, dtype=torch.int32)
    if bones.num_joints < 2 or count == 0:
        return votes
    points = points_canonical.float()
    weights = weights.float()
    own = weights >= torch.clamp(weights.amax(1, keepdim=True), max=min_own_weight)
    excess_canonical = torch.cat([
        _own_excess(joint_distances(points[i : i + chunk_size], bones.start, bones.end, bones.joint, bones.num_joints),
                    own[i : i + chunk_size])
        for i in range(0, count, chunk_size)
    ])
    for frame in frames:
        start, end = bones.segments_in_frame(int(frame))
        for i in range(0, count, chunk_size):
            posed = skin(int(frame), points[i : i + chunk_size]).float().cpu()
            distances = joint_distances(posed, start, end, bones.joint, bones.num_joints)
            excess = _own_excess(distances, own[i : i + chunk_size])
            votes[i : i + chunk_size] += (excess - excess_canonical[i : i + chunk_size] > margin_m).int()
    return votes
