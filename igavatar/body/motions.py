"""Procedural motions (turntable, walk, arm raise, squat, turn) for any supported skeleton kind.

    motion = motion_by_name("walk", "anny", n_frames=90, seed=0)
    rotations = motion.local_rotations_for(body.skeleton)        # (N, J, 3, 3), unnamed joints at rest

Motions are written in body-centric terms ("flex the left knee by 40 degrees", "raise the arms
sideways to 150 degrees") in a body frame with axes left, up, forward, and converted per skeleton
kind: Anny's world is +Z up with the face towards -Y; SMPL's is +Y up with the face towards +Z; in
both the subject's left is +X. Since every rest frame is world-aligned (SMPL convention), a body-frame
rotation becomes a world-aligned local rotation by conjugation with the body-to-world rotation.
Rest poses differ (Anny: A-pose, SMPL: T-pose), so arm angles are absolute (angle of the upper arm
from straight down), measured against the skeleton's rest arms; every motion starts from the
"neutral" stance: the rest pose, except that arms raised above NEUTRAL_ARM_ABDUCTION (a T-pose) are
lowered to it. Anny's neutral stance is its rest pose. Angles in radians, lengths in meters.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np
import torch

from igavatar.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from igavatar.body.skeleton import Skeleton
from igavatar.errors import InputError

SKELETON_KINDS: tuple[str, ...] = ("anny", "smpl")
MOTION_NAMES: tuple[str, ...] = ("turntable", "walk", "arm_raise", "squat", "turn")

NEUTRAL_ARM_ABDUCTION = 0.8
"""Largest upper-arm angle from straight down (rad, ~46 degrees) kept in the neutral stance."""

_SIDES = (("left", 1.0), ("right", -1.0))
_LIMB_PARTS = ("collar", "upper_arm", "forearm", "hand", "thigh", "shin", "foot")
SEMANTIC_JOINTS: tuple[str, ...] = (
    "pelvis", "spine_lower", "spine_mid", "spine_upper", "neck", "head",
) + tuple(f"{side}_{part}" for side, _ in _SIDES for part in _LIMB_PARTS)
"""Body parts the motions drive; "pelvis" is the skeleton's root."""

ROOT_FINDING_PARTS: tuple[str, ...] = (
    "pelvis", "spine_mid", "neck", "head",
) + tuple(f"{side}_{part}" for side, _ in _SIDES for part in ("thigh", "shin", "foot", "upper_arm", "forearm"))
"""Major bones that Fast-SNARF starts root finding from (SMPL's 13 plus the mid spine)."""

_ANNY_JOINTS = {
    "pelvis": "root", "spine_lower": "spine05", "spine_mid": "spine03", "spine_upper": "spine01",
    "neck": "neck01", "head": "head",
}
_SMPL_JOINTS = {
    "pelvis": "pelvis", "spine_lower": "spine1", "spine_mid": "spine2", "spine_upper": "spine3",
    "neck": "neck", "head": "head",
}
for _side, _ in _SIDES:
    _suffix = "L" if _side == "left" else "R"
    _ANNY_JOINTS.update({
        f"{_side}_collar": f"clavicle.{_suffix}", f"{_side}_upper_arm": f"upperarm01.{_suffix}",
        f"{_side}_forearm": f"lowerarm01.{_suffix}", f"{_side}_hand": f"wrist.{_suffix}",
        f"{_side}_thigh": f"upperleg01.{_suffix}", f"{_side}_shin": f"lowerleg01.{_suffix}",
        f"{_side}_foot": f"foot.{_suffix}",
    })
    _SMPL_JOINTS.update({
        f"{_side}_collar": f"{_side}_collar", f"{_side}_upper_arm": f"{_side}_shoulder",
        f"{_side}_forearm": f"{_side}_elbow", f"{_side}_hand": f"{_side}_wrist",
        f"{_side}_thigh": f"{_side}_hip", f"{_side}_shin": f"{_side}_knee",
        f"{_side}_foot": f"{_side}_ankle",
    })

