"""The body fit to landmarks: known poses recovered from synthetic landmarks; back views relabelled."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from igavatar.body.anny_body import AnnyBody
from igavatar.body.landmark_fit import LandmarkFitConfig, LandmarkTargets, fit_landmarks
from igavatar.body.rotations import axis_angle_to_matrix
from igavatar.body.skeleton import forward_kinematics
from igavatar.capture.person_landmarks import LANDMARKS, MIRROR
from igavatar.capture.video_fit import (FREE_BONES, HINGE_BONES, VideoCamera, anny_body_of_height,
                                        anny_landmark_points, consistent_facing, facing_yaw)
from igavatar.errors import InputError


@pytest.fixture(scope="module")
def body() -> AnnyBody:
    return AnnyBody.load()


def _pose_clip(body: AnnyBody, n_frames: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Local rotations (N, J, 3, 3) and root translations (N, 3): a body turning in front of the
    VideoCamera (about 3 m away along +Y), limbs swinging by up to ~25 degrees."""
    generator = torch.Generator().manual_seed(seed)
    rotvecs = torch.zeros(n_frames, body.skeleton.num_joints, 3, dtype=torch.float64)
    free = [body.skeleton.index(b) for b in FREE_BONES]
    rotvecs[:, free] = 0.25 * (torch.rand(n_frames, len(free), 3, generator=generator, dtype=torch.float64) - 0.5) * 2
    for bone in HINGE_BONES:  # knees bend one way, about +X
        rotvecs[:, body.skeleton.index(bone)] = torch.tensor([0.3, 0.0, 0.0], dtype=torch.float64)
    yaw = torch.linspace(0.0, 1.5, n_frames, dtype=torch.float64)
    rotvecs[:, 0] = torch.stack([torch.zeros_like(yaw), torch.zeros_like(yaw), yaw], dim=1)
    translation = torch.zeros(n_frames, 3, dtype=torch.float64)
    translation[:, 1] = 3.0 + 0.1 * torch.arange(n_frames, dtype=torch.float64) / n_frames
    return axis_angle_to_matrix(rotvecs), translation


def _landmarks(body: AnnyBody, local: torch.Tensor, translation: torch.Tensor, camera: VideoCamera,
               shift_m: np.ndarray | None = None):
    """Perfect BlazePose-like observations of the posed body: pixels and hip-centred camera-axis 3D.
    `shift_m` (33, 3) moves the detector's landmarks from the fit's rest points (rest frame)."""
    points = anny_landmark_points(body)
    if shift_m is not None:
        points = dataclasses.replace(points, rest_points=points.rest_points + shift_m)
    global_posed = forward_kinematics(local, body.skeleton.rest_joints, body.skeleton.parents, translation).numpy()
    joints = np.maximum(points.joints, 0)
    offset = points.rest_points - body.skeleton.rest_joints[joints]
    x_world = np.einsum("nlij,lj->nli", global_posed[:, joints][..., :3, :3], offset) + global_posed[:, joints][..., :3, 3]
    x_camera = x_world @ camera.w2c[:3, :3].T + camera.w2c[:3, 3]
    uv = x_camera @ camera.K.T
    image_xy = uv[..., :2] / uv[..., 2:]
    hips = 0.5 * (x_camera[:, LANDMARKS["left_hip"]] + x_camera[:, LANDMARKS["right_hip"]])
    confidence = (points.joints >= 0).astype(np.float64)[None].repeat(len(local), 0)
    return LandmarkTargets(image_xy, confidence, x_camera - hips[:, None]), global_posed[..., :3, 3]


def test_fit_recovers_known_poses_from_synthetic_landmarks(body):
    camera = VideoCamera.for_frames(512, 512, focal_px=700.0)
    local, translation = _pose_clip(body, n_frames=6, seed=1)
    targets, true_joints = _landmarks(body, local, translation, camera)
    hinge = tuple(body.skeleton.index(b) for b in HINGE_BONES)
    config = LandmarkFitConfig(smooth_weight=0.0, translation_smooth_weight=0.0,
                               hinge_joints=hinge)
    fit = fit_landmarks(body.skeleton, anny_landmark_points(body), [body.skeleton.index(b) for b in FREE_BONES],
                        camera.K, camera.w2c, targets, config)
    fitted = forward_kinematics(torch.as_tensor(fit.local_rotations), body.skeleton.rest_joints, body.skeleton.parents,
                                torch.as_tensor(fit.root_translation))[..., :3, 3].numpy()
    main = [body.skeleton.index(b) for b in ("upperarm01.L", "lowerarm01.R", "wrist.L", "wrist.R", "upperleg01.R",
                                              "lowerleg01.L", "foot.L", "foot.R", "head")]
    error_m = np.linalg.norm(fitted[:, main] - true_joints[:, main], axis=-1)
    assert fit.mean_residual_px() < 1.0
    # Exact landmarks of the same body: the joints come back to about a centimetre, depth included
    # (a single view fixes depth weakly: measured 1.2 cm mean, 4.1 cm at worst).
    assert error_m.mean() < 0.02 and error_m.max() < 0.06
    # Started from the rest pose, the fit had to move the limbs: the true poses are 15+ degrees away.
    assert np.degrees(np.arccos(np.clip((np.trace(local[:, main].numpy(), axis1=-2, axis2=-1) - 1) / 2, -1, 1))).mean() > 10


