"""Anny fitted to a bare skeleton: a naked body for captures that give joints but no body model.

    fit = fit_anny_to_skeleton(load_anny(), skeleton, "smpl")
    fit.vertices (V, 3), fit.faces (F, 3), fit.weights (V, J)   # in the skeleton's rest pose
    fit.phenotype, fit.joint_rms_m, fit.joint_max_m              # what was fitted, how well

A bare skeleton (HumanNeRF / ZJU-MoCap's SMPL joints without the licensed SMPL file, a capture
that writes its joints only) says where the bones are but not where the body ends. Silhouettes
cannot say it either where every training frame closes the body (arms against the torso, thighs
together): the masks' visual hull keeps webs there, which stretch in new poses. Anny, the free
body model igavatar already ships, knows what fills those places. This module fits it to the
skeleton and returns its mesh posed into the skeleton's rest pose, with Anny's skinning weights
moved onto the skeleton's joints, so that the capture can be treated like a body-model capture.

What is fitted, and what is not:
- **Proportions from the joints.** The phenotype values that move Anny's joints (gender, age,
  height, proportions) are fitted by least squares. For a skeleton with Anny's own bones, to every
  joint's position relative to the root; for another kind (SMPL's tree), to the lengths of the
  limb bones both kinds name (thigh, shin, upper arm, forearm), the trunk and the shoulder width,
  since the two rigs place their other joints differently inside the body.
- **Not the girth.** Joints barely depend on Anny's `weight` and `muscle` (a joint moves well
  under a millimetre across their range), and under clothes the masks do not tell a heavier body
  from looser clothes either (measured on the synthetic subjects: a body heavier by a third of
  the range still fits inside every mask). Both stay at Anny's average, 0.5: training takes the
  surface to the masks from there, and the trainer's body-inside term checks the template
  against the masks before it trusts it (igavatar.training.body_prior).
- **Pose.** Anny's limb bones are turned onto the skeleton's rest bone directions
  (igavatar.body.retarget's rest-pose correction) while its torso stands as in Anny's rest pose;
  a skeleton with Anny's bones needs no turn.

Weights: each Anny bone hands its weight to the skeleton joint of the same name, else to the joint
of its nearest ancestor that names a body part (twist bones to their limb, fingers to the wrist,
toes to the ankle, the spine's in-between bones to the spine joint below them).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from igavatar.body.anny_body import ANNY_PHENOTYPE_DEFAULTS, AnnyBody
from igavatar.body.motions import body_to_world, semantic_joint_map
from igavatar.body.retarget import retarget_rotations
from igavatar.body.skeleton import Skeleton, forward_kinematics
from igavatar.errors import InputError

if TYPE_CHECKING:
    import anny

__all__ = ["AnnyFit", "FITTED_PHENOTYPES", "fit_anny_to_skeleton", "anny_bone_targets"]

#: Phenotype values fitted to the joints; the others (weight, muscle: the girth) stay at Anny's average.
FITTED_PHENOTYPES: tuple[str, ...] = ("gender", "age", "height", "proportions")
#: (part, part) pairs whose distances a cross-rig fit matches: the limb bones, the trunk (neck to
#: hips) and the shoulder width. Left out: the spine's inner joints, the collars and the hip width,
#: which the rigs place differently (igavatar's nominal SMPL skeleton has its hips 12 cm apart and
#: 9 cm below its pelvis joint, Anny its 20 cm apart at its root's height).
_CROSS_RIG_PAIRS: tuple[tuple[str, str], ...] = tuple(
    (f"{side}_{a}", f"{side}_{b}")
    for side in ("left", "right")
    for a, b in (("upper_arm", "forearm"), ("forearm", "hand"), ("thigh", "shin"), ("shin", "foot"))
) + (("neck", "left_thigh"), ("neck", "right_thigh"), ("left_upper_arm", "right_upper_arm"))
#: Body parts whose joints a cross-rig fit puts on the skeleton's (the translation and the rebinding):
#: the limbs, the neck and the head. The pelvis, spine and collar joints are conventions of each rig
#: (SMPL's first spine joint sits 12 cm above its pelvis joint, Anny's at its root): pulling Anny's
#: onto SMPL's would tear the torso, so the torso keeps Anny's shape and the limbs move.
_REBOUND_PARTS: tuple[str, ...] = ("neck", "head") + tuple(
    f"{side}_{part}" for side in ("left", "right") for part in ("upper_arm", "forearm", "hand", "thigh", "shin", "foot")
)
#: Parts a cross-rig fit leaves in Anny's rest pose: the torso stands as Anny's does, since the rigs
#: run the spine through the body differently (turning Anny's spine bones onto SMPL's bent its torso
#: forward by several centimetres at the shoulders); the limbs turn onto the skeleton's.
_TORSO_PARTS = frozenset({"pelvis", "spine_lower", "spine_mid", "spine_upper", "neck", "head"})
#: L-BFGS rounds of up to 100 iterations each (the fit converges in two on the synthetic subjects).
_LBFGS_ROUNDS = 3


@dataclass(frozen=True)
class AnnyFit:
    """Anny fitted to a skeleton, in that skeleton's rest pose and world axes (float32 / int64 CPU).

    Attributes:
        vertices: (V, 3) the naked body in the skeleton's rest pose.
        faces: (F, 3) triangles.
        weights: (V, J) skinning weights over the skeleton's J joints (rows sum to 1).
        phenotype: Anny's phenotype used (fitted values and the averages kept).
        joint_rms_m, joint_max_m: distance (meters) between the skeleton's joints and Anny's joints
            of the same name (or body part) after the fit and the best common translation, before
            the rebinding that closes it: how well Anny's build matches the bones.
        joints_compared: how many joints those distances are over.
        same_rig: True when the skeleton has Anny's own bones (fitted joint by joint, not posed).
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    weights: torch.Tensor
    phenotype: dict[str, float]
    joint_rms_m: float
    joint_max_m: float
    joints_compared: int
    same_rig: bool

    def description(self) -> dict:
        """JSON-able facts for the dataset manifest."""
        return {
            "model": "anny",
            "phenotype": {k: round(v, 4) for k, v in self.phenotype.items()},
            "fitted": list(FITTED_PHENOTYPES),
            "girth": "Anny's average (weight 0.5, muscle 0.5), not fitted",
            "joint_rms_mm": round(1000.0 * self.joint_rms_m, 2),
            "joint_max_mm": round(1000.0 * self.joint_max_m, 2),
            "joints_compared": self.joints_compared,
        }


