"""Fit a skeleton's poses to 2D body landmarks of a whole clip, seen by one fixed pinhole camera.

    fit = fit_landmarks(skeleton, points, free_joints, K, w2c, targets, LandmarkFitConfig())
    fit.local_rotations   # (N, J, 3, 3) relative to the rest pose; joints not free stay at rest
    fit.root_translation  # (N, 3) world
    fit.residual_px       # (N, L) reprojection error of each landmark (NaN where unused)

What is fitted: per frame, the root's world rotation and translation and the local rotations of
`free_joints`; the skeleton's proportions (its rest joints) and the camera are given. The losses:
- the landmarks' 2D reprojection, weighted by their confidence, robust (Huber) in pixels;
- a 3D prior: the direction of each limb in camera axes agrees with metric "world" landmarks
  (BlazePose gives them around the hips, in the camera's axes), which resolves the depth
  ambiguity of a single view (does the forearm point to the camera or away?);
- temporal smoothness of every rotation (as matrices, so a 360-degree turn has no wrap) and of
  the root's path;
- a pose prior towards the rest pose, and hinge limits: knees bend one way only;
- per clip, one offset of each landmark from its rest point (left-right symmetric), with a prior
  towards none: a detector's joint is not the body model's, and where it lies depends on the
  body (a heavier body's hip landmarks sit further from its thigh bones). Without it the fit
  tilted limbs and the pelvis in depth, where a single view cannot see it, to absorb the
  difference: on a heavy subject its pelvis leant 12 cm back in a front view.
- with the person's masks (a SilhouetteTarget), a last stage keeps the body inside them
  (igavatar.body.silhouette_fit), and with the frames' optical flow (a FlowTarget) moves the
  body's visible surface from frame to frame as the pixels moved (igavatar.body.flow_fit); the
  smoothness prior is then weaker in every stage (flow_smooth_weight).
The root is initialised per frame from the world landmarks' torso and the 2D hips (its depth from
the torso's length in pixels against the skeleton's), then the root is fitted alone, then all,
then all with the silhouette.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from igavatar.body.flow_fit import FlowTarget
from igavatar.body.image_maps import huber_px
from igavatar.body.rotations import axis_angle_to_matrix
from igavatar.body.silhouette_fit import SilhouetteTarget
from igavatar.body.skeleton import Skeleton, forward_kinematics
from igavatar.errors import InputError


@dataclass(frozen=True)
class BodyPoints:
    """Where each of L landmarks sits on the skeleton.

    Attributes:
        joints: (L,) int joint each landmark is attached to, or -1 for a landmark not modelled.
        rest_points: (L, 3) the landmark's position in the rest pose (meters, world frame).
        limbs: (B, 2) landmark index pairs (from, to) whose direction the 3D prior compares.
        torso: landmark indices (left_shoulder, right_shoulder, left_hip, right_hip) for the root's
            initialisation.
        body_axes: (3, 3) rows: the body's left, up and forward directions in the rest pose (world).
        mirror: (L,) int index of each landmark's left-right mirror (itself on the midline), or
            None: the clip's landmark offsets are then fitted without symmetry.
    """

    joints: np.ndarray
    rest_points: np.ndarray
    limbs: np.ndarray
    torso: tuple[int, int, int, int]
    body_axes: np.ndarray
    mirror: np.ndarray | None = None


@dataclass(frozen=True)
class LandmarkTargets:
    """Per-frame observations (N frames, L landmarks), numpy float.

    Attributes:
        image_xy: (N, L, 2) pixels (any value where confidence is 0).
        confidence: (N, L) weights in [0, 1]; 0 drops the landmark in that frame.
        world_xyz: (N, L, 3) metric landmarks in camera axes around the hips, or NaN.
    """

    image_xy: np.ndarray
    confidence: np.ndarray
    world_xyz: np.ndarray


#: The size of a landmark offset the prior calls typical: where a detector puts a joint differs
#: from a body model's joint by a few centimetres, and by body shape (a heavier body's hips).
OFFSET_SCALE_M = 0.02


@dataclass(frozen=True)
class LandmarkFitConfig:
    """Weights and schedule of the fit (defaults tuned on synthetic clips at 512 px)."""

    root_iterations: int = 150
    # A single view fixes depth weakly: with exact landmarks, 600 steps leave the root 2 cm off in
    # depth, 1000 steps 1 mm (tests/test_video_fit.py); a decaying rate stalled earlier.
    iterations: int = 1000
    learning_rate: float = 0.01
    huber_px: float = 8.0
    # Measured on three synthetic turns (tests/benchmarks/results/video-fit-offsets.md): a weaker
    # limb prior (0.5) and smoothness (2.0) let the fit tilt limbs in depth to absorb a few px.
    # With the flow term below (frames given), the smoothness of every stage is flow_smooth_weight:
    # the flow ties consecutive frames where the person has texture, fast motion included
    # (tests/benchmarks/results/video-fit-flow.md).
    limb_weight: float = 4.0
    smooth_weight: float = 10.0
    flow_smooth_weight: float = 5.0
    translation_smooth_weight: float = 20.0
    # The silhouette stage (igavatar.body.silhouette_fit), run after the landmark stages when the
    # person's masks are given. Measured on three synthetic turns and a synthetic walk/arm-raise/squat
    # clip (tests/benchmarks/results/video-fit-silhouette.md): the body inside the masks brought the
    # joints closer on every clip. The outline's coverage (coverage_weight > 0) fixed more of the
    # frames' depth on some clips, but pulled the dress's legs towards its hem: off by default.
    silhouette_weight: float = 10.0
    silhouette_iterations: int = 300
    silhouette_points: int = 600
    coverage_weight: float = 0.0
    # The optical-flow term of the same stage (igavatar.body.flow_fit), when the frames are given:
    # consecutive poses move the body's visible surface as the pixels moved. Measured on the same
    # four clips (tests/benchmarks/results/video-fit-flow.md): PA-MPJPE lower on all four.
    flow_weight: float = 2.0
    prior_weight: float = 0.002
    hinge_weight: float = 1.0
    hinge_joints: tuple[int, ...] = ()
    """Joints that bend about their rest frame's +X only (knees): other components and negative
    bends are penalised."""
    offset_weight: float = 0.1
    """Weight of the prior on the clip's landmark offsets, per (offset / OFFSET_SCALE_M)^2; 0 fits
    no offsets (each landmark stays at its rest point)."""


@dataclass(frozen=True)
class LandmarkFit:
    """The fitted poses and how well they explain the landmarks.

    Attributes:
        local_rotations: (N, J, 3, 3) float64 relative to the rest pose.
        root_translation: (N, 3) float64 world.
        residual_px: (N, L) reprojection error in pixels, NaN where the landmark was unused.
        posed_points: (N, L, 3) float64 fitted landmark positions in world coordinates.
        landmark_offsets: (L, 3) float64 the clip's fitted offsets of the landmarks from their
            rest points (rest frame, meters; zeros when none were fitted).
        silhouette_px: after a silhouette stage, the mean distances (px) of the body outside the
            masks and of the masks' outlines from the body (SilhouetteTarget.mean_distances_px),
            and with the flow term the visible points' mean distance off the flow ("flow_px").
    """

    local_rotations: np.ndarray
    root_translation: np.ndarray
    residual_px: np.ndarray
    posed_points: np.ndarray
    landmark_offsets: np.ndarray
    silhouette_px: dict[str, float] | None = None

    def mean_residual_px(self) -> float:
        """Mean reprojection error over every used landmark of every frame."""
        values = self.residual_px[np.isfinite(self.residual_px)]
        return float(values.mean()) if values.size else float("nan")


def _frame_from_axes(left: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(3, 3) orthonormal columns (left, up x left, up) with up made orthogonal to left."""
    left = left / max(np.linalg.norm(left), 1e-9)
    up = up - left * float(up @ left)
    up = up / max(np.linalg.norm(up), 1e-9)
    return np.stack([left, np.cross(up, left), up], axis=1)


