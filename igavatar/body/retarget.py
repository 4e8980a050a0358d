"""Retarget a pose sequence from one skeleton kind to another by semantic joint names.

    rotations, translation = retarget_sequence(smpl_rotvecs, smpl_transl, anny_skeleton, "smpl", "anny")
    # rotations (N, J, 3, 3) local to Anny's rest pose, translation (N, 3): forward_kinematics inputs

Both skeletons follow SMPL's convention (rest frames world-aligned, locals relative to the rest
pose; see igavatar.body.skeleton), and igavatar.body.motions names the same body parts in both
(pelvis, spine, neck, head, collars, arms, hands, legs, feet) and says where each kind's left, up
and forward axes point (`body_to_world`). Retargeting transfers the *world orientation* of each
named part:

1. The source's global rotation of every named part, R_src, is re-expressed in the target's world
   axes: A R_src A^T with A = body_to_world(target) @ body_to_world(source)^T.
2. Rest-pose correction: the two rest poses differ (SMPL stands in a T-pose, Anny in an A-pose),
   so each part is first turned, by C, from the target's rest direction of its bone (the part's
   joint to the next named joint down the chain) onto the source's rest direction of that bone
   (the shortest rotation). The target part's global rotation is A R_src A^T C: its bone points
   where the source's bone points. Hands take their forearm's correction (the wrist stays
   straight); the pelvis, head and feet take none, so the root's facing, the gaze and the soles
   follow the source's exactly.
3. Target joints that no part names (Anny's twist bones, fingers, toes, ...) keep their rest
   rotation relative to their parent; named joints get local = G_parent^T G_joint.
4. The root translation is the source's, in meters, turned into the target's world axes: the root
   makes the same displacements (its absolute position is the target's rest root plus it).

Pose files do not say which way their world is up (AIST++ is +Y up like SMPL, AMASS +Z up,
PeopleSnapshot's camera frame -Y up), so `retarget_sequence` first turns the source world by
`upright_rotation`: the quarter or half turn that brings the world axis nearest to the pelvis'
mean up direction onto the source kind's up. The motion is unchanged up to that rotation of the
whole world (root path included); a sequence already upright is left as it is.

So an identity SMPL pose puts an Anny avatar in SMPL's T-pose (arms level, not Anny's A-pose rest),
since that is the pose the motion describes. Bone lengths are the target's own. SMPL files carry
no rest joints, so the source rest directions come from NOMINAL_SMPL_REST_JOINTS (a hand-typed
T-pose, not the licensed model's).
"""

from __future__ import annotations

import numpy as np
import torch

from igavatar.body.motions import body_to_world, semantic_joint_map
from igavatar.body.rotations import axis_angle_to_matrix
from igavatar.body.skeleton import NOMINAL_SMPL_REST_JOINTS, SMPL_JOINT_NAMES, SMPL_PARENTS, Skeleton
from igavatar.errors import InputError, NotAvailableError


#: Each part's bone for the rest-pose correction: part -> the next named part down its chain.
BONE_END: dict[str, str] = {
    "spine_lower": "spine_mid", "spine_mid": "spine_upper", "spine_upper": "neck", "neck": "head",
} | {
    f"{side}_{part}": f"{side}_{end}"
    for side in ("left", "right")
    for part, end in (("collar", "upper_arm"), ("upper_arm", "forearm"), ("forearm", "hand"),
                      ("thigh", "shin"), ("shin", "foot"))
}
#: Parts without a bone end that borrow another part's correction (the wrist stays straight).
BORROWED_CORRECTION: dict[str, str] = {"left_hand": "left_forearm", "right_hand": "right_forearm"}

#: (source kind, target kind) pairs retarget_sequence supports.
RETARGETS: tuple[tuple[str, str], ...] = (("smpl", "anny"),)


def nominal_smpl_skeleton() -> Skeleton:
    """SMPL's tree with NOMINAL_SMPL_REST_JOINTS (for sequences that carry no rest joints)."""
    return Skeleton(np.array(SMPL_PARENTS), NOMINAL_SMPL_REST_JOINTS, SMPL_JOINT_NAMES)


