"""The Anny body fitted to BlazePose landmarks of a clip: camera, proportions, poses.

    camera = VideoCamera.for_frames(height, width, focal_px=None, fov_deg=None)
    body = anny_body_of_height(model, height_m=1.70)
    fit = fit_anny_to_tracks(body, tracks, camera)      # igavatar.body.landmark_fit.LandmarkFit

The world frame is Anny's (+Z up, the subject's rest face towards -Y) with the camera at the
origin, level, looking along +Y: one fixed pinhole camera for the whole clip. Its focal length
is `--focal` in pixels, or from `--fov` (degrees across the longer side), or DEFAULT_FOV_DEG. A
level camera is assumed: a tilted one leaves the body leaning by the tilt, which the root's
rotation absorbs, so the canonical avatar is the same.

The scale of a single view is unknowable from the image: the body's height is `--height`
(DEFAULT_HEIGHT_M), which sets Anny's height phenotype; the other phenotype values stay at Anny's
average. A wrong height scales the avatar and its distance to the camera together, so the
images and the canonical shape's proportions are unchanged; only sizes in meters are off.

BlazePose assumes a frontal view; on some clips it labels a back view as a front one, left and
right swapped. `consistent_facing` relabels such frames so that the body's facing direction turns
smoothly over the clip (a person turning in place keeps turning the same way).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from igavatar.body.anny_body import AnnyBody
from igavatar.body.flow_fit import FlowTarget
from igavatar.body.landmark_fit import BodyPoints, LandmarkFit, LandmarkFitConfig, LandmarkTargets, fit_landmarks
from igavatar.body.silhouette_fit import SilhouetteTarget
from igavatar.capture.person_landmarks import LANDMARK_COUNT, LANDMARKS, MIRROR, PersonTracks
from igavatar.errors import InputError

DEFAULT_FOV_DEG = 50.0
DEFAULT_HEIGHT_M = 1.70
#: Anny's height phenotype in [0, 1] spans about 1.12-2.13 m at the default age.
HEIGHT_RANGE_M = (1.15, 2.10)
#: Landmark -> the Anny bone whose head it is.
_JOINT_LANDMARKS = {
    "left_eye": "eye.L", "right_eye": "eye.R",
    "left_shoulder": "upperarm01.L", "right_shoulder": "upperarm01.R",
    "left_elbow": "lowerarm01.L", "right_elbow": "lowerarm01.R", "left_wrist": "wrist.L", "right_wrist": "wrist.R",
    "left_hip": "upperleg01.L", "right_hip": "upperleg01.R", "left_knee": "lowerleg01.L", "right_knee": "lowerleg01.R",
    "left_ankle": "foot.L", "right_ankle": "foot.R",
}
#: Where BlazePose puts a landmark relative to the point above, meters up (+Z) on Anny's average body
#: (scaled with the height): its shoulders lie above the arm bones' heads, its hips below the
#: thigh bones' heads, its ankles above the foot bone's head. Measured as the mean image offset
#: between Anny's points and BlazePose's landmarks over a synthetic 360-degree turn (synth seed
#: 0, the default subject; tests/benchmarks/results/video-path.md), so the fit does not bend
#: the body to make up for the two models' different definitions of a joint.
LANDMARK_LIFT_M = {
    "nose": 0.035, "left_eye": 0.026, "right_eye": 0.026, "left_ear": 0.013, "right_ear": 0.013,
    "left_shoulder": 0.042, "right_shoulder": 0.042, "left_elbow": 0.016, "right_elbow": 0.016,
    "left_wrist": -0.004, "right_wrist": -0.004, "left_hip": -0.043, "right_hip": -0.043,
    "left_knee": -0.006, "right_knee": -0.006, "left_ankle": 0.037, "right_ankle": 0.037,
    "left_heel": 0.016, "right_heel": 0.016, "left_foot_index": 0.016, "right_foot_index": 0.016,
}
#: The height of the body LANDMARK_LIFT_M was measured on.
LIFT_BODY_HEIGHT_M = 1.626
#: Bones whose rotations are fitted; the rest stay at Anny's rest pose.
FREE_BONES = ("spine05", "spine03", "spine01", "neck01", "head", "upperarm01.L", "upperarm01.R",
              "lowerarm01.L", "lowerarm01.R", "upperleg01.L", "upperleg01.R", "lowerleg01.L", "lowerleg01.R",
              "foot.L", "foot.R")
HINGE_BONES = ("lowerleg01.L", "lowerleg01.R")
_LIMBS = (("left_shoulder", "left_elbow"), ("left_elbow", "left_wrist"), ("right_shoulder", "right_elbow"),
          ("right_elbow", "right_wrist"), ("left_hip", "left_knee"), ("left_knee", "left_ankle"),
          ("right_hip", "right_knee"), ("right_knee", "right_ankle"), ("left_hip", "left_shoulder"),
          ("right_hip", "right_shoulder"), ("right_shoulder", "left_shoulder"), ("right_hip", "left_hip"),
          ("left_ankle", "left_foot_index"), ("right_ankle", "right_foot_index"), ("left_shoulder", "nose"),
          ("right_shoulder", "nose"))
#: Face landmarks count less: BlazePose puts them on the back of the head in back views.
FACE_WEIGHT = 0.3
_FACE = ("nose", "left_eye", "right_eye", "left_ear", "right_ear")


@dataclass(frozen=True)
class VideoCamera:
    """One fixed pinhole camera: K (3, 3), w2c (4, 4), image height and width, and where f came from."""

    K: np.ndarray
    w2c: np.ndarray
    height: int
    width: int
    focal_source: str

    @classmethod
    def for_frames(cls, height: int, width: int, focal_px: float | None = None, fov_deg: float | None = None) -> "VideoCamera":
        if focal_px is not None and fov_deg is not None:
            raise InputError("give --focal or --fov, not both")
        if focal_px is not None:
            if not focal_px > 0:
                raise InputError(f"--focal {focal_px}: must be > 0 (pixels of the frames as read)")
            focal, source = float(focal_px), "--focal"
        else:
            fov = DEFAULT_FOV_DEG if fov_deg is None else float(fov_deg)
            if not 5.0 <= fov <= 150.0:
                raise InputError(f"--fov {fov}: expected degrees across the longer side, between 5 and 150")
            focal = 0.5 * max(height, width) / np.tan(np.radians(fov) / 2)
            source = "--fov" if fov_deg is not None else f"default field of view {DEFAULT_FOV_DEG:g} deg"
        K = np.array([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]])
        # Level camera at the origin looking along +Y: camera x = world x, y = -world z, z = world y.
        w2c = np.array([[1.0, 0, 0, 0], [0, 0, -1.0, 0], [0, 1.0, 0, 0], [0, 0, 0, 1.0]])
        return cls(K, w2c, int(height), int(width), source)


def anny_body_of_height(body: AnnyBody, height_m: float) -> AnnyBody:
    """`body`'s model with the height phenotype that makes the rest mesh `height_m` tall (others 0.5)."""
    if not HEIGHT_RANGE_M[0] <= height_m <= HEIGHT_RANGE_M[1]:
        raise InputError(f"--height {height_m}: expected the person's height in meters, "
                         f"{HEIGHT_RANGE_M[0]}-{HEIGHT_RANGE_M[1]}")

    def tallness(value: float) -> tuple[AnnyBody, float]:
        candidate = body.with_phenotype({"height": value})
        z = candidate.rest_vertices[:, 2]
        return candidate, float(z.max() - z.min())

    low, high = (0.0, tallness(0.0)[1]), (1.0, tallness(1.0)[1])
    candidate = body
    for _ in range(6):  # secant steps: height is nearly linear in the phenotype value
        value = float(np.clip(low[0] + (height_m - low[1]) * (high[0] - low[0]) / (high[1] - low[1]), 0.0, 1.0))
        candidate, reached = tallness(value)
        if abs(reached - height_m) < 1e-3:
            break
        if reached < height_m:
            low = (value, reached)
        else:
            high = (value, reached)
    return candidate