def anny_bone_targets(anny_skeleton: Skeleton, skeleton: Skeleton, kind: str) -> np.ndarray:
    """(104,) the skeleton joint each Anny bone's weight goes to.

    A bone whose label the skeleton has goes to that joint; any other to the joint of its nearest
    ancestor that names a body part of igavatar.body.motions (Anny's root names the pelvis, so
    every chain ends at a part).
    """
    anny_parts = {name: part for part, name in semantic_joint_map("anny").items()}
    kind_names = semantic_joint_map(kind)
    names = set(skeleton.joint_names)
    targets = np.full(anny_skeleton.num_joints, -1, np.int64)
    for b, label in enumerate(anny_skeleton.joint_names):
        if label in names:
            targets[b] = skeleton.index(label)
            continue
        k = b
        while anny_skeleton.joint_names[k] not in anny_parts:
            k = int(anny_skeleton.parents[k])
        targets[b] = skeleton.index(kind_names[anny_parts[anny_skeleton.joint_names[k]]])
    return targets


def _fit_phenotype(model: "anny.Anny", loss_of_heads) -> dict[str, float]:
    """Phenotype minimising `loss_of_heads((104, 3) rest bone heads)` over FITTED_PHENOTYPES."""
    logits = torch.zeros(len(FITTED_PHENOTYPES), dtype=torch.float64, requires_grad=True)

    def phenotype(values: torch.Tensor) -> dict[str, torch.Tensor]:
        # tanh keeps every value inside Anny's [0, 1] without a projection step.
        fitted = {k: (0.5 + 0.5 * torch.tanh(values[i]))[None] for i, k in enumerate(FITTED_PHENOTYPES)}
        kept = {k: torch.tensor([v], dtype=torch.float64) for k, v in ANNY_PHENOTYPE_DEFAULTS.items() if k not in fitted}
        return fitted | kept

    optimizer = torch.optim.LBFGS([logits], lr=1.0, max_iter=100, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        optimizer.zero_grad()
        heads = model(pose_parameters=None, phenotype_kwargs=phenotype(logits))["rest_bone_heads"][0]
        loss = loss_of_heads(heads.to(torch.float64))
        loss.backward()
        return loss

    for _ in range(_LBFGS_ROUNDS):
        optimizer.step(closure)
    return {k: float(v) for k, v in phenotype(logits.detach()).items()}


def fit_anny_to_skeleton(model: "anny.Anny", skeleton: Skeleton, kind: str) -> AnnyFit:
    """Fit Anny to a bare skeleton of a known kind (see the module docstring).

    Args:
        model: Anny (igavatar.body.anny_body.load_anny).
        skeleton: the bare skeleton, rest joints in meters in its rest pose.
        kind: its kind ('anny' or 'smpl', igavatar.body.bones.skeleton_kind).
    Returns:
        AnnyFit in the skeleton's rest pose.
    Raises:
        InputError: the skeleton lacks a joint its kind names.
    """
    kind_names = semantic_joint_map(kind)
    missing = [name for name in kind_names.values() if name not in skeleton.joint_names]
    if missing:
        raise InputError(f"body fit: the skeleton lacks the {kind} joints {', '.join(missing[:4])}")
    anny_labels = tuple(model.bone_labels)
    same_rig = set(anny_labels) <= set(skeleton.joint_names)
    rest = torch.tensor(skeleton.rest_joints, dtype=torch.float64)

    if same_rig:
        target = rest[[skeleton.index(label) for label in anny_labels]]
        target = target - target[0]

        def loss(heads: torch.Tensor) -> torch.Tensor:
            return ((heads - heads[0] - target) ** 2).sum(-1).mean()
    else:
        anny_names = semantic_joint_map("anny")
        anny_index = [(anny_labels.index(anny_names[a]), anny_labels.index(anny_names[b])) for a, b in _CROSS_RIG_PAIRS]
        lengths = torch.stack([
            (rest[skeleton.index(kind_names[b])] - rest[skeleton.index(kind_names[a])]).norm()
            for a, b in _CROSS_RIG_PAIRS
        ])

        def loss(heads: torch.Tensor) -> torch.Tensor:
            anny_lengths = torch.stack([(heads[b] - heads[a]).norm() for a, b in anny_index])
            return ((anny_lengths - lengths) ** 2).mean()

    return _posed_fit(AnnyBody(model, _fit_phenotype(model, loss)), skeleton, kind, same_rig)


def _posed_fit(body: AnnyBody, skeleton: Skeleton, kind: str, same_rig: bool) -> AnnyFit:
    """The fitted body turned into the skeleton's rest pose and rebound onto its joints, weights mapped.

    Rebinding: after the best common translation, each compared joint j of Anny still lies d_j
    from the skeleton's; every vertex moves by sum_j w_vj d_j (its own weights), so each limb
    lands on the skeleton's bone and the surface stays smooth where the weights blend. For a
    skeleton with Anny's bones the d_j are the fit's sub-millimetre residual; across rigs they are
    the rigs' different joint conventions (SMPL's hips sit lower and closer together than Anny's).
    """
    anny = body.skeleton
    if same_rig:
        rotations = torch.eye(3, dtype=torch.float64).expand(1, anny.num_joints, 3, 3)
        to_skeleton = np.eye(3)
        pairs = [(b, skeleton.index(label)) for b, label in enumerate(anny.joint_names)]
    else:
        identity = torch.eye(3, dtype=torch.float64).expand(1, skeleton.num_joints, 3, 3)
        rotations, _ = retarget_rotations(identity, torch.zeros(1, 3, dtype=torch.float64), skeleton, kind, anny, "anny",
                                          uncorrected=_TORSO_PARTS)
        # Column vectors: x_anny = A x_skeleton with A = body_to_world(anny) body_to_world(kind)^T.
        to_skeleton = (body_to_world("anny") @ body_to_world(kind).T).T
        anny_names, kind_names = semantic_joint_map("anny"), semantic_joint_map(kind)
        pairs = [(anny.index(anny_names[part]), skeleton.index(kind_names[part])) for part in _REBOUND_PARTS]
    with torch.no_grad():
        vertices = body.posed_vertices(rotations)[0].numpy() @ to_skeleton.T
        joints = forward_kinematics(rotations, anny.rest_joints, anny.parents)[0, :, :3, 3].numpy() @ to_skeleton.T
    anny_index, skeleton_index = [a for a, _ in pairs], [s for _, s in pairs]
    # The translation that best puts Anny's joints on the skeleton's (least squares: the mean offset).
    shift = (skeleton.rest_joints[skeleton_index] - joints[anny_index]).mean(axis=0)
    residual = np.zeros((skeleton.num_joints, 3))
    residual[skeleton_index] = skeleton.rest_joints[skeleton_index] - (joints[anny_index] + shift)
    distance = np.linalg.norm(residual[skeleton_index], axis=1)

    targets = anny_bone_targets(anny, skeleton, kind)
    weights = torch.zeros(body.skinning_weights.shape[0], skeleton.num_joints, dtype=torch.float64)
    weights.index_add_(1, torch.as_tensor(targets), body.skinning_weights.to(torch.float64))
    weights /= weights.sum(1, keepdim=True)
    rebound = vertices + shift + weights.numpy() @ residual
    return AnnyFit(
        vertices=torch.as_tensor(rebound, dtype=torch.float32),
        faces=body.faces.clone(),
        weights=weights.to(torch.float32),
        phenotype=dict(body.phenotype),
        joint_rms_m=float(np.sqrt(np.mean(distance**2))),
        joint_max_m=float(distance.max()),
        joints_compared=len(pairs),
        same_rig=same_rig,
    )
