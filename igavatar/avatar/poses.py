"""Every pose source as one PoseSequence on a model's skeleton.

    poses = procedural_poses(model, "walk", n_frames=60, seed=0, fps=30.0)
    poses = read_poses(model, Path("poses.npz"), select=lambda n, where: list(range(n)))
    poses.bone_transforms (N, J, 4, 4), poses.pose_condition (N, pose_dim), poses.local_rotations (N, J, 3, 3)

Sources: a procedural motion (igavatar.body.motions), a pose file in any format of
igavatar.body.pose_files (retargeted to the model's skeleton there), a capture directory (its
poses.npz) and a dataset artifact. A dataset's frames keep its own bone transforms and pose
conditioning as stored (they are what the model was trained on); their local rotations, which
the GLB animation and poses.npz need, are recovered from those transforms.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from igavatar.artifacts.manifest import MANIFEST_NAME, InputRecord, read_artifact, read_manifest, sha256_file
from igavatar.artifacts.npz import read_npz
from igavatar.avatar.dataset import read_dataset
from igavatar.avatar.model import ModelArtifact
from igavatar.avatar.pose_carry import apply_corrections, carry_corrections
from igavatar.body.motions import SKELETON_KINDS, motion_by_name, walk
from igavatar.body.pose_files import local_pose_from_bone_transforms, read_pose_sequence, sequence_local_pose
from igavatar.errors import ArtifactError, InputError
from igavatar.training.pose_refine import REFINED_POSES_FILE

#: Frames per second of procedural motions, and of pose files that do not say.
DEFAULT_FPS = 30.0

#: select(n_frames, where) -> the frame indices to keep of a source with n_frames frames
#: (`where` names the source for error messages).
FrameSelection = Callable[[int, str], list[int]]


@dataclass(frozen=True, eq=False)
class PoseSequence:
    """N frames of a model's J-joint skeleton, ready to pose the avatar.

    Attributes:
        name: the motion's name or the source's file name; source: "procedural" or the path read.
        frame_names: N names (a pose file's or dataset's frame names, else 0000, 0001, ...).
        local_rotations: (N, J, 3, 3) relative to the rest pose; root_translation: (N, 3) meters.
        bone_transforms: (N, J, 4, 4) canonical -> posed world; pose_condition: (N, pose_dim);
        posed_joints: (N, J, 3) world joints.
        fps: playback rate; in_place: whether the motion stays over one spot.
        description: JSON-able facts for manifests (format, skeleton, source frames, indices).
        inputs: the files and artifacts read (for manifests).
    """

    name: str
    source: str
    frame_names: list[str]
    local_rotations: torch.Tensor
    root_translation: torch.Tensor
    bone_transforms: torch.Tensor
    pose_condition: torch.Tensor
    posed_joints: torch.Tensor
    fps: float
    in_place: bool = False
    description: dict = field(default_factory=dict)
    inputs: tuple[InputRecord, ...] = ()

    @property
    def n_frames(self) -> int:
        return int(self.local_rotations.shape[0])


def _from_rotations(model: ModelArtifact, local_rotations: torch.Tensor, root_translation: torch.Tensor,
                    **fields) -> PoseSequence:
    frames = model.pose(local_rotations, root_translation)
    if "frame_names" not in fields:
        digits = max(4, len(str(local_rotations.shape[0] - 1)))
        fields["frame_names"] = [f"{i:0{digits}d}" for i in range(local_rotations.shape[0])]
    return PoseSequence(
        local_rotations=local_rotations.float(), root_translation=root_translation.float(),
        bone_transforms=frames.bone_transforms, pose_condition=frames.pose_condition, posed_joints=frames.posed_joints,
        **fields,
    )


def procedural_poses(model: ModelArtifact, name: str, n_frames: int, seed: int, fps: float,
                     travel: bool = False) -> PoseSequence:
    """A shipped motion (igavatar.body.motions) for the model's skeleton; walk stays in place unless `travel`."""
    kind = model.body_model
    if kind not in SKELETON_KINDS:
        raise InputError(
            f"procedural motions drive {' and '.join(SKELETON_KINDS)} skeletons; the model {model.path} "
            f"has body model '{kind}': give a pose file as MOTION instead"
        )
    skeleton = model.skeleton
    if name == "walk":
        motion = walk(kind, n_frames, seed, fps=fps, in_place=not travel, skeleton=skeleton)
    else:
        motion = motion_by_name(name, kind, n_frames, seed, fps=fps, skeleton=skeleton)
    return _from_rotations(
        model, motion.local_rotations_for(skeleton), motion.root_translation_tensor(), name=name,
        source="procedural", fps=fps, in_place=name != "walk" or not travel,
        description={"source": "procedural", "format": "procedural", "skeleton": kind, "source_frames": n_frames},
    )