def shortest_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of least angle taking direction `a` (3,) onto direction `b` (3,)."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    cosine = float(np.dot(a, b))
    if cosine < -1.0 + 1e-9:  # opposite: a half turn about any axis perpendicular to a
        helper = np.eye(3)[int(np.argmin(np.abs(a)))]
        perpendicular = np.cross(a, helper)
        perpendicular /= np.linalg.norm(perpendicular)
        return 2.0 * np.outer(perpendicular, perpendicular) - np.eye(3)
    skew = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + skew + skew @ skew / (1.0 + cosine)


def _global_rotations(local: torch.Tensor, parents: np.ndarray) -> torch.Tensor:
    """(N, J, 3, 3) global rotations from local ones (parents precede children)."""
    out = [local[:, 0]]
    for j in range(1, local.shape[1]):
        out.append(out[int(parents[j])] @ local[:, j])
    return torch.stack(out, dim=1)


def _rest_corrections(source: Skeleton, source_kind: str, target: Skeleton, target_kind: str,
                      to_target: np.ndarray) -> dict[str, np.ndarray]:
    """part -> (3, 3) correction C turning the target's rest bone onto the source's (target axes)."""
    source_names, target_names = semantic_joint_map(source_kind), semantic_joint_map(target_kind)

    def direction(skeleton: Skeleton, names, part: str) -> np.ndarray:
        start, end = skeleton.index(names[part]), skeleton.index(names[BONE_END[part]])
        return skeleton.rest_joints[end] - skeleton.rest_joints[start]

    corrections = {}
    for part in BONE_END:
        source_dir = to_target @ direction(source, source_names, part)
        target_dir = direction(target, target_names, part)
        if np.linalg.norm(source_dir) < 1e-9 or np.linalg.norm(target_dir) < 1e-9:
            raise InputError(
                f"retarget: the rest bone of '{part}' has zero length in the "
                f"{'source' if np.linalg.norm(source_dir) < 1e-9 else 'target'} skeleton"
            )
        corrections[part] = shortest_rotation(target_dir, source_dir)
    for part, lender in BORROWED_CORRECTION.items():
        corrections[part] = corrections[lender]
    return corrections


def retarget_rotations(
    source_rotations: torch.Tensor,
    source_translation: torch.Tensor,
    source: Skeleton,
    source_kind: str,
    target: Skeleton,
    target_kind: str,
    uncorrected: frozenset[str] = frozenset(),
) -> tuple[torch.Tensor, torch.Tensor]:
    """Local rotations and root translation for `target` that reproduce a `source` pose sequence.

    Args:
        source_rotations: (N, Js, 3, 3) local rotations relative to the source's rest pose.
        source_translation: (N, 3) source root translation (meters, source world axes).
        source, target: the two skeletons (rest joints and names; the kinds' joint names).
        source_kind, target_kind: skeleton kinds of igavatar.body.motions ('smpl', 'anny').
        uncorrected: parts that take no rest-pose correction (they keep the target's rest
            direction relative to the source's rotation), e.g. the spine when the two rigs run it
            through the body differently.
    Returns:
        local_rotations (N, Jt, 3, 3) and root_translation (N, 3), float64, for forward_kinematics
        with `target` (see the module docstring for what is transferred).
    Raises:
        InputError: a skeleton lacks a joint its kind's part map names, or shapes disagree.
    """
    rotations = torch.as_tensor(source_rotations, dtype=torch.float64)
    translation = torch.as_tensor(source_translation, dtype=torch.float64)
    if rotations.ndim != 4 or rotations.shape[1:] != (source.num_joints, 3, 3):
        raise InputError(
            f"retarget: source rotations have shape {tuple(rotations.shape)}, expected (N, {source.num_joints}, 3, 3)"
        )
    if translation.shape != (rotations.shape[0], 3):
        raise InputError(f"retarget: source translation has shape {tuple(translation.shape)}, expected ({rotations.shape[0]}, 3)")
    for role, skeleton, kind in (("source", source, source_kind), ("target", target, target_kind)):
        missing = [name for name in semantic_joint_map(kind).values() if name not in skeleton.joint_names]
        if missing:
            raise InputError(
                f"retarget: the {role} skeleton lacks {len(missing)} of the {kind} joints that name body parts "
                f"(e.g. {', '.join(missing[:3])}); is it really a {kind} skeleton?"
            )
    to_target = body_to_world(target_kind) @ body_to_world(source_kind).T
    axes = torch.as_tensor(to_target)
    corrections = _rest_corrections(source, source_kind, target, target_kind, to_target)
    source_names, target_names = semantic_joint_map(source_kind), semantic_joint_map(target_kind)

    source_global = _global_rotations(rotations, source.parents)
    wanted: dict[int, torch.Tensor] = {}
    for part, source_name in source_names.items():
        in_target = axes @ source_global[:, source.index(source_name)] @ axes.T
        correction = torch.as_tensor(np.eye(3) if part in uncorrected else corrections.get(part, np.eye(3)))
        wanted[target.index(target_names[part])] = in_target @ correction

    n_frames = rotations.shape[0]
    identity = torch.eye(3, dtype=torch.float64).expand(n_frames, 3, 3)
    target_global: list[torch.Tensor] = []
    local = []
    for j in range(target.num_joints):
        parent = int(target.parents[j])
        parent_global = identity if parent < 0 else target_global[parent]
        if j in wanted:
            target_global.append(wanted[j])
            local.append(parent_global.transpose(-1, -2) @ wanted[j])
        else:  # follows its parent rigidly
            target_global.append(parent_global)
            local.append(identity)
    return torch.stack(local, dim=1), translation @ axes.T