def anny_landmark_points(body: AnnyBody) -> BodyPoints:
    """Where BlazePose's 33 landmarks sit on Anny's rest body (hands and mouth are not modelled)."""
    skeleton = body.skeleton
    joints = np.full(LANDMARK_COUNT, -1, dtype=np.int64)
    rest_points = np.zeros((LANDMARK_COUNT, 3))
    for landmark, bone in _JOINT_LANDMARKS.items():
        joints[LANDMARKS[landmark]] = skeleton.index(bone)
        rest_points[LANDMARKS[landmark]] = skeleton.rest_joints[skeleton.index(bone)]
    vertices = body.rest_vertices.double().numpy()
    head = skeleton.index("head")
    eye_z = float(skeleton.rest_joints[skeleton.index("eye.L"), 2])
    face_band = vertices[np.abs(vertices[:, 2] - (eye_z - 0.03)) < 0.02]
    ear_band = vertices[np.abs(vertices[:, 2] - eye_z) < 0.015]
    surface = {"nose": face_band[np.argmin(face_band[:, 1] + 10 * np.abs(face_band[:, 0]))],
               "left_ear": ear_band[np.argmax(ear_band[:, 0])], "right_ear": ear_band[np.argmin(ear_band[:, 0])]}
    for side in ("L", "R"):
        name = "left" if side == "L" else "right"
        foot = vertices[(np.sign(vertices[:, 0]) == (1 if side == "L" else -1)) & (vertices[:, 2] < vertices[:, 2].min() + 0.04)]
        surface[f"{name}_heel"] = foot[np.argmax(foot[:, 1])]
        surface[f"{name}_foot_index"] = foot[np.argmin(foot[:, 1])]
    for landmark, point in surface.items():
        bone = "head" if landmark in ("nose", "left_ear", "right_ear") else ("foot.L" if landmark.startswith("left") else "foot.R")
        joints[LANDMARKS[landmark]] = head if bone == "head" else skeleton.index(bone)
        rest_points[LANDMARKS[landmark]] = point
    z = vertices[:, 2]
    scale = float(z.max() - z.min()) / LIFT_BODY_HEIGHT_M
    for landmark, lift in LANDMARK_LIFT_M.items():
        rest_points[LANDMARKS[landmark], 2] += scale * lift
    limbs = np.array([[LANDMARKS[a], LANDMARKS[b]] for a, b in _LIMBS])
    torso = (LANDMARKS["left_shoulder"], LANDMARKS["right_shoulder"], LANDMARKS["left_hip"], LANDMARKS["right_hip"])
    # Anny: the subject's left is +X, up +Z, the face looks towards -Y.
    return BodyPoints(joints, rest_points, limbs, torso, np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]), MIRROR)