def dataset_poses(model: ModelArtifact, path: Path, select: FrameSelection, fps: float | None) -> PoseSequence:
    """Frames of a dataset artifact, with its stored bone transforms and pose conditioning."""
    dataset = read_dataset(path)
    subject = dataset.subject
    if not subject.same_skeleton(model.subject):
        raise InputError(
            f"{path}: its skeleton ({subject.n_joints} joints) is not the model's "
            f"({len(model.joint_names)} joints, {model.body_model}); retargeting is not available"
        )
    all_frames = dataset.frames()
    chosen = select(all_frames.n_frames, str(path / "frames.npz"))
    frames = all_frames.select(chosen)
    bone_transforms = torch.from_numpy(frames.bone_transforms).float()
    posed_joints = torch.from_numpy(frames.posed_joints).float()
    own = model_frame_poses(model, path, list(frames.names), bone_transforms)
    # The model's own training frames take the poses it refined while training (train --refine-poses),
    # and the frames between them in the same clips their neighbours' corrections.
    canonical_joints = torch.from_numpy(subject.canonical_joints).float()
    for slot, transforms in {**own.refined, **own.carried}.items():
        bone_transforms[slot] = transforms
        posed_joints[slot] = (transforms[:, :3, :3] @ canonical_joints[..., None])[..., 0] + transforms[:, :3, 3]
    rotations, translation = local_pose_from_bone_transforms(
        bone_transforms.double(), subject.parents, torch.from_numpy(subject.rest_joints).double(),
        torch.from_numpy(subject.canonical_rotations).double(),
    )
    return PoseSequence(
        name=path.name, source=str(path), frame_names=list(frames.names), local_rotations=rotations.float(),
        root_translation=translation.float(), bone_transforms=bone_transforms,
        pose_condition=torch.from_numpy(frames.pose_condition).float(),
        posed_joints=posed_joints, fps=float(fps or DEFAULT_FPS),
        description={"source": str(path), "format": "dataset", "skeleton": model.body_model,
                     "source_frames": all_frames.n_frames, "frame_indices": chosen,
                     **({"refined_frames": len(own.refined)} if own.refined else {}),
                     **({"carried_frames": len(own.carried)} if own.carried else {})},
        inputs=(InputRecord(path, "dataset"),),
    )


@dataclass(frozen=True)
class ModelFramePoses:
    """The model's own poses for some of a dataset's frames.

    Attributes:
        refined: slot -> (J, 4, 4) transforms of the frames the model refined (its training frames).
        carried: slot -> (J, 4, 4) transforms of other frames of the same clips, corrected by their
            refined neighbours' corrections interpolated in time (igavatar.avatar.pose_carry).
        carried_sizes: slot -> {"mean_joint_correction_deg", "root_correction_mm"}: the size of the
            correction each carried frame took.
    """

    refined: dict[int, torch.Tensor] = field(default_factory=dict)
    carried: dict[int, torch.Tensor] = field(default_factory=dict)
    carried_sizes: dict[int, dict[str, float]] = field(default_factory=dict)


def _refined_file(model: ModelArtifact, dataset_path: Path) -> dict | None:
    """The model's refined_poses.npz when it refined poses of the dataset at `dataset_path` (same
    manifest hash), else None."""
    refined_file = model.path / REFINED_POSES_FILE
    if not refined_file.is_file():
        return None
    trained_on = [record.get("sha256") for record in model.manifest["inputs"] if record.get("artifact") == "dataset"]
    if sha256_file(dataset_path / MANIFEST_NAME) not in trained_on:
        return None
    shapes = {"frame_names": ("N",), "bone_transforms": ("N", "J", 4, 4), "rotation_corrections": ("N", "K", 3),
              "translation_corrections": ("N", 3)}
    with np.load(refined_file) as stored:
        recorded_joints = "joints" in stored.files
    if recorded_joints:
        shapes["joints"] = ("K",)
    refined = read_npz(refined_file, shapes, "refined poses", "re-run `igavatar train`",
                       sizes={"J": model.subject.n_joints})
    if not recorded_joints:
        # Written before the file named them: train corrected the root and the major bones.
        refined["joints"] = np.union1d([0], np.asarray(model.subject.init_bones, dtype=np.int64))
        if len(refined["joints"]) != refined["rotation_corrections"].shape[1]:
            raise ArtifactError(f"{refined_file}: rotation_corrections has {refined['rotation_corrections'].shape[1]} "
                                "joints and the file does not say which; re-run `igavatar train`")
    return refined


