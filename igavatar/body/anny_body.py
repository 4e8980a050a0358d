"""Adapter from the Anny body model (PyPI `anny`) to igavatar's skeleton + LBS conventions.

    body = AnnyBody.load(phenotype={"height": 0.7}, on_status=print_status)
    rotations, root_translation = body.local_rotations_from_pose_parameters(pose_parameters)

What Anny's pose parameters mean (read from anny 0.6.2, `utils/kinematics.py::forward_kinematic`,
default "local-ref" parameterization, "cached" bone orientations): with rest bone poses
P_c = [R_c | h_c] (h_c the bone head), fixed reference orientations U_c and the deltas
[D_c | d_c] = pose_parameters[..., c, :, :], define A_c = U_c R_c^T (the rotation from a bone's rest
to its reference orientation; phenotype dependent, A_root = I). Then Anny's world-aligned joint
frames G'_c = W_c [R_c^T | 0] obey

    G'_root = [D_root | d_root],   G'_c = G'_p [A_p^T D_c A_c | h_c - h_p + A_p^T d_c],

and its skinning transforms are T_c = G'_c [I | -h_c]. This is exactly igavatar's
forward_kinematics (rest joints = rest bone heads h) with local rotations L_c = A_p^T D_c A_c,
L_root = D_root and root translation t = d_root - h_root, followed by plain linear blend skinning of
the rest vertices; only per-bone translations d_c (c != root) have no counterpart and are rejected.
Note that Anny's identity pose parameters are its *reference* pose (root head at the origin, bones
at U), a few degrees from the rest mesh; igavatar's identity rotations are the rest mesh itself.

Anny skins with linear blend skinning ("warp_lbs" by default, a sparse kernel); this adapter builds
the model with `skinning_method="lbs"` (dense LBS, pure torch, no Warp/CUDA kernel compile), which
is the same function.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from igavatar.body.rotations import axis_angle_to_matrix, rigid_matrix
from igavatar.body.skeleton import Skeleton, forward_kinematics, linear_blend_skinning
from igavatar.errors import BodyModelError, InputError

if TYPE_CHECKING:
    import anny

ANNY_BONE_COUNT = 104
"""J of Anny's default full-body rig."""

ANNY_PHENOTYPE_DEFAULTS: Mapping[str, float] = MappingProxyType(
    {"gender": 0.5, "age": 0.5, "muscle": 0.5, "weight": 0.5, "height": 0.5, "proportions": 0.5}
)
"""Anny's default phenotype labels and their neutral values; every value lies in [0, 1]."""

ANNY_PHENOTYPE_LABELS: tuple[str, ...] = tuple(ANNY_PHENOTYPE_DEFAULTS)

# Per-bone translations below this (meters) count as zero: files written in float32 carry noise.
_TRANSLATION_TOLERANCE = 1e-5
# Rotation blocks further than this from orthonormal (max |D^T D - I|) are not rotations.
_ORTHONORMAL_TOLERANCE = 1e-3

# Bones the canonical star pose rotates, and the body's forward axis in Anny's frame
# (+Z up, the face looks towards -Y, the subject's left is +X).
_ANNY_FORWARD = (0.0, -1.0, 0.0)
_LEFT_HIP, _RIGHT_HIP = "upperleg01.L", "upperleg01.R"


def _import_anny() -> Any:
    try:
        import anny
        import anny.paths
    except ImportError as error:
        raise BodyModelError(
            "the Anny body model needs the Python package 'anny' (pip install anny==0.6.2); "
            f"importing it failed: {error}"
        ) from error
    return anny


def resolve_anny_cache_dir(cache_dir: Path | None = None) -> Path:
    """The Anny cache directory to use: `cache_dir`, else $ANNY_CACHE_DIR, else ~/.cache/anny."""
    if cache_dir is not None:
        return Path(cache_dir).expanduser()
    env = os.environ.get("ANNY_CACHE_DIR")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "anny"


def anny_cache_is_built(cache_dir: Path | None = None) -> bool:
    """Whether Anny's compact model cache exists in `cache_dir` (see resolve_anny_cache_dir)."""
    directory = resolve_anny_cache_dir(cache_dir)
    try:
        from anny.models.model_data import CURRENT_DATA_VERSION

        pattern = f"v{CURRENT_DATA_VERSION}/build_compact_model_data_*.safetensors"
    except ImportError:
        pattern = "v*/build_compact_model_data_*.safetensors"
    return any(directory.glob(pattern))