def facing_yaw(world_xyz: np.ndarray) -> np.ndarray:
    """(N,) yaw in radians of the body's facing direction from world landmarks (N, 33, 3) in
    camera axes: 0 faces the camera, +-pi faces away; NaN where the torso is missing."""
    w = world_xyz.astype(np.float64)
    left = (w[:, 11] - w[:, 12]) + (w[:, 23] - w[:, 24])
    up = 0.5 * (w[:, 11] + w[:, 12]) - 0.5 * (w[:, 23] + w[:, 24])
    facing = np.cross(left, up)
    return np.arctan2(facing[:, 0], -facing[:, 2])


def _mirrored(world_xyz: np.ndarray) -> np.ndarray:
    """World landmarks of the other reading of a view: left and right swapped, depth reversed."""
    return world_xyz[:, MIRROR] * np.array([1.0, 1.0, -1.0])


def _wrap(angle: np.ndarray) -> np.ndarray:
    return (angle + np.pi) % (2 * np.pi) - np.pi


#: Cost (radians of turning) of reading a frame against BlazePose's labels, per frame: a tie-break
#: towards its labels. It must stay far below the turning speed's change it saves: a back half of
#: 17 frames read against a turn saves about 0.6 rad in all.
RELABEL_COST = 0.005
#: Cost (radians) of changing the reading between two frames. A misread back view spans many
#: frames; a lone relabelled frame at a side view (where both readings nearly agree) was a wrong
#: call on a synthetic turn (its joints 9 cm off): two switches cost more than such a frame saves.
SWITCH_COST = 0.3


