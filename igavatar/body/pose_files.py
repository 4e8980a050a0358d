"""Pose sequence files (DATA.md section 2): read any supported format, convert to an avatar's skeleton.

    sequence = read_pose_sequence(Path("poses.npz"))      # or a capture v1 directory
    rotations, translation = sequence_local_pose(sequence.select([0, 5]), skeleton, "anny", phenotype=phenotype)

Formats, detected from the keys of the .npz (every per-frame array has N rows):
    anny         capture v1, Anny body model: pose_parameters (N, 104, 4, 4) in Anny's "local-ref"
                 parameterization [phenotype_labels (P,), phenotype_values (P,)]
    skeleton     capture v1, bare skeleton: parents (J,), rest_joints (J, 3), rotvecs (N, J, 3),
                 transl (N, 3) [joint_names (J,)]
    smpl-split   anim_nerf split files and capture v1 SMPL: global_orient (N, 3), body_pose (N, 69),
                 transl (N, 3) [betas]
    smpl-poses   AIST++ demo format used by InstantAvatar: poses (N, 72), trans (N, 3) [betas]
    smpl-amass   AMASS SMPL-H: poses (N, 156) (the first 66 values are the body; the hands are
                 padded to SMPL's 72 with zero rotations), trans (N, 3), mocap_framerate [betas, ...]
A capture v1 directory stands for its poses.npz, with the frames named as in capture.json.

Converting to an avatar's skeleton (`sequence_local_pose`) never guesses: an Anny sequence drives
an Anny avatar (its pose parameters are read with the avatar's own phenotype, through
igavatar.body.anny_body), an SMPL sequence drives a skeleton with SMPL's 24-joint tree directly and
an Anny avatar through igavatar.body.retarget (joint-name mapping with rest-pose correction), and a
bare-skeleton sequence drives a skeleton with the same parents (and names, when the file has
them). Anything else is an error naming both skeletons.

`local_pose_from_bone_transforms` goes the other way round for data that stores only bone
transforms (a dataset artifact's frames.npz): it recovers local rotations and root translation.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import jsonschema
import numpy as np
import torch

from igavatar import __version__
from igavatar.body.rotations import axis_angle_to_matrix
from igavatar.body.skeleton import SMPL_PARENTS, Skeleton, forward_kinematics
from igavatar.errors import BodyModelError, InputError, NotAvailableError
from schemas import load_schema

POSE_FORMATS: tuple[str, ...] = ("anny", "skeleton", "smpl-split", "smpl-poses", "smpl-amass")
"""Pose file formats read_pose_sequence recognises (see the module docstring)."""

ANNY_JOINTS = 104
SMPL_JOINTS = 24
_AMASS_BODY_VALUES = 66  # 22 joints x 3: SMPL-H's body; its hands (joints 22..51) are dropped
_CAPTURE_FILE = "capture.json"
_POSES_FILE = "poses.npz"


@dataclass(frozen=True)
class SourcePoses:
    """A pose sequence as read from a file, in its own skeleton (numpy, float64).

    Attributes:
        source: the file read (a capture's poses.npz for a capture directory).
        format: one of POSE_FORMATS.
        skeleton_kind: 'anny', 'smpl' or 'skeleton' (the skeleton the poses are written for).
        frame_names: N names (a capture's frame names, else '00000', '00001', ...).
        fps: frames per second when the file says (AMASS mocap_framerate, capture.json fps), else None.
        pose_parameters: (N, 104, 4, 4) Anny deltas (anny), else None.
        phenotype: the Anny phenotype stored with the poses (label -> value), or None.
        rotvecs: (N, J, 3) local axis-angle rotations relative to the rest pose (smpl, skeleton).
        transl: (N, 3) root translation in meters (smpl, skeleton).
        parents: (J,) parent indices (smpl: SMPL_PARENTS; skeleton: the file's), else None.
        rest_joints: (J, 3) rest joint positions of a bare-skeleton file, else None.
        joint_names: J names when the file has them, else None.
    """

    source: Path
    format: str
    skeleton_kind: str
    frame_names: tuple[str, ...]
    fps: float | None = None
    pose_parameters: np.ndarray | None = None
    phenotype: Mapping[str, float] | None = None
    rotvecs: np.ndarray | None = None
    transl: np.ndarray | None = None
    parents: np.ndarray | None = None
    rest_joints: np.ndarray | None = None
    joint_names: tuple[str, ...] | None = None

    @property
    def n_frames(self) -> int:
        """N, the number of frames."""
        return len(self.frame_names)

    @property
    def num_joints(self) -> int:
        """J of the sequence's skeleton."""
        return ANNY_JOINTS if self.skeleton_kind == "anny" else int(self.rotvecs.shape[1])

    def describe(self) -> str:
        """One phrase naming the format and skeleton, e.g. 'an SMPL pose sequence (smpl-amass, 24 joints)'."""
        article = {"anny": "an Anny", "smpl": "an SMPL", "skeleton": "a bare-skeleton"}[self.skeleton_kind]
        return f"{article} pose sequence ({self.format}, {self.num_joints} joints)"

    def select(self, indices: Sequence[int]) -> "SourcePoses":
        """The frames at `indices` (each in [0, N)), in that order; InputError naming the range otherwise."""
        index = np.asarray(list(indices), dtype=np.int64)
        bad = index[(index < 0) | (index >= self.n_frames)]
        if bad.size:
            raise InputError(
                f"{self.source}: frame {int(bad[0])} is out of range; the sequence has {self.n_frames} "
                f"frames (0..{self.n_frames - 1})"
            )
        pick = lambda array: None if array is None else array[index]  # noqa: E731
        return replace(
            self,
            frame_names=tuple(self.frame_names[i] for i in index),
            pose_parameters=pick(self.pose_parameters),
            rotvecs=pick(self.rotvecs),
            transl=pick(self.transl),
        )


# --------------------------------------------------------------------------------------------
# Reading


class _NpzReader:
    """Keys of one .npz read on demand (pickle refused), with errors naming the file and key."""

    def __init__(self, path: Path) -> None:
        self.path = path
        if not path.is_file():
            raise InputError(f"{path}: no such pose file")
        try:
            self._data = np.load(path, allow_pickle=False)
        except Exception as exc:  # zipfile.BadZipFile, OSError, ValueError: not an npz
            raise InputError(f"{path}: not a readable .npz pose file ({exc})") from exc
        if not isinstance(self._data, np.lib.npyio.NpzFile):
            raise InputError(f"{path}: is a single .npy array, expected an .npz pose file with named arrays")
        self.keys = set(self._data.files)

    def array(self, key: str, tail: tuple[int, ...], frames: int | None = None) -> np.ndarray:
        """Finite float64 array `key` of shape (N, *tail) with N >= 1 (N == frames when given)."""
        raw = self.raw(key)
        expected = "(" + ", ".join(["N" if frames is None else str(frames)] + [str(t) for t in tail]) + ")"
        if raw.dtype.kind not in "fiu" or raw.ndim != len(tail) + 1 or raw.shape[1:] != tail:
            raise InputError(f"{self.path}: key '{key}' has shape {raw.shape} and dtype {raw.dtype}, expected {expected}")
        if (frames is not None and raw.shape[0] != frames) or raw.shape[0] == 0:
            raise InputError(f"{self.path}: key '{key}' has shape {raw.shape}, expected {expected}")
        array = raw.astype(np.float64)
        if not np.all(np.isfinite(array)):
            raise InputError(f"{self.path}: key '{key}' holds NaN or infinite values")
        return array

    def raw(self, key: str) -> np.ndarray:
        """The array `key` as stored; InputError if it is missing or needs pickle."""
        if key not in self.keys:
            raise InputError(f"{self.path}: key '{key}' missing (keys present: {', '.join(sorted(self.keys))})")
        try:
            return self._data[key]
        except ValueError as exc:
            raise InputError(f"{self.path}: key '{key}' holds pickled objects, which igavatar never loads") from exc

    def scalar(self, key: str) -> np.ndarray:
        """A single finite number `key` as a float64 0-d array."""
        raw = self.raw(key)
        if raw.dtype.kind not in "fiu" or raw.size != 1 or not np.isfinite(raw).all():
            raise InputError(f"{self.path}: key '{key}' has shape {raw.shape} and dtype {raw.dtype}, expected one number")
        return np.asarray(raw, dtype=np.float64).reshape(())

    def strings(self, key: str, count: int | None = None) -> tuple[str, ...]:
        """1-D string array `key` (of `count` entries when given) as a tuple."""
        raw = self.raw(key)
        if raw.dtype.kind not in "US" or raw.ndim != 1 or (count is not None and raw.shape[0] != count):
            want = "(J,)" if count is None else f"({count},)"
            raise InputError(
                f"{self.path}: key '{key}' has shape {raw.shape} and dtype {raw.dtype}, expected {want} strings"
            )
        return tuple(str(s) for s in raw)

    def close(self) -> None:
        self._data.close()


def _detect_format(reader: _NpzReader) -> str:
    keys = reader.keys
    if "pose_parameters" in keys:
        return "anny"
    if "rotvecs" in keys:
        return "skeleton"
    if "global_orient" in keys or "body_pose" in keys:
        return "smpl-split"
    if "poses" in keys:
        raw = reader.raw("poses")
        columns = raw.shape[1] if raw.ndim == 2 else None
        if columns == 72:
            return "smpl-poses"
        if columns == 156:
            return "smpl-amass"
        raise InputError(
            f"{reader.path}: key 'poses' has shape {raw.shape}, expected (N, 72) (SMPL, AIST++ format) or "
            "(N, 156) (AMASS SMPL-H); other layouts (e.g. SMPL-X with 165 values) are not supported"
        )
    raise InputError(
        f"{reader.path}: not a pose sequence igavatar knows (keys: {', '.join(sorted(keys)) or 'none'}); "
        "expected one of: pose_parameters (Anny capture v1); parents/rest_joints/rotvecs/transl (skeleton "
        "capture v1); global_orient/body_pose/transl (SMPL); poses (N, 72)/trans (AIST++); poses (N, 156)/"
        "trans/mocap_framerate (AMASS)"
    )


def _read_npz(path: Path, frame_names: Sequence[str] | None, fps: float | None) -> SourcePoses:
    reader = _NpzReader(path)
    try:
        return _parse(reader, frame_names, fps)
    finally:
        reader.close()


def _parse(reader: _NpzReader, frame_names: Sequence[str] | None, fps: float | None) -> SourcePoses:
    path = reader.path
    kind = _detect_format(reader)
    frames = None if frame_names is None else len(frame_names)

    def names(n: int) -> tuple[str, ...]:
        return tuple(frame_names) if frame_names is not None else tuple(f"{i:05d}" for i in range(n))

    if kind == "anny":
        parameters = reader.array("pose_parameters", (ANNY_JOINTS, 4, 4), frames)
        phenotype = None
        if "phenotype_labels" in reader.keys or "phenotype_values" in reader.keys:
            labels = reader.strings("phenotype_labels")
            values = reader.array("phenotype_values", (), len(labels))
            phenotype = dict(zip(labels, (float(v) for v in values)))
        return SourcePoses(path, "anny", "anny", names(parameters.shape[0]), fps,
                            pose_parameters=parameters, phenotype=phenotype)

    if kind == "skeleton":
        parents = reader.array("parents", (), None)
        num_joints = parents.shape[0]
        if not np.all(parents == np.round(parents)):
            raise InputError(f"{path}: key 'parents' must hold integers")
        rest = reader.array("rest_joints", (3,), num_joints)
        rotvecs = reader.array("rotvecs", (num_joints, 3), frames)
        transl = reader.array("transl", (3,), rotvecs.shape[0])
        joint_names = reader.strings("joint_names", num_joints) if "joint_names" in reader.keys else None
        # Skeleton validates the tree (one root at 0, parents before children).
        Skeleton(parents.astype(np.int64), rest, joint_names or tuple(f"joint_{j}" for j in range(num_joints)))
        return SourcePoses(path, "skeleton", "skeleton", names(rotvecs.shape[0]), fps, rotvecs=rotvecs,
                            transl=transl, parents=parents.astype(np.int64), rest_joints=rest, joint_names=joint_names)

    if kind == "smpl-split":
        orient = reader.array("global_orient", (3,), frames)
        body = reader.array("body_pose", (69,), orient.shape[0])
        transl = reader.array("transl", (3,), orient.shape[0])
        values = np.concatenate((orient, body), axis=1)
    elif kind == "smpl-poses":
        values = reader.array("poses", (72,), frames)
        transl = reader.array("trans", (3,), values.shape[0])
    else:  # smpl-amass
        poses = reader.array("poses", (156,), frames)
        transl = reader.array("trans", (3,), poses.shape[0])
        hands = np.zeros((poses.shape[0], 72 - _AMASS_BODY_VALUES))
        values = np.concatenate((poses[:, :_AMASS_BODY_VALUES], hands), axis=1)
        if "mocap_framerate" in reader.keys:
            fps = float(reader.scalar("mocap_framerate"))
    return SourcePoses(path, kind, "smpl", names(values.shape[0]), fps,
                        rotvecs=values.reshape(-1, SMPL_JOINTS, 3), transl=transl,
                        parents=np.asarray(SMPL_PARENTS, dtype=np.int64))


def _read_capture(root: Path) -> SourcePoses:
    meta_path = root / _CAPTURE_FILE
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{meta_path}: not valid JSON ({exc})") from exc
    errors = sorted(jsonschema.Draft202012Validator(load_schema("capture")).iter_errors(meta), key=lambda e: list(e.path))
    if errors:
        where = ".".join(str(p) for p in errors[0].absolute_path) or "(top level)"
        raise InputError(f"{meta_path}: {where}: {errors[0].message}")
    sequence = _read_npz(root / _POSES_FILE, meta["frames"], meta.get("fps"))
    if sequence.skeleton_kind != meta["body_model"]:
        raise InputError(
            f"{root / _POSES_FILE}: holds {sequence.describe()} but {meta_path} says body_model "
            f"'{meta['body_model']}'"
        )
    return sequence


def read_pose_sequence(path: str | Path) -> SourcePoses:
    """Read a pose sequence file (any of POSE_FORMATS) or a capture v1 directory's poses.

    Raises:
        InputError naming the file, key and shape for a missing file, an unknown layout, a wrong
        shape, or NaN values.
    """
    path = Path(path)
    if path.is_dir():
        if not (path / _CAPTURE_FILE).is_file():
            raise InputError(
                f"{path}: is a directory without {_CAPTURE_FILE}; --pose takes a pose .npz file, a capture v1 "
                "directory or a dataset artifact"
            )
        return _read_capture(path)
    return _read_npz(path, None, None)


# --------------------------------------------------------------------------------------------
# Conversion to an avatar's skeleton


def _skeleton_label(body_model: str, skeleton: Skeleton) -> str:
    names = {"anny": "Anny", "smpl": "SMPL", "skeleton": "a bare skeleton"}
    return f"{names.get(body_model, body_model)} ({skeleton.num_joints} joints)"


def sequence_local_pose(
    sequence: SourcePoses,
    skeleton: Skeleton,
    body_model: str,
    *,
    phenotype: Mapping[str, float] | None = None,
    anny_cache: Path | None = None,
    on_status: Callable[[str], None] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Local rotations and root translation of a sequence for an avatar's skeleton.

    SMPL sequences on an Anny avatar are retargeted (igavatar.body.retarget): the avatar's world is
    then taken to be Anny's (+Z up), as for every Anny capture igavatar makes.

    Args:
        sequence: from read_pose_sequence (select the frames first: Anny conversion is per frame).
        skeleton: the avatar's skeleton (rest joints, parents, names).
        body_model: the avatar's body model, 'anny', 'smpl' or 'skeleton'.
        phenotype: the avatar's Anny phenotype (needed for Anny sequences).
        anny_cache, on_status: passed to AnnyBody.load.
    Returns:
        local_rotations (N, J, 3, 3) relative to the skeleton's rest pose and root_translation
        (N, 3), float32 CPU tensors (forward_kinematics' conventions).
    Raises:
        NotAvailableError: the sequence is for another skeleton and no retarget exists yet.
        InputError / BodyModelError: skeletons that cannot match, or a missing phenotype.
    """
    avatar = _skeleton_label(body_model, skeleton)
    if sequence.skeleton_kind == "anny":
        if body_model != "anny" or skeleton.num_joints != ANNY_JOINTS:
            raise NotAvailableError(
                f"{sequence.source}: {sequence.describe()} cannot drive this avatar, whose skeleton is {avatar}; "
                f"retargeting Anny motions to other skeletons is not available yet in igavatar {__version__}"
            )
        if phenotype is None:
            raise BodyModelError(
                f"{sequence.source}: Anny poses need the avatar's phenotype to be read, and none was given "
                "(the model manifest's data.subject.phenotype); re-run `igavatar train` on a current dataset"
            )
        from igavatar.body.anny_body import AnnyBody

        body = AnnyBody.load(phenotype, cache_dir=anny_cache, on_status=on_status)
        same_bones = body.skeleton.joint_names == skeleton.joint_names
        if not (same_bones and np.array_equal(body.skeleton.parents, skeleton.parents)):
            raise BodyModelError(
                "the installed Anny model's 104 bones differ from the avatar's skeleton (names or parents): "
                "the avatar was made with another Anny version than the installed one"
            )
        if not np.allclose(body.skeleton.rest_joints, skeleton.rest_joints, atol=1e-4):
            raise BodyModelError(
                "Anny with the avatar's phenotype does not reproduce the avatar's rest skeleton "
                f"(max joint difference {np.abs(body.skeleton.rest_joints - skeleton.rest_joints).max():.3g} m); "
                "the phenotype recorded in the model does not match its skeleton"
            )
        rotations, translation = body.local_rotations_from_pose_parameters(torch.as_tensor(sequence.pose_parameters))
        return rotations.to(torch.float32), translation.to(torch.float32)

    if sequence.skeleton_kind == "smpl":
        if skeleton.num_joints != SMPL_JOINTS or tuple(skeleton.parents.tolist()) != SMPL_PARENTS:
            from igavatar.body.retarget import RETARGETS, retarget_sequence

            if ("smpl", body_model) in RETARGETS:
                try:
                    rotations, translation = retarget_sequence(sequence.rotvecs, sequence.transl, skeleton, "smpl", body_model)
                except InputError as exc:
                    raise InputError(f"{sequence.source}: cannot retarget {sequence.describe()} to {avatar}: {exc}") from exc
                return rotations.to(torch.float32), translation.to(torch.float32)
            targets = ", ".join(t for s, t in RETARGETS if s == "smpl")
            raise NotAvailableError(
                f"{sequence.source}: {sequence.describe()} cannot drive this avatar: its skeleton is {avatar}, "
                f"which is not SMPL's 24-joint tree, and igavatar {__version__} retargets SMPL motions only to "
                f"{targets} avatars"
            )
    else:  # skeleton
        same_tree = sequence.num_joints == skeleton.num_joints and np.array_equal(sequence.parents, skeleton.parents)
        same_names = sequence.joint_names is None or tuple(sequence.joint_names) == skeleton.joint_names
        if not (same_tree and same_names):
            raise InputError(
                f"{sequence.source}: {sequence.describe()} is for another skeleton than this avatar's, which is "
                f"{avatar}{'' if same_tree else ' with other parents'}"
                f"{'' if same_names else ' and other joint names'}; bare-skeleton sequences drive only avatars of the same "
                "skeleton (only SMPL motions are retargeted, onto Anny)"
            )
    rotations = axis_angle_to_matrix(torch.as_tensor(sequence.rotvecs, dtype=torch.float64))
    return rotations.to(torch.float32), torch.as_tensor(sequence.transl, dtype=torch.float32)


def local_pose_from_bone_transforms(
    bone_transforms: torch.Tensor,
    parents: Sequence[int] | np.ndarray,
    rest_joints: torch.Tensor,
    canonical_rotations: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Local rotations and root translation that produce given bone transforms (pose_frames inverted).

    With C_j = FK(canonical pose) and B_j = G_j C_j^-1, the posed global transforms are
    G_j = B_j C_j; local rotations are Q_parent^T Q_j (Q the rotation parts) and the root
    translation is G_root's translation minus the root's rest position.

    Args:
        bone_transforms: (N, J, 4, 4) canonical -> posed world.
        parents: (J,) parent indices; rest_joints: (J, 3); canonical_rotations: (J, 3, 3).
    Returns:
        local_rotations (N, J, 3, 3) relative to the rest pose and root_translation (N, 3), in
        bone_transforms' dtype and device.
    """
    like = bone_transforms
    canonical_global = forward_kinematics(
        canonical_rotations.to(like), rest_joints.to(like), np.asarray(parents, dtype=np.int64)
    )
    posed_global = like @ canonical_global
    q = posed_global[..., :3, :3]
    parent_index = torch.as_tensor(np.maximum(np.asarray(parents, dtype=np.int64), 0), device=like.device)
    local = q[..., parent_index, :, :].transpose(-1, -2) @ q
    local = torch.cat((q[..., :1, :, :], local[..., 1:, :, :]), dim=-3)
    root_translation = posed_global[..., 0, :3, 3] - rest_joints.to(like)[0]
    return local, root_translation
