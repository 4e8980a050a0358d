"""The SMPL body model, read from the user's licensed model file (igavatar never ships one).

    model = load_smpl_model(Path("SMPL_NEUTRAL.pkl"))          # .pkl (chumpy or not) or .npz
    vertices, joints = model.forward(betas, global_orient, body_pose, transl)   # (N, V, 3), (N, 24, 3)

The SMPL function (Loper et al. 2015), computed as smplx's `lbs` does: shaped template
v_shaped = T + S beta; rest joints J = J_regressor v_shaped; pose blend shapes
v_posed = v_shaped + P (R(theta)_{1..23} - I); then linear blend skinning with the forward
kinematics of igavatar.body.skeleton. Our FK's root translation is exactly smplx's `transl`: a point
attached to the root goes to R_root (v - J_root) + J_root + transl. Tensors are float64 torch;
shapes use V vertices, F faces, B shape components, J = 24 joints, leading `...` = frames.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import scipy.sparse
import torch

from igavatar.body.motions import body_to_world
from igavatar.body.rotations import axis_angle_to_matrix
from igavatar.body.skeleton import (
    SMPL_JOINT_NAMES,
    SMPL_PARENTS,
    Skeleton,
    bone_transforms,
    forward_kinematics,
    linear_blend_skinning,
)
from igavatar.body.smpl_file import SMPL_MODEL_FLAG, ChumpyArray, read_smpl_arrays
from igavatar.errors import InputError

SMPL_NUM_JOINTS = len(SMPL_PARENTS)
"""J = 24."""

SMPL_POSE_BASIS = 9 * (SMPL_NUM_JOINTS - 1)
"""207 pose blend shapes: one per entry of the 23 non-root rotation matrices."""

SMPL_REQUIRED_KEYS: tuple[str, ...] = (
    "v_template", "shapedirs", "posedirs", "J_regressor", "weights", "kintree_table", "f",
)

# Skinning-weight rows of a real file sum to 1 up to float32 round-off; further off is a wrong array.
_WEIGHT_SUM_TOLERANCE = 1e-3


class SmplOutput(NamedTuple):
    """A posed SMPL body (float64): vertices (..., V, 3) and joints (..., 24, 3) in world space."""

    vertices: torch.Tensor
    joints: torch.Tensor


def smpl_local_rotations(global_orient: Any, body_pose: Any) -> torch.Tensor:
    """SMPL axis-angle pose -> per-joint rotation matrices relative to the rest (T) pose.

    Args:
        global_orient: (..., 3) root rotation (axis-angle).
        body_pose: (..., 69) the 23 other joints' axis-angles, in SMPL joint order.
    Returns:
        (..., 24, 3, 3) float64 local rotations (igavatar.body.skeleton's convention, which is SMPL's).
    """
    orient = torch.as_tensor(global_orient, dtype=torch.float64)
    pose = torch.as_tensor(body_pose, dtype=torch.float64)
    pose_size = 3 * (SMPL_NUM_JOINTS - 1)
    if orient.shape[-1:] != (3,) or pose.shape[-1:] != (pose_size,) or orient.shape[:-1] != pose.shape[:-1]:
        raise InputError(
            f"SMPL pose: global_orient has shape {tuple(orient.shape)} and body_pose {tuple(pose.shape)}; "
            "expected (..., 3) and (..., 69) with the same leading dimensions"
        )
    rotvecs = torch.cat((orient[..., None, :], pose.unflatten(-1, (SMPL_NUM_JOINTS - 1, 3))), dim=-2)
    return axis_angle_to_matrix(rotvecs)


def smpl_star_pose(leg_spread: float = 0.5) -> torch.Tensor:
    """Local rotations (24, 3, 3) float32 of the canonical "star" (Da-) pose of SMPL.

    SMPL's rest pose is a T-pose with the legs together; as in Fast-SNARF / InstantAvatar each hip
    turns `leg_spread` radians about the body's forward axis (+Z), i.e. body_pose[2] = +0.5 and
    body_pose[5] = -0.5, so the legs do not touch in canonical space. Mirrors Anny's star pose.
    """
    rotvecs = torch.zeros(SMPL_NUM_JOINTS, 3, dtype=torch.float64)
    forward = torch.as_tensor(body_to_world("smpl")[:, 2], dtype=torch.float64)
    # A positive rotation about the forward axis swings a downward limb towards the subject's left (+X).
    rotvecs[SMPL_JOINT_NAMES.index("left_hip")] = leg_spread * forward
    rotvecs[SMPL_JOINT_NAMES.index("right_hip")] = -leg_spread * forward
    return axis_angle_to_matrix(rotvecs).to(torch.float32)


@dataclass(frozen=True, eq=False)
class SmplModel:
    """The arrays of an SMPL model file, checked (float64 CPU tensors).

    Attributes:
        path: the file it was read from.
        gender: 'neutral', 'male' or 'female' when the file or its name says so, else None.
        v_template: (V, 3) mean template in the T-pose, meters, +Y up, facing +Z.
        shapedirs: (V, 3, B) shape blend shapes.
        posedirs: (207, V * 3) pose blend shapes (smplx's layout: pose feature @ posedirs).
        joint_regressor: (24, V) rest joints = joint_regressor @ shaped vertices.
        weights: (V, 24) skinning weights, rows sum to 1.
        faces: (F, 3) int64 triangle indices.
    """

    path: Path
    gender: str | None
    v_template: torch.Tensor
    shapedirs: torch.Tensor
    posedirs: torch.Tensor
    joint_regressor: torch.Tensor
    weights: torch.Tensor
    faces: torch.Tensor

    @property
    def num_vertices(self) -> int:
        """V."""
        return int(self.v_template.shape[0])

    @property
    def num_betas(self) -> int:
        """B, the number of shape components in the file (10 or 300)."""
        return int(self.shapedirs.shape[-1])

    def _betas(self, betas: Any) -> torch.Tensor:
        values = torch.as_tensor(betas, dtype=torch.float64)
        if values.ndim != 1 or values.shape[0] > self.num_betas:
            raise InputError(
                f"SMPL betas have shape {tuple(values.shape)}, expected (B,) with B <= {self.num_betas} "
                f"(the shape components in {self.path.name})"
            )
        return values

    def shaped_vertices(self, betas: Any) -> torch.Tensor:
        """Template with shape blend shapes, T-pose: betas (B',) with B' <= B -> (V, 3)."""
        values = self._betas(betas)
        return self.v_template + self.shapedirs[..., : values.shape[0]] @ values

    def rest_shape(self, betas: Any) -> tuple[torch.Tensor, torch.Tensor]:
        """Shaped T-pose body: betas (B',) -> (vertices (V, 3), joints (24, 3))."""
        vertices = self.shaped_vertices(betas)
        return vertices, self.joint_regressor @ vertices

    def skeleton(self, betas: Any) -> Skeleton:
        """The 24-joint SMPL skeleton with the rest joints of this body shape."""
        _, joints = self.rest_shape(betas)
        return Skeleton(np.asarray(SMPL_PARENTS), joints.numpy(), SMPL_JOINT_NAMES)

    def forward(
        self,
        betas: Any,
        global_orient: Any,
        body_pose: Any,
        transl: Any | None = None,
        pose_blend_shapes: bool = True,
    ) -> SmplOutput:
        """The SMPL function: one body shape, any number of poses.

        Args:
            betas: (B',) shape coefficients, B' <= B.
            global_orient: (..., 3) root axis-angle.
            body_pose: (..., 69) axis-angles of joints 1..23.
            transl: (..., 3) world translation (smplx's `transl`), or None for zero.
            pose_blend_shapes: add the pose-dependent corrective offsets (SMPL does; the canonical
                template of an avatar does not).
        Returns:
            SmplOutput: vertices (..., V, 3) and joints (..., 24, 3), float64.
        """
        rotations = smpl_local_rotations(global_orient, body_pose)
        vertices, rest_joints = self.rest_shape(betas)
        if pose_blend_shapes:
            eye = torch.eye(3, dtype=torch.float64)
            feature = (rotations[..., 1:, :, :] - eye).flatten(-3)  # (..., 207), smplx's order
            vertices = vertices + (feature @ self.posedirs).unflatten(-1, (self.num_vertices, 3))
        translation = None if transl is None else torch.as_tensor(transl, dtype=torch.float64)
        global_posed = forward_kinematics(rotations, rest_joints, SMPL_PARENTS, translation)
        identity = torch.eye(3, dtype=torch.float64).expand(SMPL_NUM_JOINTS, 3, 3)
        global_rest = forward_kinematics(identity, rest_joints, SMPL_PARENTS)
        posed = linear_blend_skinning(vertices, self.weights, bone_transforms(global_posed, global_rest))
        return SmplOutput(vertices=posed, joints=global_posed[..., :3, 3])


def _fail(path: Path, message: str) -> InputError:
    return InputError(
        f"{path}: {message}; is {SMPL_MODEL_FLAG} an SMPL model file (SMPL_NEUTRAL/MALE/FEMALE .pkl or .npz)?"
    )


def _numeric(path: Path, raw: dict[str, Any], key: str) -> np.ndarray:
    value = raw[key]
    if isinstance(value, ChumpyArray):  # a chumpy expression: raises, naming the key
        value = value.to_array(f"{path}: key '{key}'")
    if scipy.sparse.issparse(value):
        value = value.toarray()  # the official J_regressor is a scipy sparse matrix
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise _fail(path, f"key '{key}' is a {type(value).__name__}, not a numeric array") from None
    if not np.all(np.isfinite(array)):
        raise _fail(path, f"key '{key}' contains NaN or infinite values")
    return array


def _shape_error(path: Path, key: str, array: np.ndarray, expected: str) -> InputError:
    return _fail(path, f"key '{key}' has shape {tuple(array.shape)}, expected {expected}")


def _gender(raw: dict[str, Any], path: Path) -> str | None:
    """'neutral'/'male'/'female' from a 'gender' entry, else from the usual file names
    (SMPL_FEMALE.pkl, basicModel_f_lbs_10_207_0_v1.0.0.pkl, ...)."""
    words = set(re.split(r"[^a-z]+", path.stem.lower()))
    value = raw.get("gender")
    if isinstance(value, (str, np.ndarray)) and np.asarray(value).shape == ():
        words = {str(np.asarray(value)).lower()}
    for gender, names in (("neutral", {"neutral"}), ("female", {"female", "f"}), ("male", {"male", "m"})):
        if words & names:
            return gender
    return None


def smpl_model_from_arrays(raw: dict[str, Any], path: Path) -> SmplModel:
    """Check the SMPL arrays of `raw` (key -> array) and build the model; errors name `path`."""
    missing = [key for key in SMPL_REQUIRED_KEYS if key not in raw]
    if missing:
        found = ", ".join(sorted(raw)[:10]) or "nothing"
        raise _fail(path, f"missing key(s) {', '.join(repr(k) for k in missing)} (it holds: {found})")
    v_template = _numeric(path, raw, "v_template")
    if v_template.ndim != 2 or v_template.shape[1] != 3 or v_template.shape[0] == 0:
        raise _shape_error(path, "v_template", v_template, "(V, 3)")
    num_vertices = v_template.shape[0]
    shapedirs = _numeric(path, raw, "shapedirs")
    if shapedirs.ndim != 3 or shapedirs.shape[:2] != (num_vertices, 3) or shapedirs.shape[2] == 0:
        raise _shape_error(path, "shapedirs", shapedirs, f"({num_vertices}, 3, B)")
    posedirs = _numeric(path, raw, "posedirs")
    if posedirs.shape not in ((num_vertices, 3, SMPL_POSE_BASIS), (num_vertices * 3, SMPL_POSE_BASIS)):
        raise _shape_error(path, "posedirs", posedirs, f"({num_vertices}, 3, {SMPL_POSE_BASIS})")
    regressor = _numeric(path, raw, "J_regressor")
    if regressor.shape != (SMPL_NUM_JOINTS, num_vertices):
        expected = f"({SMPL_NUM_JOINTS}, {num_vertices}) (24 SMPL joints; SMPL-H/SMPL-X files have more)"
        raise _shape_error(path, "J_regressor", regressor, expected)
    weights = _numeric(path, raw, "weights")
    if weights.shape != (num_vertices, SMPL_NUM_JOINTS):
        raise _shape_error(path, "weights", weights, f"({num_vertices}, {SMPL_NUM_JOINTS})")
    worst = float(np.abs(weights.sum(axis=1) - 1.0).max())
    if worst > _WEIGHT_SUM_TOLERANCE or weights.min() < -_WEIGHT_SUM_TOLERANCE:
        raise _fail(
            path,
            f"key 'weights' is not a partition of unity "
            f"(rows sum to 1 within {worst:.3g}, min {weights.min():.3g})",
        )

    kintree = _numeric(path, raw, "kintree_table")
    if kintree.shape != (2, SMPL_NUM_JOINTS):
        raise _shape_error(path, "kintree_table", kintree, f"(2, {SMPL_NUM_JOINTS})")
    # The root's parent is stored as -1 or as uint32 -1 (4294967295); only the others are checked.
    parents = kintree[0, 1:].astype(np.int64)
    if not np.array_equal(parents, SMPL_PARENTS[1:]) or not np.array_equal(kintree[1], np.arange(SMPL_NUM_JOINTS)):
        raise _fail(
            path,
            f"key 'kintree_table' is not SMPL's kinematic tree "
            f"(parents {parents.tolist()}, expected {list(SMPL_PARENTS[1:])})",
        )

    faces = _numeric(path, raw, "f")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise _shape_error(path, "f", faces, "(F, 3)")
    if np.any(faces != np.round(faces)) or faces.min(initial=0) < 0 or faces.max(initial=0) >= num_vertices:
        raise _fail(path, f"key 'f' must hold vertex indices in [0, {num_vertices - 1}]")

    def tensor(array: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(array, dtype=np.float64))

    return SmplModel(
        path=path,
        gender=_gender(raw, path),
        v_template=tensor(v_template),
        shapedirs=tensor(shapedirs),
        posedirs=tensor(posedirs.reshape(num_vertices * 3, SMPL_POSE_BASIS).T),
        joint_regressor=tensor(regressor),
        weights=tensor(weights),
        faces=torch.from_numpy(faces.astype(np.int64)),
    )


def load_smpl_model(path: Path) -> SmplModel:
    """Read and check an SMPL model file (.pkl with or without chumpy arrays, or .npz).

    Raises:
        InputError: naming the file and the missing key or wrong shape, and the --smpl-model flag.
    """
    path = Path(path)
    return smpl_model_from_arrays(read_smpl_arrays(path), path)


def require_smpl_model(path: Path | None, needed_by: str) -> Path:
    """`path` if it names an existing file; otherwise an InputError saying that `needed_by` (e.g. a
    capture's poses.npz) holds SMPL parameters and needs the user's SMPL model file."""
    if path is None:
        raise InputError(
            f"{needed_by}: holds SMPL body parameters (betas, body_pose), which need the SMPL model file: "
            f"pass {SMPL_MODEL_FLAG} PATH (or set IGAVATAR_SMPL_MODEL) to your licensed SMPL_NEUTRAL/MALE/FEMALE "
            ".pkl or .npz from smpl.is.tue.mpg.de (igavatar never ships or downloads it)"
        )
    path = Path(path)
    if not path.is_file():
        read_smpl_arrays(path)  # raises the InputError that says what is there instead
    return path