def load_anny(
    cache_dir: Path | None = None, on_status: Callable[[str], None] | None = None
) -> "anny.Anny":
    """Load Anny's default full-body model (float64, CPU, dense LBS, "local-ref" poses).

    Args:
        cache_dir: Anny's cache directory (default $ANNY_CACHE_DIR or ~/.cache/anny). The first
            load builds a ~790 MB cache there in about a minute; later loads take well under 1 s.
        on_status: called with a one-line message before a slow first-run build.
    Returns:
        the `anny.Anny` torch module.
    Raises:
        BodyModelError: anny is not installed, or the model cannot be built or loaded.
    """
    anny = _import_anny()
    directory = resolve_anny_cache_dir(cache_dir)
    # Anny reads ANNY_CACHE_DIR once at import; set it through its API so that this call wins.
    anny.paths.set_anny_cache_path(directory)
    if on_status is not None and not anny_cache_is_built(directory):
        on_status(f"building Anny body-model cache in {directory} (first run, ~1 min)")
    try:
        model = anny.Anny(skinning_method="lbs", pose_parameterization="local-ref")
    except Exception as error:  # anny raises OSError, ValueError, RuntimeError, ... on bad caches
        raise BodyModelError(
            f"could not build or load the Anny body model with cache directory {directory}: "
            f"{type(error).__name__}: {error}. Check that the directory is writable, or delete it "
            "to rebuild the cache."
        ) from error
    if len(model.bone_labels) != ANNY_BONE_COUNT:
        raise BodyModelError(
            f"Anny model has {len(model.bone_labels)} bones, expected {ANNY_BONE_COUNT}; "
            "igavatar supports anny==0.6.2's default full-body rig"
        )
    if tuple(model.phenotype_labels) != ANNY_PHENOTYPE_LABELS:
        raise BodyModelError(
            f"Anny phenotype labels are {list(model.phenotype_labels)}, expected "
            f"{list(ANNY_PHENOTYPE_LABELS)}; igavatar supports anny==0.6.2"
        )
    return model


def resolve_phenotype(phenotype: Mapping[str, float] | None) -> dict[str, float]:
    """A full phenotype: the defaults overridden by `phenotype`; InputError on unknown labels or
    values outside [0, 1]."""
    resolved = dict(ANNY_PHENOTYPE_DEFAULTS)
    for label, value in (phenotype or {}).items():
        if label not in ANNY_PHENOTYPE_DEFAULTS:
            raise InputError(
                f"unknown Anny phenotype label {label!r}; valid labels: {', '.join(ANNY_PHENOTYPE_LABELS)}"
            )
        number = float(value)
        if not (0.0 <= number <= 1.0):
            raise InputError(f"Anny phenotype {label!r} = {number}, expected a value in [0, 1]")
        resolved[label] = number
    return resolved