def initial_root(points: BodyPoints, skeleton: Skeleton, K: np.ndarray, w2c: np.ndarray,
                 targets: LandmarkTargets) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame root rotation (N, 3, 3) and translation (N, 3) from the torso's landmarks.

    The rotation turns the rest body's (left, up) onto the world landmarks' (shoulders + hips
    left-right, hips -> shoulders); frames without world landmarks take the nearest that has
    them. The translation puts the rest hips' centre on the ray through the 2D hips' centre, at
    the depth where the rest torso's length matches its length in pixels.
    """
    l_sh, r_sh, l_hip, r_hip = points.torso
    c2w = np.linalg.inv(w2c)
    world = targets.world_xyz.astype(np.float64) @ c2w[:3, :3].T  # camera axes -> world axes
    good = np.isfinite(world[:, list(points.torso)]).all(axis=(1, 2))
    if not good.any():
        raise InputError("no frame has 3D body landmarks to start the body fit from")
    rest_frame = _frame_from_axes(points.body_axes[0], points.body_axes[1])
    n_frames = world.shape[0]
    rotations = np.zeros((n_frames, 3, 3))
    for i in np.flatnonzero(good):
        w = world[i]
        left = (w[l_sh] - w[r_sh]) + (w[l_hip] - w[r_hip])
        up = 0.5 * (w[l_sh] + w[r_sh]) - 0.5 * (w[l_hip] + w[r_hip])
        rotations[i] = _frame_from_axes(left, up) @ rest_frame.T
    nearest = np.flatnonzero(good)[np.abs(np.arange(n_frames)[:, None] - np.flatnonzero(good)[None]).argmin(1)]
    rotations = rotations[nearest]

    rest = points.rest_points
    hips_rest = 0.5 * (rest[l_hip] + rest[r_hip])
    torso_rest = float(np.linalg.norm(0.5 * (rest[l_sh] + rest[r_sh]) - hips_rest))
    xy = targets.image_xy.astype(np.float64)
    hips_px = 0.5 * (xy[:, l_hip] + xy[:, r_hip])
    torso_px = np.linalg.norm(0.5 * (xy[:, l_sh] + xy[:, r_sh]) - hips_px, axis=1)
    seen = (targets.confidence[:, list(points.torso)] > 0).all(axis=1) & (torso_px > 1.0)
    if not seen.any():
        raise InputError("no frame shows the shoulders and hips together; the body fit cannot start")
    fill = np.flatnonzero(seen)[np.abs(np.arange(n_frames)[:, None] - np.flatnonzero(seen)[None]).argmin(1)]
    hips_px, torso_px = hips_px[fill], torso_px[fill]
    depth = float(K[1, 1]) * torso_rest / torso_px
    rays = np.linalg.solve(K, np.concatenate([hips_px, np.ones((n_frames, 1))], axis=1).T).T
    hips_world = (rays * depth[:, None]) @ c2w[:3, :3].T + c2w[:3, 3]
    root_rest = skeleton.rest_joints[0]
    translation = hips_world - root_rest - np.einsum("nij,j->ni", rotations, hips_rest - root_rest)
    return rotations, translation


def _posed_points(skeleton: Skeleton, points: BodyPoints, local: torch.Tensor, translation: torch.Tensor,
                  offsets: torch.Tensor | None = None, global_posed: torch.Tensor | None = None) -> torch.Tensor:
    """(N, L, 3) world landmark positions of the posed skeleton (unmodelled ones at the origin);
    `offsets` (L, 3) move the landmarks from their rest points in the rest frame; `global_posed`
    (N, J, 4, 4): the skeleton's forward kinematics, when already computed."""
    rest_joints = torch.tensor(skeleton.rest_joints, dtype=local.dtype)
    if global_posed is None:
        global_posed = forward_kinematics(local, rest_joints, skeleton.parents, translation)
    joints = torch.as_tensor(np.maximum(points.joints, 0))
    rest_points = torch.as_tensor(points.rest_points, dtype=local.dtype)
    if offsets is not None:
        rest_points = rest_points + offsets
    transform = global_posed[:, joints]  # (N, L, 4, 4)
    offset = rest_points - rest_joints[joints]
    return (transform[..., :3, :3] @ offset[..., None])[..., 0] + transform[..., :3, 3]


