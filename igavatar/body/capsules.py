"""A shape prior for skeleton-only subjects: a union of capsules around the bones, as a mesh.

    capsules = skeleton_capsules(joints_canonical, skeleton, capsule_radii(skeleton))
    vertices, faces = capsule_mesh(capsules)          # watertight, normals outwards

Each joint's bone segments (igavatar.body.bones) get a capsule of that joint's radius; the union's
signed distance is the minimum over capsules (exact outside, a lower bound on depth inside), and
its zero level set, meshed by marching cubes, stands in for a body model's template: training fits
its SDF to it before the photometric loss takes over, and preprocess sizes the canonical boxes
from it. Radii come from a per-part table for skeletons whose kind is known (SMPL's tree, Anny's
labels: the parts of igavatar.body.motions.SEMANTIC_JOINTS), written for an adult of
NOMINAL_LEG_LENGTH_M legs and scaled by the subject's leg length; joints the table does not name
take the radius of their nearest named ancestor (Anny's fingers that of the hand). A skeleton of
unknown kind gets radii from its size and tree instead (see `_generic_radii`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from igavatar.body.bones import bone_segments, leaf_lengths, leg_scale, skeleton_kind
from igavatar.body.motions import semantic_joint_map
from igavatar.body.skeleton import Skeleton
from igavatar.errors import InputError
from igavatar.geometry.extract import extract_mesh

#: Capsule radius (m, adult scale) around the segments each semantic part's joint moves. Torso
#: capsules are round where a torso is elliptic: they trade a little extra depth for width.
CAPSULE_RADII_M: dict[str, float] = {
    "pelvis": 0.11, "spine_lower": 0.12, "spine_mid": 0.12, "spine_upper": 0.11,
    "neck": 0.055, "head": 0.10,
    "collar": 0.065, "upper_arm": 0.05, "forearm": 0.04, "hand": 0.035,
    "thigh": 0.08, "shin": 0.055, "foot": 0.045,
}
#: Unknown skeletons: radius = size x (GENERIC_BASE + GENERIC_TREE x sqrt(descendants / J)), so
#: joints carrying much of the tree (the trunk) are thicker than the limbs' ends.
GENERIC_BASE, GENERIC_TREE = 0.02, 0.045


def _generic_radii(skeleton: Skeleton) -> np.ndarray:
    """Radii of a skeleton of unknown kind; size = the rest joints' largest extent."""
    size = float((skeleton.rest_joints.max(axis=0) - skeleton.rest_joints.min(axis=0)).max())
    size = size if size > 1e-6 else 1.0
    counts = np.array([len(skeleton.descendants(j)) for j in range(skeleton.num_joints)], dtype=np.float64)
    return size * (GENERIC_BASE + GENERIC_TREE * np.sqrt(counts / skeleton.num_joints))


def capsule_radii(skeleton: Skeleton) -> np.ndarray:
    """(J,) capsule radius in meters of each joint's segments (see the module docstring)."""
    kind = skeleton_kind(skeleton)
    if kind is None:
        return _generic_radii(skeleton)
    named = {}
    for part, joint_name in semantic_joint_map(kind).items():
        key = part.split("_", 1)[1] if part.startswith(("left_", "right_")) else part
        named[skeleton.index(joint_name)] = CAPSULE_RADII_M[key]
    scale = leg_scale(skeleton, kind)
    radii = np.zeros(skeleton.num_joints)
    for j in range(skeleton.num_joints):  # parents precede children: an ancestor is always set
        parent = int(skeleton.parents[j])
        radii[j] = named.get(j, radii[parent] if parent >= 0 else CAPSULE_RADII_M["pelvis"])
    return radii * scale


def _float64(values: torch.Tensor | np.ndarray) -> np.ndarray:
    """A float64 numpy copy of a tensor or array (read-only arrays welcome)."""
    if isinstance(values, torch.Tensor):
        return values.detach().cpu().double().numpy()
    return np.array(values, dtype=np.float64)


@dataclass(frozen=True)
class Capsules:
    """Capsules (float32 tensors): B segments with a radius each, each attached to a joint.

    Attributes:
        joint: (B,) int64, the joint whose transform moves capsule b.
        start, end: (B, 3) segment ends.
        radius: (B,) meters.
    """

    joint: torch.Tensor
    start: torch.Tensor
    end: torch.Tensor
    radius: torch.Tensor

    def sdf(self, points: torch.Tensor) -> torch.Tensor:
        """(P, 3) points -> (P,) signed distance of the union (negative inside), on the points' device."""
        a, axis = self.start.to(points.device), (self.end - self.start).to(points.device)
        offset = points[:, None, :].float() - a[None]  # (P, B, 3)
        t = ((offset * axis).sum(-1) / (axis * axis).sum(-1).clamp_min(1e-12)).clamp(0.0, 1.0)
        distance = (offset - t[..., None] * axis).norm(dim=-1) - self.radius.to(points.device)
        return distance.min(dim=1).values