_JOINT_MAPS: Mapping[str, Mapping[str, str]] = MappingProxyType(
    {"anny": MappingProxyType(_ANNY_JOINTS), "smpl": MappingProxyType(_SMPL_JOINTS)}
)
# Columns: the body's left, up and forward directions in each skeleton kind's world frame.
_BODY_TO_WORLD = {
    "anny": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
    "smpl": np.eye(3),
}

# Body-frame axes.
LEFT = np.array([1.0, 0.0, 0.0])
UP = np.array([0.0, 1.0, 0.0])
FORWARD = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class BodyProportions:
    """The few rest-pose measurements the motions need (a skeleton's, or a kind's nominal ones).

    Attributes:
        arm_abduction: rest angle (rad) of the upper arms from straight down in the frontal plane.
        thigh_length, shin_length: hip-to-knee and knee-to-ankle lengths (m) in the sagittal plane.
        thigh_tilt, shin_tilt: their rest forward tilt from straight down (rad).
    """

    arm_abduction: float
    thigh_length: float
    shin_length: float
    thigh_tilt: float = 0.0
    shin_tilt: float = 0.0

    @property
    def leg_height(self) -> float:
        """Rest height (m) of the hip above the ankle."""
        return self.thigh_length * np.cos(self.thigh_tilt) + self.shin_length * np.cos(self.shin_tilt)


# Anny default phenotype (measured from its rest bone heads); SMPL: a typical neutral T-pose.
_NOMINAL_PROPORTIONS = {
    "anny": BodyProportions(
        arm_abduction=0.727, thigh_length=0.390, shin_length=0.400, thigh_tilt=0.083, shin_tilt=-0.091
    ),
    "smpl": BodyProportions(arm_abduction=1.54, thigh_length=0.39, shin_length=0.43),
}


def _check_kind(skeleton_kind: str) -> str:
    if skeleton_kind not in SKELETON_KINDS:
        raise InputError(
            f"motions: unknown skeleton kind {skeleton_kind!r}; valid kinds: {', '.join(SKELETON_KINDS)}"
        )
    return skeleton_kind


def semantic_joint_map(skeleton_kind: str) -> Mapping[str, str]:
    """Semantic body part -> joint name of `skeleton_kind` ("anny" bone labels or SMPL names)."""
    return _JOINT_MAPS[_check_kind(skeleton_kind)]


def body_to_world(skeleton_kind: str) -> np.ndarray:
    """(3, 3) rotation whose columns are the body's left, up, forward axes in the kind's world."""
    return _BODY_TO_WORLD[_check_kind(skeleton_kind)].copy()


def measure_proportions(skeleton_kind: str, skeleton: Skeleton | None = None) -> BodyProportions:
    """BodyProportions of `skeleton` (rest joints), or the kind's nominal ones when None."""
    if skeleton is None:
        return _NOMINAL_PROPORTIONS[_check_kind(skeleton_kind)]
    names = semantic_joint_map(skeleton_kind)
    world_to_body = body_to_world(skeleton_kind).T

    def joint(part: str) -> np.ndarray:
        return world_to_body @ skeleton.rest_joints[skeleton.index(names[part])]

    def sagittal(start: str, end: str) -> tuple[float, float]:
        """Length and forward tilt of a segment projected on the sagittal (up, forward) plane."""
        segment = joint(end) - joint(start)
        return float(np.hypot(segment[1], segment[2])), float(np.arctan2(segment[2], -segment[1]))

    measures = []
    for side, sign in _SIDES:
        arm = joint(f"{side}_forearm") - joint(f"{side}_upper_arm")
        thigh = sagittal(f"{side}_thigh", f"{side}_shin")
        shin = sagittal(f"{side}_shin", f"{side}_foot")
        measures.append((np.arctan2(sign * arm[0], -arm[1]), thigh[0], shin[0], thigh[1], shin[1]))
    return BodyProportions(*(float(value) for value in np.mean(measures, axis=0)))