class _Parameters(torch.nn.Module):
    """Root rotation (as a correction to its initial matrix), translation and free joints' rotvecs."""

    def __init__(self, root_init: np.ndarray, translation_init: np.ndarray, num_free: int, num_points: int,
                 mirror: np.ndarray | None) -> None:
        super().__init__()
        n_frames = root_init.shape[0]
        self.register_buffer("root_init", torch.as_tensor(root_init, dtype=torch.float64))
        self.root_delta = torch.nn.Parameter(torch.zeros(n_frames, 3, dtype=torch.float64))
        self.translation = torch.nn.Parameter(torch.as_tensor(translation_init, dtype=torch.float64).clone())
        self.free = torch.nn.Parameter(torch.zeros(n_frames, num_free, 3, dtype=torch.float64))
        self.raw_offsets = torch.nn.Parameter(torch.zeros(num_points, 3, dtype=torch.float64))
        self.mirror = None if mirror is None else torch.as_tensor(mirror, dtype=torch.long)

    def offsets(self) -> torch.Tensor:
        """(L, 3) the clip's landmark offsets (rest frame, meters), left-right symmetric when a
        mirror is known (a midline landmark then keeps x = 0)."""
        if self.mirror is None:
            return self.raw_offsets
        flip = torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
        return 0.5 * (self.raw_offsets + self.raw_offsets[self.mirror] * flip)

    def local_rotations(self, num_joints: int, free_joints: torch.Tensor) -> torch.Tensor:
        n_frames = self.free.shape[0]
        eye = torch.eye(3, dtype=torch.float64).expand(n_frames, num_joints, 3, 3)
        root = axis_angle_to_matrix(self.root_delta) @ self.root_init
        free = axis_angle_to_matrix(self.free)
        local = eye.clone()
        local[:, free_joints] = free
        local[:, 0] = root
        return local


