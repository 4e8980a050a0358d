"""`preprocess --video CLIP --poses-from FILE`: the clip's frames and masks with a GPU estimator's SMPL poses.

    estimate = read_estimate(poses_from, smpl_model)                  # before the clip is read: errors first
    frames, tracks = keep_estimated(frames, tracks, estimate.poses)  # frames the estimate covers
    placed = place_estimate(estimate, frames, tracks, focal_px, fov_deg)   # camera, world poses, body-mask IoU
    write_estimate_capture(tmp, frames, tracks, estimate, placed, meta)

The estimate (igavatar.capture.estimator_poses) is in the camera frame of the source video. The
capture's world is that camera frame turned to SMPL's +Y up (x right, y up, the camera looking
down -z): w2c = diag(1, -1, -1). SMPL's transl moves the root joint, so turning the world changes
it by the shaped body's root joint J0: transl_world = F (J0 + transl_camera) - J0. The person's
masks are MediaPipe's, as on the plain video path; the estimate replaces igavatar's Anny fit. As
a check that the file belongs to this clip (frame indices, focal length, conventions), the posed
body's silhouette is compared with each frame's mask; a clip where they do not overlap is refused.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from igavatar.artifacts.png import write_png
from igavatar.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from igavatar.body.skeleton import SMPL_PARENTS
from igavatar.body.smpl_model import SmplModel, load_smpl_model, require_smpl_model
from igavatar.capture.contact_sheet import contact_sheet
from igavatar.capture.estimator_poses import EstimatorPoses, read_estimator_poses
from igavatar.capture.person_landmarks import PersonTracks, person_mask
from igavatar.capture.video_fit import VideoCamera
from igavatar.capture.video_frames import VideoFrames
from igavatar.errors import InputError
from igavatar.geometry.projection import filled_silhouette, project_points
from stages.video_frames_io import keep_frames, write_frames

#: Camera frame (OpenCV) -> the capture's +Y-up world, and back (its own inverse).
CAMERA_TO_WORLD = np.diag([1.0, -1.0, -1.0])
#: Below this mean IoU of the posed body and the person's masks the estimate is not this clip's.
MIN_BODY_MASK_IOU = 0.25
SHEET_FRAMES = 12


@dataclass(frozen=True)
class Estimate:
    """The estimator's poses and the user's SMPL model that poses them."""

    poses: EstimatorPoses
    model: SmplModel


@dataclass(frozen=True)
class PlacedEstimate:
    """The kept frames' SMPL parameters in the capture's world, its camera, and the body-mask check.

    Attributes:
        global_orient, body_pose, transl: (N, 3), (N, 69), (N, 3) per kept frame (world).
        camera: the fixed camera (K at the frames' size, w2c = CAMERA_TO_WORLD).
        vertices: (N, V, 3) the posed bodies in the world; joints: (N, 24, 3).
        body_mask_iou: (N,) IoU of each frame's body silhouette and person mask.
    """

    global_orient: np.ndarray
    body_pose: np.ndarray
    transl: np.ndarray
    camera: VideoCamera
    vertices: np.ndarray
    joints: np.ndarray
    body_mask_iou: np.ndarray


def read_estimate(poses_from: Path, smpl_model: Path | None) -> Estimate:
    """The estimate and the SMPL model, or the InputError a user can act on (checked before the clip is read)."""
    poses = read_estimator_poses(poses_from)
    path = require_smpl_model(smpl_model, f"--poses-from {poses_from} (SMPL poses)")
    return Estimate(poses, load_smpl_model(path))


def keep_estimated(frames: VideoFrames, tracks: PersonTracks, poses: EstimatorPoses) -> tuple[VideoFrames, PersonTracks]:
    """The frames the estimate covers (the others recorded in frames.dropped['no_estimate'])."""
    covered = np.isin(np.asarray(frames.source_indices), poses.source_frames)
    if not covered.any():
        raise InputError(
            f"{poses.path}: covers source frames {poses.source_frames.min()}-{poses.source_frames.max()}, none of the "
            f"{len(frames.source_indices)} frames kept from the clip; is it this clip's estimate?")
    return keep_frames(frames, tracks, covered, "no_estimate")


def estimate_camera(poses: EstimatorPoses, frames: VideoFrames, focal_px: float | None,
                    fov_deg: float | None) -> VideoCamera:
    """The clip's camera at the frames' size: --focal or --fov when given, else the file's focal
    length, else WHAM's own assumption (the image diagonal); the file's principal point or the centre."""
    height, width = frames.images[0].shape[:2]
    scale = width / frames.source_size[1]
    if focal_px is not None or fov_deg is not None:
        camera = VideoCamera.for_frames(height, width, focal_px, fov_deg)
        focal, source = float(camera.K[0, 0]), camera.focal_source
    elif poses.focal_px is not None:
        focal, source = poses.focal_px * scale, f"{poses.estimator}'s img_focal"
    else:
        focal, source = float(np.hypot(*frames.source_size)) * scale, f"{poses.estimator}'s default (the image diagonal)"
    if poses.center_px is not None:
        # Continuous pixel coordinates scale about the image's corner: c' = s (c + 0.5) - 0.5.
        cx, cy = scale * (poses.center_px + 0.5) - 0.5
    else:
        cx, cy = (width - 1) / 2, (height - 1) / 2
    K = np.array([[focal, 0.0, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]])
    w2c = np.eye(4)
    w2c[:3, :3] = CAMERA_TO_WORLD
    return VideoCamera(K, w2c, int(height), int(width), source)


def _world_parameters(estimate: Estimate, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """global_orient, body_pose, transl of the estimate's `rows`, turned into the capture's world."""
    poses = estimate.poses
    flip = torch.as_tensor(CAMERA_TO_WORLD)
    orient = matrix_to_axis_angle(flip @ axis_angle_to_matrix(torch.as_tensor(poses.global_orient[rows]))).numpy()
    root = estimate.model.rest_shape(torch.as_tensor(poses.betas))[1][0].numpy()
    transl = (poses.transl[rows] + root) @ CAMERA_TO_WORLD.T - root
    return orient, poses.body_pose[rows].copy(), transl


def place_estimate(estimate: Estimate, frames: VideoFrames, tracks: PersonTracks, focal_px: float | None,
                   fov_deg: float | None) -> PlacedEstimate:
    """The kept frames' world parameters, camera, posed bodies and body-mask agreement (refused below
    MIN_BODY_MASK_IOU on average: the file is not this clip's, or its focal length is wrong)."""
    poses = estimate.poses
    rows = np.searchsorted(poses.source_frames, np.asarray(frames.source_indices))
    orient, body_pose, transl = _world_parameters(estimate, rows)
    camera = estimate_camera(poses, frames, focal_px, fov_deg)
    posed = estimate.model.forward(torch.as_tensor(poses.betas), torch.as_tensor(orient), torch.as_tensor(body_pose),
                                   torch.as_tensor(transl))
    vertices, joints = posed.vertices.numpy(), posed.joints.numpy()
    faces = estimate.model.faces.numpy()
    ious = []
    for i in range(len(rows)):
        body = filled_silhouette(camera.K, camera.w2c, vertices[i], faces, camera.height, camera.width)
        mask = person_mask(tracks.masks[i]) > 127
        ious.append((body & mask).sum() / max(1, (body | mask).sum()))
    placed = PlacedEstimate(orient, body_pose, transl, camera, vertices, joints, np.asarray(ious))
    if placed.body_mask_iou.mean() < MIN_BODY_MASK_IOU:
        raise InputError(
            f"{poses.path}: its posed body overlaps the person's masks by IoU {placed.body_mask_iou.mean():.2f} on "
            f"average (a clip's own estimate gives 0.5 or more); it belongs to another clip or other frames, or the "
            f"focal length is off (used {camera.K[0, 0]:.0f} px, {camera.focal_source}: try --focal)")
    return placed


def estimate_meta(estimate: Estimate, placed: PlacedEstimate) -> dict:
    """capture.json's video.body and video.fit for an imported estimate."""
    poses = estimate.poses
    return {
        "camera": {"focal_px": float(placed.camera.K[0, 0]), "focal_from": placed.camera.focal_source,
                   "principal_point_px": [round(float(v), 2) for v in placed.camera.K[:2, 2]],
                   "image_size": [placed.camera.height, placed.camera.width]},
        "body": {"model": "smpl", "smpl_model": estimate.model.path.name, "betas": [round(float(b), 5) for b in poses.betas]},
        "poses_from": {"estimator": poses.estimator, "file": str(poses.path), "track": poses.track,
                       "tracks_in_file": poses.tracks, "frames_in_file": int(len(poses.source_frames))},
        "fit": {"body_mask_iou_mean": round(float(placed.body_mask_iou.mean()), 4),
                "frame_body_mask_iou": [round(float(v), 3) for v in placed.body_mask_iou]},
    }


def write_estimate_capture(tmp: Path, frames: VideoFrames, tracks: PersonTracks, estimate: Estimate,
                           placed: PlacedEstimate, meta: dict) -> None:
    """images/, masks/, cameras.npz, poses.npz (SMPL), contact_sheet.png and capture.json into `tmp`."""
    write_frames(tmp, frames, tracks, placed.camera)
    np.savez(tmp / "poses.npz", betas=estimate.poses.betas, global_orient=placed.global_orient,
             body_pose=placed.body_pose, transl=placed.transl)
    write_png(tmp / "contact_sheet.png", _sheet(frames, estimate, placed))
    (tmp / "capture.json").write_text(json.dumps(meta, indent=2) + "\n")


def _sheet(frames: VideoFrames, estimate: Estimate, placed: PlacedEstimate) -> np.ndarray:
    """The estimator's body (tinted, outlined) and skeleton over up to SHEET_FRAMES frames."""
    picks = np.unique(np.linspace(0, len(frames.images) - 1, min(SHEET_FRAMES, len(frames.images))).round().astype(int))
    faces = estimate.model.faces.numpy()
    items = []
    for i in picks:
        joints_uv, _ = project_points(placed.camera.K, placed.camera.w2c, placed.joints[i])
        items.append((frames.images[i], filled_silhouette(placed.camera.K, placed.camera.w2c, placed.vertices[i], faces,
                                        placed.camera.height, placed.camera.width), joints_uv,
                      f"{frames.names[i]} {estimate.poses.estimator}"))
    return contact_sheet(items, np.asarray(SMPL_PARENTS))