@dataclass(frozen=True, eq=False)
class Motion:
    """A pose sequence for the named joints of one skeleton kind (others stay at rest).

    Attributes:
        joint_names: J joint names (the skeleton's own names; generated motions include the root).
        local_rotvecs: (N, J, 3) float64 axis-angle rotations relative to the rest pose in
            world-aligned rest frames (the forward_kinematics convention).
        root_translation: (N, 3) float64 world translation of the root from its rest position (m).
        fps: frames per second.
        name: the motion's name. skeleton_kind: "anny" or "smpl".
    """

    joint_names: tuple[str, ...]
    local_rotvecs: np.ndarray
    root_translation: np.ndarray
    fps: float
    name: str = "motion"
    skeleton_kind: str = ""

    def __post_init__(self) -> None:
        names = tuple(str(n) for n in self.joint_names)
        if len(set(names)) != len(names):
            raise InputError(f"motion {self.name!r}: duplicate joint names in {names}")
        rotvecs = np.array(self.local_rotvecs, dtype=np.float64)
        translation = np.array(self.root_translation, dtype=np.float64)
        if rotvecs.ndim != 3 or rotvecs.shape[1:] != (len(names), 3) or rotvecs.shape[0] < 1:
            raise InputError(
                f"motion {self.name!r}: local_rotvecs has shape {rotvecs.shape}, "
                f"expected (N, {len(names)}, 3) with N >= 1"
            )
        if translation.shape != (rotvecs.shape[0], 3):
            raise InputError(
                f"motion {self.name!r}: root_translation has shape {translation.shape}, "
                f"expected ({rotvecs.shape[0]}, 3)"
            )
        if not (np.all(np.isfinite(rotvecs)) and np.all(np.isfinite(translation))):
            raise InputError(f"motion {self.name!r}: contains NaN or infinite values")
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise InputError(f"motion {self.name!r}: fps = {self.fps}, expected a positive number")
        rotvecs.setflags(write=False)
        translation.setflags(write=False)
        object.__setattr__(self, "joint_names", names)
        object.__setattr__(self, "local_rotvecs", rotvecs)
        object.__setattr__(self, "root_translation", translation)
        object.__setattr__(self, "fps", float(self.fps))

    @property
    def n_frames(self) -> int:
        """N, the number of frames."""
        return int(self.local_rotvecs.shape[0])

    def rotvecs_for(self, joint_names: Sequence[str]) -> np.ndarray:
        """(N, len(joint_names), 3) rotvecs in that joint order; joints the motion does not name
        stay at rest (zero). InputError if a motion joint is missing from `joint_names`."""
        index = {name: i for i, name in enumerate(joint_names)}
        missing = [name for name in self.joint_names if name not in index]
        if missing:
            raise InputError(
                f"motion {self.name!r} ({self.skeleton_kind or 'unknown'} skeleton) drives joints "
                f"{missing} that the target skeleton does not have"
            )
        out = np.zeros((self.n_frames, len(joint_names), 3), dtype=np.float64)
        out[:, [index[name] for name in self.joint_names]] = self.local_rotvecs
        return out

    def local_rotations_for(
        self,
        skeleton: Skeleton,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> torch.Tensor:
        """(N, J, 3, 3) local rotations for every joint of `skeleton` (see rotvecs_for)."""
        rotvecs = torch.as_tensor(self.rotvecs_for(skeleton.joint_names), dtype=torch.float64)
        return axis_angle_to_matrix(rotvecs).to(dtype=dtype, device=device)

    def root_translation_tensor(
        self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
    ) -> torch.Tensor:
        """root_translation as an (N, 3) tensor."""
        return torch.tensor(self.root_translation, dtype=dtype, device=device)


class _BodyPose:
    """Per-frame body-frame rotations of semantic joints, composed in the order they are applied."""

    def __init__(self, n_frames: int) -> None:
        self.n_frames = n_frames
        self.rotations: dict[str, torch.Tensor] = {}
        self.translation = np.zeros((n_frames, 3))

    def rotate(self, part: str, axis: np.ndarray, angle: np.ndarray | float) -> None:
        """Rotate `part` by `angle` (N,) or scalar about the body-frame `axis`, after what it has."""
        angles = np.broadcast_to(np.asarray(angle, dtype=np.float64), (self.n_frames,))
        rotvec = torch.as_tensor(angles[:, None] * axis[None, :], dtype=torch.float64)
        rotation = axis_angle_to_matrix(rotvec)
        previous = self.rotations.get(part)
        self.rotations[part] = rotation if previous is None else rotation @ previous

    def to_motion(self, name: str, skeleton_kind: str, fps: float) -> Motion:
        to_world = torch.as_tensor(body_to_world(skeleton_kind))
        names = semantic_joint_map(skeleton_kind)
        parts = [part for part in SEMANTIC_JOINTS if part in self.rotations or part == "pelvis"]
        identity = torch.eye(3, dtype=torch.float64).expand(self.n_frames, 3, 3)
        world = torch.stack(
            [to_world @ self.rotations.get(part, identity) @ to_world.T for part in parts], dim=1
        )
        return Motion(
            joint_names=tuple(names[part] for part in parts),
            local_rotvecs=matrix_to_axis_angle(world).numpy(),
            root_translation=self.translation @ to_world.numpy().T,
            fps=fps,
            name=name,
            skeleton_kind=skeleton_kind,
        )


def _times(n_frames: int, fps: float) -> np.ndarray:
    if int(n_frames) != n_frames or n_frames < 1:
        raise InputError(f"motions: n_frames = {n_frames}, expected a positive integer")
    if not (np.isfinite(fps) and fps > 0):
        raise InputError(f"motions: fps = {fps}, expected a positive number")
    return np.arange(int(n_frames)) / float(fps)


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _ramp_in(t: np.ndarray, seconds: float = 0.5) -> np.ndarray:
    """0 at the first frame rising smoothly to 1, so that every motion starts from neutral."""
    duration = float(t[-1])
    if duration <= 0.0:
        return np.zeros_like(t)
    return _smoothstep(t / min(seconds, 0.25 * duration))


def _neutral_stance(pose: _BodyPose, proportions: BodyProportions) -> float:
    """Lower raised rest arms to the neutral stance; returns the neutral arm abduction."""
    neutral = min(proportions.arm_abduction, NEUTRAL_ARM_ABDUCTION)
    for side, sign in _SIDES:
        if neutral != proportions.arm_abduction:
            pose.rotate(f"{side}_upper_arm", FORWARD, sign * (neutral - proportions.arm_abduction))
    return neutral


def _elbow_axis(proportions: BodyProportions, sign: float) -> np.ndarray:
    """Body-frame elbow hinge of one arm: perpendicular to the rest upper arm and to forward,
    oriented so that a positive angle swings the forearm forward."""
    a = proportions.arm_abduction
    return np.array([-np.cos(a), -sign * np.sin(a), 0.0])


def _leg_extent(proportions: BodyProportions, hip_flexion: np.ndarray, knee_flexion: np.ndarray):
    """(vertical, forward) offsets (m) of the ankle below / ahead of the hip for sagittal leg angles,
    relative to the rest pose's."""
    thigh, shin = proportions.thigh_length, proportions.shin_length
    thigh_angle = proportions.thigh_tilt + hip_flexion
    shin_angle = proportions.shin_tilt + hip_flexion - knee_flexion  # forward tilt from straight down
    vertical = thigh * np.cos(thigh_angle) + shin * np.cos(shin_angle) - proportions.leg_height
    forward = (
        thigh * (np.sin(thigh_angle) - np.sin(proportions.thigh_tilt))
        + shin * (np.sin(shin_angle) - np.sin(proportions.shin_tilt))
    )
    return vertical, forward


def _flex_leg(pose: _BodyPose, side: str, hip: np.ndarray, knee: np.ndarray, ankle: np.ndarray) -> None:
    """Sagittal leg motion: hip flexion (thigh forward), knee flexion (shin back), ankle angle
    (positive tips the toes up)."""
    pose.rotate(f"{side}_thigh", LEFT, -hip)
    pose.rotate(f"{side}_shin", LEFT, knee)
    pose.rotate(f"{side}_foot", LEFT, -ankle)


def turntable(
    skeleton_kind: str,
    n_frames: int = 120,
    seed: int = 0,
    *,
    small_motion: bool = True,
    fps: float = 30.0,
    skeleton: Skeleton | None = None,
) -> Motion:
    """The subject turns 360 degrees in place (to its left, about the vertical through the pelvis)
    in the neutral A-pose, frame i at 360 * i / N degrees; with `small_motion`, slight arm sway,
    breathing-like spine motion and head motion (PeopleSnapshot-like)."""
    t = _times(n_frames, fps)
    rng = np.random.default_rng(seed)
    proportions = measure_proportions(skeleton_kind, skeleton)
    pose = _BodyPose(len(t))
    _neutral_stance(pose, proportions)
    if small_motion:
        envelope = _ramp_in(t, 1.0)

        def wave(amplitude: float, low_hz: float, high_hz: float) -> np.ndarray:
            frequency, phase = rng.uniform(low_hz, high_hz), rng.uniform(0.0, 2.0 * np.pi)
            return amplitude * envelope * np.sin(2.0 * np.pi * frequency * t + phase)

        breathing = wave(0.02, 0.2, 0.3)
        for part in ("spine_lower", "spine_mid", "spine_upper"):
            pose.rotate(part, LEFT, breathing)
        pose.rotate("head", UP, wave(0.12, 0.1, 0.2))
        pose.rotate("head", LEFT, wave(0.06, 0.15, 0.3))
        for side, sign in _SIDES:
            pose.rotate(f"{side}_upper_arm", FORWARD, sign * wave(0.05, 0.2, 0.4))
            pose.rotate(f"{side}_upper_arm", LEFT, wave(0.05, 0.2, 0.4))
            pose.rotate(f"{side}_forearm", _elbow_axis(proportions, sign), wave(0.05, 0.2, 0.4))
    pose.rotate("pelvis", UP, 2.0 * np.pi * np.arange(len(t)) / len(t))
    return pose.to_motion("turntable", skeleton_kind, fps)


def walk(
    skeleton_kind: str,
    n_frames: int = 90,
    seed: int = 0,
    *,
    fps: float = 30.0,
    in_place: bool = False,
    skeleton: Skeleton | None = None,
) -> Motion:
    """Walking forward (about 0.8 m/s; `in_place` keeps the pelvis over the origin): alternating
    leg swing with knee flexion in swing, counter-swinging arms, slight pelvis and spine rotation;
    the pelvis height follows the supporting leg so that the feet stay on the ground."""
    t = _times(n_frames, fps)
    rng = np.random.default_rng(seed)
    proportions = measure_proportions(skeleton_kind, skeleton)
    pose = _BodyPose(len(t))
    neutral = _neutral_stance(pose, proportions)
    envelope = _ramp_in(t, 0.6)
    cycle_hz = rng.uniform(0.85, 1.0)
    amplitude = rng.uniform(0.3, 0.36)
    phase = 2.0 * np.pi * cycle_hz * t

    extents, advance = [], []
    for side, sign in _SIDES:
        leg_phase = phase if side == "left" else phase + np.pi
        hip = envelope * (0.08 + amplitude * np.sin(leg_phase))
        # The knee flexes while the leg swings forward (hip flexion increasing, cos > 0), peaking
        # when the thigh is already ahead so that the shin tilts back by ~40 degrees, not more.
        knee = envelope * (0.06 + 0.95 * np.clip(np.cos(leg_phase - 0.4), 0.0, None) ** 2)
        ankle = 0.7 * (knee - hip)  # mostly flattens the foot (its pitch is knee - hip - ankle)
        _flex_leg(pose, side, hip, knee, ankle)
        vertical, forward = _leg_extent(proportions, hip, knee)
        extents.append(vertical)
        advance.append(forward)
        # Each arm swings with the opposite leg.
        arm_swing = -envelope * 1.1 * amplitude * np.sin(leg_phase)
        pose.rotate(f"{side}_upper_arm", FORWARD, sign * envelope * (0.25 - neutral))
        pose.rotate(f"{side}_upper_arm", LEFT, -arm_swing)
        pose.rotate(f"{side}_forearm", _elbow_axis(proportions, sign),
                    envelope * (0.1 + 0.3 * np.clip(arm_swing, 0.0, None)))
    # Pelvis yaw towards the forward leg and the shoulders countering it.
    pose.rotate("pelvis", UP, envelope * 0.08 * np.sin(phase))
    pose.rotate("spine_mid", UP, -envelope * 0.07 * np.sin(phase))
    pose.rotate("spine_upper", UP, -envelope * 0.05 * np.sin(phase))
    # The supporting (longest) leg keeps its ankle at the rest height.
    pose.translation[:, 1] = np.maximum(extents[0], extents[1])
    if not in_place:
        # Step length from the leg's reach, two steps per cycle.
        step = proportions.leg_height * (np.sin(0.08 + amplitude) + np.sin(amplitude - 0.08))
        speed = 2.0 * step * cycle_hz
        pose.translation[:, 2] = np.concatenate(([0.0], np.cumsum(speed * envelope[1:] / fps)))
    return pose.to_motion("walk", skeleton_kind, fps)


def arm_raise(
    skeleton_kind: str,
    n_frames: int = 90,
    seed: int = 0,
    *,
    fps: float = 30.0,
    skeleton: Skeleton | None = None,
) -> Motion:
    """Both arms rise sideways from the neutral stance to 140-160 degrees and back down, once over
    the sequence (the right arm lagging slightly), with a small forward component."""
    t = _times(n_frames, fps)
    rng = np.random.default_rng(seed)
    proportions = measure_proportions(skeleton_kind, skeleton)
    pose = _BodyPose(len(t))
    neutral = _neutral_stance(pose, proportions)
    top = rng.uniform(np.radians(140.0), np.radians(160.0))
    lag = rng.uniform(0.0, 0.08)
    progress = np.arange(len(t)) / max(len(t) - 1, 1)
    for side, sign in _SIDES:
        shifted = np.clip(progress - (lag if side == "right" else 0.0), 0.0, 1.0) / (
            1.0 - (lag if side == "right" else 0.0)
        )
        lift = 0.5 * (1.0 - np.cos(2.0 * np.pi * shifted))
        pose.rotate(f"{side}_upper_arm", FORWARD, sign * (top - neutral) * lift)
        pose.rotate(f"{side}_upper_arm", LEFT, -0.25 * lift)
    return pose.to_motion("arm_raise", skeleton_kind, fps)


def squat(
    skeleton_kind: str,
    n_frames: int = 90,
    seed: int = 0,
    *,
    fps: float = 30.0,
    skeleton: Skeleton | None = None,
) -> Motion:
    """Squats (one per ~3 s, at least one): hips and knees flex, the feet stay flat and in place
    (the pelvis is lowered and moved back accordingly), the torso leans and the arms reach forward."""
    t = _times(n_frames, fps)
    rng = np.random.default_rng(seed)
    proportions = measure_proportions(skeleton_kind, skeleton)
    pose = _BodyPose(len(t))
    neutral = _neutral_stance(pose, proportions)
    depth_max = rng.uniform(0.8, 1.0)
    repetitions = max(1, int(round(float(t[-1]) / 3.0)))
    progress = np.arange(len(t)) / max(len(t) - 1, 1)
    depth = depth_max * 0.5 * (1.0 - np.cos(2.0 * np.pi * repetitions * progress))
    hip, knee = 1.45 * depth, 2.0 * depth
    for side, sign in _SIDES:
        _flex_leg(pose, side, hip, knee, knee - hip)  # keeps each foot flat on the floor
        pose.rotate(f"{side}_upper_arm", FORWARD, sign * (0.15 - neutral) * depth / depth_max)
        pose.rotate(f"{side}_upper_arm", LEFT, -1.3 * depth)
    for part in ("spine_lower", "spine_mid", "spine_upper"):
        pose.rotate(part, LEFT, 0.15 * depth)
    pose.rotate("head", LEFT, -0.2 * depth)  # keeps the gaze level while the torso leans
    vertical, forward = _leg_extent(proportions, hip, knee)
    pose.translation[:, 1] = vertical
    pose.translation[:, 2] = -forward
    return pose.to_motion("squat", skeleton_kind, fps)


def turn(
    skeleton_kind: str,
    n_frames: int = 90,
    seed: int = 0,
    *,
    fps: float = 30.0,
    skeleton: Skeleton | None = None,
) -> Motion:
    """The subject turns on the spot by 90-180 degrees (direction from the seed), stepping with
    alternate feet while turning, the head leading the turn."""
    t = _times(n_frames, fps)
    rng = np.random.default_rng(seed)
    proportions = measure_proportions(skeleton_kind, skeleton)
    pose = _BodyPose(len(t))
    _neutral_stance(pose, proportions)
    angle = rng.choice([-1.0, 1.0]) * rng.uniform(np.pi / 2.0, np.pi)
    progress = np.arange(len(t)) / max(len(t) - 1, 1)
    turning = _smoothstep((progress - 0.15) / 0.7)
    yaw = angle * turning
    # The head looks ahead of the body: towards where the body will be a short while later.
    lead = angle * _smoothstep((progress - 0.05) / 0.7) - yaw
    activity = np.sin(np.pi * np.clip((progress - 0.15) / 0.7, 0.0, 1.0))  # 0 at rest, 1 mid-turn
    step_phase = 2.0 * np.pi * rng.uniform(1.4, 1.8) * np.clip(t - 0.15 * t[-1], 0.0, None)
    extents = []
    for side, _sign in _SIDES:
        lift = activity * np.clip(np.sin(step_phase + (0.0 if side == "left" else np.pi)), 0.0, None)
        hip, knee = 0.3 * lift, 0.6 * lift
        _flex_leg(pose, side, hip, knee, 0.5 * (knee - hip))
        extents.append(_leg_extent(proportions, hip, knee)[0])
    pose.rotate("neck", UP, 0.5 * np.clip(lead, -0.5, 0.5))
    pose.rotate("head", UP, 0.5 * np.clip(lead, -0.5, 0.5))
    pose.rotate("pelvis", UP, yaw)
    pose.translation[:, 1] = np.maximum(extents[0], extents[1])
    return pose.to_motion("turn", skeleton_kind, fps)


_GENERATORS: Mapping[str, Callable[..., Motion]] = MappingProxyType(
    {"turntable": turntable, "walk": walk, "arm_raise": arm_raise, "squat": squat, "turn": turn}
)


def motion_by_name(
    name: str,
    skeleton_kind: str,
    n_frames: int,
    seed: int = 0,
    *,
    fps: float = 30.0,
    skeleton: Skeleton | None = None,
) -> Motion:
    """The motion `name` (one of MOTION_NAMES) for `skeleton_kind`, with default options.

    Args:
        skeleton: the subject's skeleton, to measure its proportions (arm rest angle, leg lengths);
            None uses the kind's nominal proportions.
    Raises:
        InputError: unknown motion name or skeleton kind (the message lists the valid ones).
    """
    generator = _GENERATORS.get(name)
    if generator is None:
        raise InputError(f"unknown motion {name!r}; valid motions: {', '.join(MOTION_NAMES)}")
    return generator(_check_kind(skeleton_kind), n_frames, seed, fps=fps, skeleton=skeleton)