def _project(K: torch.Tensor, w2c: torch.Tensor, x_world: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixels (..., 2) and camera-frame points (..., 3) of world points (..., 3)."""
    x_camera = x_world @ w2c[:3, :3].T + w2c[:3, 3]
    uv = x_camera @ K.T
    return uv[..., :2] / uv[..., 2:].clamp_min(1e-3), x_camera


@dataclass(frozen=True)
class _Observations:
    """The targets as float64 tensors, with the unusable entries' weights set to 0."""

    image_xy: torch.Tensor
    confidence: torch.Tensor
    limb_directions: torch.Tensor
    limb_weight: torch.Tensor

    @classmethod
    def of(cls, targets: LandmarkTargets, points: BodyPoints) -> "_Observations":
        confidence = np.where(points.joints[None] >= 0, targets.confidence, 0.0)
        confidence = np.where(np.isfinite(targets.image_xy).all(-1), confidence, 0.0)
        world = targets.world_xyz.astype(np.float64)
        limbs = world[:, points.limbs[:, 1]] - world[:, points.limbs[:, 0]]
        length = np.linalg.norm(limbs, axis=-1, keepdims=True)
        usable = np.isfinite(limbs).all(-1) & (length[..., 0] > 1e-3)
        weight = np.minimum(confidence[:, points.limbs[:, 0]], confidence[:, points.limbs[:, 1]]) * usable
        directions = np.where(usable[..., None], limbs / np.where(length > 1e-3, length, 1.0), 0.0)
        return cls(torch.as_tensor(np.nan_to_num(targets.image_xy.astype(np.float64))),
                   torch.as_tensor(confidence, dtype=torch.float64),
                   torch.as_tensor(directions), torch.as_tensor(weight, dtype=torch.float64))


def _loss(local: torch.Tensor, params: _Parameters, obs: _Observations, skeleton: Skeleton, points: BodyPoints,
          camera: tuple[torch.Tensor, torch.Tensor], config: LandmarkFitConfig, free_joints: torch.Tensor,
          silhouette: SilhouetteTarget | None = None, flow: FlowTarget | None = None) -> torch.Tensor:
    """The fit's objective for the current parameters (a scalar); `silhouette` adds its term, and
    `flow` (with a silhouette, whose surface points it moves) its own; each is None when off."""
    offsets = params.offsets() if config.offset_weight > 0 else None
    global_posed = forward_kinematics(local, torch.tensor(skeleton.rest_joints, dtype=local.dtype), skeleton.parents,
                                      params.translation)
    x_world = _posed_points(skeleton, points, local, params.translation, offsets, global_posed)
    uv, x_camera = _project(camera[0], camera[1], x_world)
    residual = (uv - obs.image_xy).norm(dim=-1)
    loss = (obs.confidence * huber_px(residual, config.huber_px)).sum() / obs.confidence.sum().clamp_min(1.0)
    limbs = x_camera[:, points.limbs[:, 1]] - x_camera[:, points.limbs[:, 0]]
    cosine = (limbs * obs.limb_directions).sum(-1) / limbs.norm(dim=-1).clamp_min(1e-6)
    loss = loss + config.limb_weight * (obs.limb_weight * (1 - cosine)).sum() / obs.limb_weight.sum().clamp_min(1.0)
    if local.shape[0] > 1:
        moving = local[:, torch.cat((torch.zeros(1, dtype=torch.long), free_joints))]
        loss = loss + config.smooth_weight * (moving[1:] - moving[:-1]).square().sum((-1, -2)).mean()
        step = params.translation[1:] - params.translation[:-1]
        loss = loss + config.translation_smooth_weight * step.square().sum(-1).mean()
    loss = loss + config.prior_weight * params.free.square().sum(-1).mean()
    if offsets is not None:
        loss = loss + config.offset_weight * (offsets / OFFSET_SCALE_M).square().sum(-1).mean()
    for slot in _hinge_slots(free_joints, config.hinge_joints):
        rotvec = params.free[:, slot]
        loss = loss + config.hinge_weight * (torch.relu(-rotvec[:, 0]).square() + rotvec[:, 1:].square().sum(-1)).mean()
    if silhouette is not None:
        uv, depth = silhouette.projected(global_posed, camera[0], camera[1])  # once for both image terms
        loss = loss + config.silhouette_weight * silhouette.loss_at(uv, config.coverage_weight)
        if flow is not None:
            loss = loss + config.flow_weight * flow.loss_px(uv, depth)
    return loss


def _hinge_slots(free_joints: torch.Tensor, hinge_joints: tuple[int, ...]) -> list[int]:
    free = free_joints.tolist()
    return [free.index(joint) for joint in hinge_joints if joint in free]


def fit_landmarks(skeleton: Skeleton, points: BodyPoints, free_joints: list[int], K: np.ndarray, w2c: np.ndarray,
                  targets: LandmarkTargets, config: LandmarkFitConfig = LandmarkFitConfig(),
                  silhouette: SilhouetteTarget | None = None, flow: FlowTarget | None = None) -> LandmarkFit:
    """Fit the clip's poses (see the module docstring).

    Args:
        skeleton: the body's skeleton (J joints) with its rest joints (its proportions).
        points: where the landmarks sit on it; free_joints: joints whose rotations are fitted (not 0).
        K: (3, 3) intrinsics; w2c: (4, 4) world-to-camera, fixed for the clip.
        targets: the observations of N frames.
        silhouette: the person's masks and the body's surface, for the last stage (None: no such
            stage; see igavatar.body.silhouette_fit).
        flow: the frames' optical flow, a term of that stage (None: none; igavatar.body.flow_fit).
    Raises:
        InputError: no frame has the torso's landmarks.
    """
    n_frames, n_landmarks = targets.confidence.shape
    if targets.image_xy.shape != (n_frames, n_landmarks, 2) or points.joints.shape != (n_landmarks,):
        raise InputError(f"landmark fit: image_xy {targets.image_xy.shape} and {points.joints.shape[0]} body points "
                         f"do not match confidence {targets.confidence.shape}")
    if silhouette is None or config.silhouette_weight <= 0:
        silhouette = None
    if flow is None or silhouette is None or config.flow_weight <= 0:
        flow = None  # the flow term moves the silhouette stage's points: no stage, no term
    else:
        # The flow follows real motion, so every stage leans less on the smoothness prior.
        config = dataclasses.replace(config, smooth_weight=config.flow_smooth_weight)
    root, translation = initial_root(points, skeleton, K, w2c, targets)
    params = _Parameters(root, translation, len(free_joints), n_landmarks, points.mirror)
    obs = _Observations.of(targets, points)
    camera = (torch.as_tensor(K, dtype=torch.float64), torch.as_tensor(w2c, dtype=torch.float64))
    free = torch.as_tensor(free_joints, dtype=torch.long)
    stages = [([params.root_delta, params.translation], config.root_iterations, None, None),
              (list(params.parameters()), config.iterations, None, None)]
    if silhouette is not None:
        stages.append((list(params.parameters()), config.silhouette_iterations, silhouette, flow))
    for stage_params, iterations, stage_silhouette, stage_flow in stages:
        optimizer = torch.optim.Adam(stage_params, lr=config.learning_rate)
        for _ in range(iterations):
            optimizer.zero_grad(set_to_none=True)
            local = params.local_rotations(skeleton.num_joints, free)
            _loss(local, params, obs, skeleton, points, camera, config, free, stage_silhouette, stage_flow).backward()
            optimizer.step()
    with torch.no_grad():
        local = params.local_rotations(skeleton.num_joints, free)
        offsets = params.offsets() if config.offset_weight > 0 else torch.zeros_like(params.raw_offsets)
        global_posed = forward_kinematics(local, torch.tensor(skeleton.rest_joints, dtype=local.dtype),
                                          skeleton.parents, params.translation)
        x_world = _posed_points(skeleton, points, local, params.translation, offsets, global_posed)
        uv, _ = _project(camera[0], camera[1], x_world)
        residual = (uv - obs.image_xy).norm(dim=-1).numpy()
    residual[obs.confidence.numpy() <= 0] = np.nan
    silhouette_px = None
    if silhouette is not None:
        surface_uv, surface_depth = silhouette.projected(global_posed, *camera)
        silhouette_px = silhouette.mean_distances_px(surface_uv)
        if flow is not None:
            flow_px = flow.mean_px(surface_uv, surface_depth)
            if np.isfinite(flow_px):  # NaN when no point saw reliable flow
                silhouette_px["flow_px"] = flow_px
    return LandmarkFit(local.numpy(), params.translation.detach().numpy(), residual, x_world.numpy(), offsets.numpy(),
                       silhouette_px)