def test_fitted_landmark_offsets_absorb_a_detector_that_places_joints_elsewhere(body):
    """A detector whose hips sit 4 cm lower and 2 cm wider than the fit's rest points (as on a heavy
    body): the clip's offsets take the difference up, so the joints are not tilted in depth."""
    camera = VideoCamera.for_frames(512, 512, focal_px=700.0)
    local, translation = _pose_clip(body, n_frames=8, seed=2)
    shift = np.zeros((33, 3))
    shift[LANDMARKS["left_hip"]] = [0.02, 0.0, -0.04]
    shift[LANDMARKS["right_hip"]] = [-0.02, 0.0, -0.04]
    targets, true_joints = _landmarks(body, local, translation, camera, shift)
    hinge = tuple(body.skeleton.index(b) for b in HINGE_BONES)
    main = [body.skeleton.index(b) for b in ("upperarm01.L", "wrist.L", "wrist.R", "upperleg01.L", "upperleg01.R",
                                              "lowerleg01.L", "foot.L", "foot.R", "head")]

    def joint_error_m(offset_weight: float) -> tuple[float, np.ndarray]:
        config = LandmarkFitConfig(smooth_weight=0.0, translation_smooth_weight=0.0, hinge_joints=hinge,
                                   offset_weight=offset_weight)
        fit = fit_landmarks(body.skeleton, anny_landmark_points(body), [body.skeleton.index(b) for b in FREE_BONES],
                            camera.K, camera.w2c, targets, config)
        fitted = forward_kinematics(torch.as_tensor(fit.local_rotations), body.skeleton.rest_joints,
                                    body.skeleton.parents, torch.as_tensor(fit.root_translation))[..., :3, 3].numpy()
        return float(np.linalg.norm(fitted[:, main] - true_joints[:, main], axis=-1).mean()), fit.landmark_offsets

    with_offsets, offsets = joint_error_m(0.1)
    without, no_offsets = joint_error_m(0.0)
    assert not no_offsets.any()
    # Measured: 2.2 cm with the offsets; 9.8 cm without, the pelvis tilted to shorten the thighs.
    assert with_offsets < 0.03 and with_offsets < 0.4 * without
    # The offsets found are the detector's, left-right mirrored (the prior shrinks them a little).
    left, right = offsets[LANDMARKS["left_hip"]], offsets[LANDMARKS["right_hip"]]
    assert left[2] < -0.02 and left[0] > 0.01  # measured (1.6, 0.2, -2.7) cm
    assert np.allclose(right, left * [-1.0, 1.0, 1.0])


def test_fit_needs_a_torso(body):
    camera = VideoCamera.for_frames(256, 256)
    local, translation = _pose_clip(body, n_frames=2, seed=0)
    targets, _ = _landmarks(body, local, translation, camera)
    blind = LandmarkTargets(targets.image_xy, targets.confidence, np.full_like(targets.world_xyz, np.nan))
    with pytest.raises(InputError, match="3D body landmarks"):
        fit_landmarks(body.skeleton, anny_landmark_points(body), [], camera.K, camera.w2c, blind)


def test_height_sets_the_rest_body_height(body):
    for height in (1.55, 1.85):
        tall = anny_body_of_height(body, height)
        z = tall.rest_vertices[:, 2]
        assert float(z.max() - z.min()) == pytest.approx(height, abs=2e-3)
    with pytest.raises(InputError, match="--height"):
        anny_body_of_height(body, 17.0)


def test_camera_from_fov_and_focal():
    camera = VideoCamera.for_frames(480, 640, fov_deg=90.0)
    assert camera.K[0, 0] == pytest.approx(320.0)
    assert camera.K[0, 2] == pytest.approx(319.5) and camera.K[1, 2] == pytest.approx(239.5)
    # Level, at the origin, looking along +Y (world up +Z is image up).
    assert np.allclose(camera.w2c[:3, :3] @ [0, 1, 0], [0, 0, 1]) and np.allclose(camera.w2c[:3, :3] @ [0, 0, 1], [0, -1, 0])
    with pytest.raises(InputError, match="not both"):
        VideoCamera.for_frames(480, 640, focal_px=500.0, fov_deg=60.0)
    with pytest.raises(InputError, match="--focal"):
        VideoCamera.for_frames(480, 640, focal_px=-5.0)


def _world_landmarks_turning(yaw: np.ndarray) -> np.ndarray:
    """(N, 33, 3) camera-axis landmarks of a torso turning by `yaw` (0 faces the camera)."""
    base = np.zeros((33, 3))
    # Facing the camera: the subject's left is image right (+x), up is -y, the face towards -z.
    base[LANDMARKS["left_shoulder"]], base[LANDMARKS["right_shoulder"]] = [0.2, -0.5, 0], [-0.2, -0.5, 0]
    base[LANDMARKS["left_hip"]], base[LANDMARKS["right_hip"]] = [0.1, 0, 0], [-0.1, 0, 0]
    out = []
    for angle in yaw:
        c, s = np.cos(angle), np.sin(angle)
        rotation = np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])  # about the camera's vertical axis
        out.append(base @ rotation.T)
    return np.stack(out)


def test_facing_yaw_and_consistent_relabelling():
    yaw = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    world = _world_landmarks_turning(yaw)
    measured = facing_yaw(world)
    assert np.allclose(np.cos(measured - yaw), 1.0, atol=1e-6)
    assert not consistent_facing(world).any()  # a correct turn keeps its labels
    # BlazePose's frontal reading of the back half: left and right swapped, depth reversed.
    back = np.cos(yaw) < -0.3
    mislabelled = world.copy()
    mislabelled[back] = world[back][:, MIRROR] * np.array([1.0, 1.0, -1.0])
    flips = consistent_facing(mislabelled)
    assert np.array_equal(flips, back)


def test_a_person_who_faces_the_camera_is_not_relabelled():
    yaw = 0.4 * np.sin(np.linspace(0, 3 * np.pi, 30))  # turning a little to and fro
    assert not consistent_facing(_world_landmarks_turning(yaw)).any()