def skeleton_capsules(joints: torch.Tensor | np.ndarray, skeleton: Skeleton, radii: np.ndarray) -> Capsules:
    """The capsules around a skeleton's bones in the pose of `joints`.

    Args:
        joints: (J, 3) joint positions (e.g. canonical).
        skeleton: the tree.
        radii: (J,) capsule radius of each joint's segments (from capsule_radii), meters.
    Returns:
        Capsules, one per bone segment (a one-joint skeleton: a sphere about its root).
    """
    joints_np = _float64(joints)
    radii = np.asarray(radii, dtype=np.float64)
    if joints_np.shape != (skeleton.num_joints, 3) or radii.shape != (skeleton.num_joints,):
        raise InputError(
            f"capsules: joints {joints_np.shape} and radii {radii.shape}, expected "
            f"({skeleton.num_joints}, 3) and ({skeleton.num_joints},)"
        )
    if not (np.all(np.isfinite(joints_np)) and np.all(np.isfinite(radii)) and np.all(radii > 0)):
        raise InputError("capsules: joints must be finite and radii positive and finite")
    segments = bone_segments(joints_np, skeleton.parents, leaf_lengths(skeleton, skeleton_kind(skeleton)))
    if segments.joint.size == 0:
        joint, start, end, radius = np.zeros(1, np.int64), joints_np[:1], joints_np[:1], radii[:1]
    else:
        joint, start, end, radius = segments.joint, segments.start, segments.end, radii[segments.joint]
    return Capsules(torch.as_tensor(joint), *(torch.as_tensor(v, dtype=torch.float32) for v in (start, end, radius)))


def posed_capsule_boxes(capsules: Capsules, bone_transforms: torch.Tensor) -> torch.Tensor:
    """World bounding boxes of the capsules moved rigidly by their joints' transforms.

    Args:
        capsules: in canonical space.
        bone_transforms: (N, J, 4, 4) canonical -> posed world.
    Returns:
        (N, 2, 3) float32 per-frame [min, max] corners: exact for the capsule union under rigid
        bone motion (skinning blends only between the joints' own positions).
    """
    transforms = bone_transforms[:, capsules.joint].float()  # (N, B, 4, 4)
    ends = []
    for points in (capsules.start, capsules.end):
        ends.append((transforms[..., :3, :3] @ points[None, :, :, None])[..., 0] + transforms[..., :3, 3])
    ends = torch.cat(ends, dim=1)  # (N, 2B, 3)
    radius = torch.cat((capsules.radius, capsules.radius))[None, :, None]
    return torch.stack(((ends - radius).amin(dim=1), (ends + radius).amax(dim=1)), dim=1)


def capsule_mesh(capsules: Capsules, voxel_m: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Mesh of the capsule union by marching cubes (igavatar.geometry.extract).

    Args:
        capsules: from skeleton_capsules.
        voxel_m: edge of the marching-cubes voxels (meters).
    Returns:
        vertices (V, 3) float32 and faces (F, 3) int64: a closed surface (the box leaves a margin
        around every capsule), normals pointing outwards.
    """
    if voxel_m <= 0:
        raise InputError(f"capsule mesh: voxel_m = {voxel_m}, expected > 0")
    ends = torch.cat((capsules.start, capsules.end)).double().numpy()
    margin = float(capsules.radius.max()) + 3 * voxel_m
    box_min, box_max = ends.min(axis=0) - margin, ends.max(axis=0) + margin
    resolution = int(np.ceil((box_max - box_min).max() / voxel_m)) + 1
    return extract_mesh(
        capsules.sdf, box_min, box_max,
        resolution=resolution, coarse_resolution=max(16, resolution // 4), chunk_points=2**14,
    )


@dataclass(frozen=True)
class CapsulePrior:
    """The capsule shape prior of a skeleton-only subject (float32 / int64 CPU tensors).

    Attributes:
        vertices: (V, 3) canonical mesh vertices.
        faces: (F, 3) int64, normals outwards; the mesh is closed.
        posed_boxes: (N, 2, 3) world boxes of the capsules in every frame (unpadded).
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    posed_boxes: torch.Tensor


def capsule_prior(
    skeleton: Skeleton, canonical_joints: torch.Tensor, bone_transforms: torch.Tensor, voxel_m: float = 0.01
) -> CapsulePrior:
    """Capsules around the canonical bones: their mesh, and their boxes in every frame.

    Args:
        skeleton: the tree (radii from capsule_radii).
        canonical_joints: (J, 3) joint positions in the canonical pose.
        bone_transforms: (N, J, 4, 4) canonical -> posed world.
        voxel_m: marching-cubes voxel edge in meters.
    """
    capsules = skeleton_capsules(canonical_joints, skeleton, capsule_radii(skeleton))
    vertices, faces = capsule_mesh(capsules, voxel_m)
    return CapsulePrior(
        vertices=torch.from_numpy(vertices), faces=torch.from_numpy(faces),
        posed_boxes=posed_capsule_boxes(capsules, bone_transforms),
    )