def model_frame_poses(model: ModelArtifact, dataset_path: Path, names: list[str], bone_transforms: torch.Tensor,
                      carry: bool = True) -> ModelFramePoses:
    """The model's poses for the frames `names` of the dataset at `dataset_path`, whose stored
    transforms are bone_transforms (N, J, 4, 4): refined for the frames it refined and, with `carry`,
    carried in time to other frames of their clips. Empty for a model that refined none of its poses."""
    refined = _refined_file(model, dataset_path)
    if refined is None:
        return ModelFramePoses()
    by_name = {str(name): i for i, name in enumerate(refined["frame_names"])}
    transforms = torch.from_numpy(refined["bone_transforms"]).float()
    poses = ModelFramePoses(refined={slot: transforms[by_name[name]] for slot, name in enumerate(names) if name in by_name})
    if not carry:
        return poses
    carried = carry_corrections(list(by_name), transforms[:, 0, :3, :3],
                                torch.from_numpy(refined["rotation_corrections"]).float(),
                                torch.from_numpy(refined["translation_corrections"]).float(),
                                list(names), bone_transforms[:, 0, :3, :3].float())
    if len(carried):
        subject = model.subject
        corrected = apply_corrections(bone_transforms[carried.positions].double(), subject.parents,
                                      subject.rest_joints, subject.canonical_rotations, refined["joints"],
                                      carried.rotation, carried.translation)
        poses.carried.update(dict(zip(carried.positions, corrected)))
        degrees = torch.rad2deg(carried.rotation.norm(dim=-1)).mean(-1)
        millimetres = 1000 * carried.translation.norm(dim=-1)
        poses.carried_sizes.update({slot: {"mean_joint_correction_deg": float(d), "root_correction_mm": float(m)}
                                    for slot, d, m in zip(carried.positions, degrees, millimetres)})
    return poses


def file_poses(model: ModelArtifact, path: Path, select: FrameSelection, fps: float | None,
               anny_cache: Path | None = None, on_status: Callable[[str], None] | None = None) -> PoseSequence:
    """Frames of a pose file or capture directory, converted to the model's skeleton."""
    captured = path.is_dir() and (path / MANIFEST_NAME).is_file()
    if captured:
        read_artifact(path, expected="capture")  # an intact capture artifact, before reading its poses
    sequence = read_pose_sequence(path)
    chosen = select(sequence.n_frames, str(sequence.source))
    selected = sequence.select(chosen)
    phenotype = model.phenotype
    rotations, translation = sequence_local_pose(
        selected, model.skeleton, model.body_model, phenotype=phenotype, anny_cache=anny_cache, on_status=on_status,
    )
    description = {"source": str(path), "format": sequence.format, "skeleton": sequence.skeleton_kind,
                   "source_frames": sequence.n_frames, "frame_indices": chosen}
    if sequence.phenotype is not None and phenotype is not None:
        description["phenotype_matches_model"] = all(
            abs(sequence.phenotype.get(k, v) - v) < 1e-6 for k, v in phenotype.items()
        )
        if not description["phenotype_matches_model"] and on_status is not None:
            on_status(f"{sequence.source}: recorded for another Anny phenotype; its pose parameters are "
                      "applied to the model's subject")
    if captured:
        inputs: tuple[InputRecord, ...] = (InputRecord(path, "capture"),)
    elif path.is_dir():
        inputs = (InputRecord(sequence.source), InputRecord(path / "capture.json"))
    else:
        inputs = (InputRecord(path),)
    return _from_rotations(
        model, rotations, translation, name=path.stem, source=str(path), frame_names=list(selected.frame_names),
        fps=float(fps or sequence.fps or DEFAULT_FPS), description=description, inputs=inputs,
    )


def read_poses(model: ModelArtifact, path: Path, select: FrameSelection, *, fps: float | None = None,
               anny_cache: Path | None = None, on_status: Callable[[str], None] | None = None,
               option: str = "MOTION") -> PoseSequence:
    """The frames of a pose file, capture directory or dataset artifact at `path`.

    Args:
        select: which of the source's frames to keep (see FrameSelection).
        fps: playback rate; None takes the file's, else DEFAULT_FPS.
        option: the command-line name of the argument, for error messages.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{option} {path}: no such file or directory")
    if path.is_dir() and (path / MANIFEST_NAME).is_file():
        kind = read_manifest(path)["artifact"]
        if kind == "dataset":
            return dataset_poses(model, path, select, fps)
        if kind != "capture":
            raise ArtifactError(
                f"{option} {path}: is a {kind} artifact; give a pose .npz, a capture directory or a dataset artifact"
            )
    return file_poses(model, path, select, fps, anny_cache, on_status)