class AnnyBody:
    """One Anny subject (a phenotype) in igavatar's conventions, with the loaded model cached.

    Attributes (CPU tensors):
        phenotype: the full phenotype (label -> value in [0, 1]).
        rest_vertices: (V, 3) float32 rest (A-pose, identity-rotation) vertices in meters.
        faces: (F, 3) int64 triangles (Anny's quads split).
        skinning_weights: (V, J) float32 dense weights, rows sum to 1.
        skeleton: Skeleton with Anny's bone parents, rest bone heads and bone labels (J = 104).
    """

    def __init__(self, model: "anny.Anny", phenotype: Mapping[str, float] | None = None) -> None:
        """Evaluate `model` (from load_anny) at `phenotype` (missing labels take the defaults)."""
        if getattr(model, "pose_parameterization", None) != "local-ref":
            raise BodyModelError(
                "AnnyBody needs an Anny model with pose_parameterization='local-ref' (use load_anny)"
            )
        self.model = model
        self.phenotype = resolve_phenotype(phenotype)
        with torch.no_grad():
            output = model(pose_parameters=None, phenotype_kwargs=self.phenotype)
        # Everything kept here lives on the CPU in float64; methods move it to their inputs' device.
        rest = {key: value.detach().cpu() for key, value in output.items()}
        rest_poses = rest["rest_bone_poses"][0].to(torch.float64)  # (J, 4, 4)
        rest_heads = rest["rest_bone_heads"][0].to(torch.float64)  # (J, 3)
        self._rest_vertices64 = rest["rest_vertices"][0].to(torch.float64)
        num_vertices, num_bones = self._rest_vertices64.shape[0], len(model.bone_labels)
        weights = torch.zeros(num_vertices, num_bones, dtype=torch.float64)
        weights.scatter_add_(
            1, model.vertex_bone_indices.long().cpu(), model.vertex_bone_weights.to(torch.float64).cpu()
        )
        self._weights64 = weights

        rest_rotations = rest_poses[:, :3, :3]
        reference = model.reference_bone_orientations
        if reference is None:
            self._reference_from_rest = torch.eye(3, dtype=torch.float64).expand(num_bones, 3, 3).clone()
        else:
            self._reference_from_rest = reference.to(torch.float64).cpu() @ rest_rotations.transpose(-1, -2)
        root_error = (self._reference_from_rest[0] - torch.eye(3, dtype=torch.float64)).abs().max()
        if root_error > 1e-9:
            # Anny then rotates the root's skin and its children's offsets differently, which no
            # skeleton with one transform per joint can reproduce.
            raise BodyModelError(
                f"Anny root bone's rest orientation differs from its reference orientation "
                f"(max entry difference {float(root_error):.3g}); unsupported Anny rig"
            )
        self._rest_heads64 = rest_heads
        self._mesh_cache: dict[tuple[torch.dtype, str], tuple[torch.Tensor, ...]] = {}
        self._parents = torch.tensor([0] + list(model.bone_parents[1:]), dtype=torch.long)

        self.rest_vertices = self._rest_vertices64.to(torch.float32)
        self.faces = model.get_triangular_faces().to(torch.int64).cpu()
        self.skinning_weights = weights.to(torch.float32)
        self.skeleton = Skeleton(
            parents=np.asarray(model.bone_parents, dtype=np.int64),
            rest_joints=rest_heads.numpy(),
            joint_names=tuple(model.bone_labels),
        )

    @classmethod
    def load(
        cls,
        phenotype: Mapping[str, float] | None = None,
        *,
        cache_dir: Path | None = None,
        on_status: Callable[[str], None] | None = None,
    ) -> "AnnyBody":
        """load_anny(cache_dir, on_status) then AnnyBody(model, phenotype)."""
        return cls(load_anny(cache_dir, on_status), phenotype)

    def with_phenotype(self, phenotype: Mapping[str, float] | None) -> "AnnyBody":
        """Another subject sharing this object's loaded model (no reload)."""
        return AnnyBody(self.model, phenotype)

    @property
    def phenotype_labels(self) -> tuple[str, ...]:
        """Anny's phenotype labels, in its order."""
        return ANNY_PHENOTYPE_LABELS

    @property
    def phenotype_values(self) -> np.ndarray:
        """(P,) float64 phenotype values in phenotype_labels order (as capture files store them)."""
        return np.array([self.phenotype[label] for label in ANNY_PHENOTYPE_LABELS], dtype=np.float64)

    def _conversion_tensors(self, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A (J,3,3), A of each bone's parent (J,3,3) (identity for the root), heads (J,3); on
        `like`'s dtype and device."""
        a = self._reference_from_rest.to(dtype=like.dtype, device=like.device)
        a_parent = a[self._parents.to(like.device)]
        a_parent = torch.cat((torch.eye(3, dtype=like.dtype, device=like.device)[None], a_parent[1:]))
        heads = self._rest_heads64.to(dtype=like.dtype, device=like.device)
        return a, a_parent, heads

    def local_rotations_from_pose_parameters(
        self, pose_parameters: torch.Tensor | np.ndarray
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """igavatar local rotations and root translation of Anny "local-ref" pose parameters.

        Args:
            pose_parameters: (..., 104, 4, 4) Anny deltas; entry 0 is the global pose; the other
                bones' translations must be zero.
        Returns:
            local_rotations (..., 104, 3, 3) relative to this subject's rest pose (world-aligned
            rest frames), and root_translation (..., 3), in the input's float dtype (float32 for
            numpy/int input), such that forward_kinematics + linear_blend_skinning of
            rest_vertices reproduce Anny's forward.
        """
        deltas = torch.as_tensor(pose_parameters)
        if not deltas.is_floating_point():
            deltas = deltas.to(torch.float32)
        num_bones = self.skeleton.num_joints
        if deltas.ndim < 3 or deltas.shape[-3:] != (num_bones, 4, 4):
            raise InputError(
                f"Anny pose_parameters has shape {tuple(deltas.shape)}, expected (N, {num_bones}, 4, 4)"
            )
        if not torch.isfinite(deltas).all():
            raise InputError("Anny pose_parameters contains NaN or infinite values")
        rotations, translations = deltas[..., :3, :3], deltas[..., :3, 3]
        eye = torch.eye(3, dtype=deltas.dtype, device=deltas.device)
        orthonormal_error = (rotations.transpose(-1, -2) @ rotations - eye).abs().amax()
        if orthonormal_error > _ORTHONORMAL_TOLERANCE:
            raise InputError(
                "Anny pose_parameters: the 3x3 blocks are not rotations "
                f"(max |R^T R - I| = {float(orthonormal_error):.3g})"
            )
        if num_bones > 1:
            bone_translation = translations[..., 1:, :].norm(dim=-1)
            worst = float(bone_translation.max())
            if worst > _TRANSLATION_TOLERANCE:
                bone = int(bone_translation.reshape(-1, num_bones - 1).max(dim=0).values.argmax()) + 1
                raise InputError(
                    f"Anny pose_parameters translate non-root bone {self.skeleton.joint_names[bone]!r} "
                    f"by {worst:.3g} m; igavatar's skeleton takes rotations only (plus the root's "
                    "translation), so those entries must be zero"
                )
        a, a_parent, heads = self._conversion_tensors(deltas)
        local_rotations = a_parent.transpose(-1, -2) @ rotations @ a
        root_translation = translations[..., 0, :] - heads[0]
        return local_rotations, root_translation

    def pose_parameters_from_local_rotations(
        self, local_rotations: torch.Tensor, root_translation: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Anny "local-ref" pose parameters of igavatar local rotations (the inverse conversion).

        Args:
            local_rotations: (..., 104, 3, 3) relative to this subject's rest pose.
            root_translation: (..., 3) or None for zero.
        Returns:
            (..., 104, 4, 4) pose parameters in the input's dtype, non-root translations zero.
        """
        num_bones = self.skeleton.num_joints
        if local_rotations.ndim < 3 or local_rotations.shape[-3:] != (num_bones, 3, 3):
            raise InputError(
                f"local_rotations has shape {tuple(local_rotations.shape)}, expected (N, {num_bones}, 3, 3)"
            )
        a, a_parent, heads = self._conversion_tensors(local_rotations)
        rotations = a_parent @ local_rotations @ a.transpose(-1, -2)
        batch = local_rotations.shape[:-3]
        translation = torch.zeros(batch + (num_bones, 3), dtype=rotations.dtype, device=rotations.device)
        root = heads[0].expand(batch + (3,))
        if root_translation is not None:
            root = root + root_translation.to(dtype=rotations.dtype, device=rotations.device)
        translation = torch.cat((root[..., None, :], translation[..., 1:, :]), dim=-2)
        return rigid_matrix(rotations, translation)

    def posed_vertices(
        self, local_rotations: torch.Tensor, root_translation: torch.Tensor | None = None
    ) -> torch.Tensor:
        """igavatar's FK + LBS of the rest mesh.

        Args:
            local_rotations: (..., 104, 3, 3); root_translation: (..., 3) or None.
        Returns:
            (..., V, 3) posed vertices in the input's dtype and device.
        """
        rest_joints, rest_vertices, weights = self._mesh_tensors(local_rotations.dtype, local_rotations.device)
        global_posed = forward_kinematics(local_rotations, rest_joints, self.skeleton.parents, root_translation)
        # Canonical = rest pose: G_j(rest) = [I | rest_j], so B_j = G_j @ [I | -rest_j].
        eye = torch.eye(3, dtype=rest_joints.dtype, device=rest_joints.device)
        transforms = global_posed @ rigid_matrix(eye, -rest_joints)
        return linear_blend_skinning(rest_vertices, weights, transforms)

    def _mesh_tensors(
        self, dtype: torch.dtype, device: torch.device
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Rest joints (J,3), rest vertices (V,3) and weights (V,J) in `dtype` on `device`,
        memoised so that posing on a GPU copies the mesh there once, not per call."""
        key = (dtype, str(device))
        if key not in self._mesh_cache:
            self._mesh_cache[key] = tuple(
                tensor.to(dtype=dtype, device=device)
                for tensor in (self._rest_heads64, self._rest_vertices64, self._weights64)
            )
        return self._mesh_cache[key]

    def anny_posed_vertices(self, pose_parameters: torch.Tensor | np.ndarray) -> torch.Tensor:
        """Anny's own forward pass (its kinematics and skinning) for this phenotype: the reference.

        Args:
            pose_parameters: (N, 104, 4, 4) "local-ref" deltas.
        Returns:
            (N, V, 3) float64 vertices on the input's device (computed on the model's device).
        """
        deltas = torch.as_tensor(pose_parameters)
        device = deltas.device
        with torch.no_grad():
            output = self.model(
                pose_parameters=deltas.to(dtype=self.model.dtype, device=self.model.device),
                phenotype_kwargs=self.phenotype,
            )
        return output["vertices"].to(device)

    def canonical_star_pose(self, leg_spread: float = 0.4) -> torch.Tensor:
        """Local rotations (104, 3, 3) float32 of the canonical "star" (Da-) pose.

        Anny's rest pose is an A-pose with the legs nearly together; this spreads each leg sideways
        by `leg_spread` radians at the hip (about the body's forward axis) so that the legs do not
        touch in canonical space. The arms stay in the A-pose, clear of the torso.
        """
        rotvecs = torch.zeros(self.skeleton.num_joints, 3, dtype=torch.float64)
        forward = torch.tensor(_ANNY_FORWARD, dtype=torch.float64)
        # A positive rotation about the forward axis swings a downward limb towards the subject's left.
        rotvecs[self.skeleton.index(_LEFT_HIP)] = leg_spread * forward
        rotvecs[self.skeleton.index(_RIGHT_HIP)] = -leg_spread * forward
        return axis_angle_to_matrix(rotvecs).to(torch.float32)