def upright_rotation(root_rotations: torch.Tensor, kind: str) -> np.ndarray:
    """(3, 3) world rotation, a multiple of 90 degrees, that makes a sequence stand upright.

    Args:
        root_rotations: (N, 3, 3) global rotations of the root (pelvis) in the sequence's world.
        kind: the skeleton kind, whose body_to_world gives its rest up axis.
    Returns:
        the rotation taking the world axis (+-X, +-Y, +-Z) nearest to the pelvis' mean up direction
        onto `kind`'s up axis (identity when they already agree).
    """
    up = body_to_world(kind)[:, 1]
    mean_up = (torch.as_tensor(root_rotations, dtype=torch.float64) @ torch.as_tensor(up)).mean(dim=0).numpy()
    axis = int(np.argmax(np.abs(mean_up)))
    world_up = np.zeros(3)
    world_up[axis] = 1.0 if mean_up[axis] >= 0 else -1.0
    if np.allclose(world_up, up):
        return np.eye(3)
    if np.allclose(world_up, -up):
        # Half turn about the body's left axis: up and forward flip, left stays left.
        left = body_to_world(kind)[:, 0]
        return 2.0 * np.outer(left, left) - np.eye(3)
    return shortest_rotation(world_up, up)


def retarget_sequence(
    rotvecs: np.ndarray, transl: np.ndarray, target: Skeleton, source_kind: str, target_kind: str,
    source: Skeleton | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """`retarget_rotations` for an axis-angle sequence (N, Js, 3) + translation (N, 3).

    `source` defaults to the nominal SMPL skeleton for SMPL sequences (pose files carry no rest
    joints). The source world is first turned upright (`upright_rotation`). Raises
    NotAvailableError for a pair of kinds outside RETARGETS, naming both.
    """
    if (source_kind, target_kind) not in RETARGETS:
        supported = ", ".join(f"{s} -> {t}" for s, t in RETARGETS)
        raise NotAvailableError(
            f"no retarget from {source_kind} skeletons to {target_kind} skeletons (supported: {supported})"
        )
    if source is None:
        source = nominal_smpl_skeleton()
    rotations = axis_angle_to_matrix(torch.as_tensor(np.asarray(rotvecs), dtype=torch.float64))
    translation = torch.as_tensor(np.asarray(transl), dtype=torch.float64)
    if rotations.ndim == 4 and rotations.shape[0] > 0:
        upright = torch.as_tensor(upright_rotation(rotations[:, 0], source_kind))
        rotations = torch.cat((upright @ rotations[:, :1], rotations[:, 1:]), dim=1)
        translation = translation @ upright.T
    return retarget_rotations(rotations, translation, source, source_kind, target, target_kind)