def consistent_facing(world_xyz: np.ndarray) -> np.ndarray:
    """(N,) bool: frames whose labels to mirror so that the facing direction turns smoothly.

    Each frame has two readings, as given or mirrored (left-right swapped, depth reversed: the
    back view of the same silhouette). A dynamic program over pairs of consecutive readings picks
    the sequence whose turning speed changes least (a turn keeps going; BlazePose's frontal
    reading of a turn swings back at the side views), plus a little turning, a tie-break
    (RELABEL_COST) per mirrored frame and SWITCH_COST per change of reading. Frames without a torso keep their labels and do not break the chain.
    """
    yaw = np.stack([facing_yaw(world_xyz), facing_yaw(_mirrored(world_xyz))], axis=1)  # (N, 2)
    valid = np.flatnonzero(np.isfinite(yaw).all(axis=1))
    flips = np.zeros(len(world_xyz), dtype=bool)
    if len(valid) < 3:
        return flips
    y = yaw[valid]
    # cost[a, b]: best cost of a sequence ending with readings a (previous frame) and b (this one).
    step = np.abs(_wrap(y[1][None, :] - y[0][:, None]))
    readings = np.arange(2)
    switch = SWITCH_COST * (readings[:, None] != readings[None, :])
    cost = 0.1 * step + RELABEL_COST * (readings[:, None] + readings[None, :]) + switch
    back: list[np.ndarray] = []
    for t in range(2, len(y)):
        velocity_prev = _wrap(y[t - 1][None, :] - y[t - 2][:, None])  # [a, b]
        velocity = _wrap(y[t][None, :] - y[t - 1][:, None])           # [b, c]
        total = (cost[:, :, None] + np.abs(_wrap(velocity[None] - velocity_prev[:, :, None]))
                 + 0.1 * np.abs(velocity)[None] + RELABEL_COST * readings[None, None, :] + switch[None])
        back.append(total.argmin(axis=0))                             # best a for each (b, c)
        cost = total.min(axis=0)
    b, c = np.unravel_index(int(cost.argmin()), cost.shape)
    path = [c, b]
    for choice in reversed(back):
        path.append(choice[path[-1], path[-2]])
    flips[valid] = np.array(path[::-1], dtype=bool)
    return flips


def relabelled(tracks: PersonTracks, flips: np.ndarray) -> PersonTracks:
    """Tracks with the `flips` frames' landmarks mirrored (labels swapped, world depth reversed)."""
    image_xy, visibility, world = tracks.image_xy.copy(), tracks.visibility.copy(), tracks.world_xyz.copy()
    image_xy[flips] = image_xy[flips][:, MIRROR]
    visibility[flips] = visibility[flips][:, MIRROR]
    world[flips] = _mirrored(world[flips])
    return PersonTracks(tracks.detected, tracks.masks, tracks.people, image_xy, visibility, world)


def landmark_targets(tracks: PersonTracks) -> LandmarkTargets:
    """The fit's targets: visibility as confidence, face landmarks down-weighted."""
    confidence = np.clip(tracks.visibility.astype(np.float64), 0.0, 1.0)
    confidence[:, [LANDMARKS[name] for name in _FACE]] *= FACE_WEIGHT
    confidence[~tracks.detected] = 0.0
    return LandmarkTargets(tracks.image_xy.astype(np.float64), confidence, tracks.world_xyz.astype(np.float64))


def fit_anny_to_tracks(body: AnnyBody, tracks: PersonTracks, camera: VideoCamera,
                       config: LandmarkFitConfig | None = None, images: list[np.ndarray] | None = None) -> LandmarkFit:
    """Anny's poses over the clip (every frame of `tracks` must have a detection); `images`, the
    frames ((H, W, 3) uint8 RGB each), add the optical-flow term to the silhouette stage."""
    skeleton = body.skeleton
    config = config or LandmarkFitConfig(hinge_joints=tuple(skeleton.index(b) for b in HINGE_BONES))
    free = [skeleton.index(bone) for bone in FREE_BONES]
    silhouette = None
    if config.silhouette_weight > 0:
        silhouette = SilhouetteTarget.of(tracks.masks, body.rest_vertices.numpy(), body.skinning_weights.numpy(),
                                         skeleton.rest_joints, config.silhouette_points)
    flow = None
    if silhouette is not None and config.flow_weight > 0 and images is not None and len(images) > 1:
        flow = FlowTarget.of(images, tracks.masks)
    return fit_landmarks(skeleton, anny_landmark_points(body), free, camera.K, camera.w2c,
                         landmark_targets(tracks), config, silhouette, flow)
