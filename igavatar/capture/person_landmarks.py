"""Person masks and body landmarks of video frames, offline on the CPU, with MediaPipe's BlazePose.

    tracks = track_person(frames.images)          # PersonTracks
    tracks.masks[i]        # (H, W) float32 in [0, 1]: the tracked person
    tracks.image_xy[i]     # (33, 2) landmark pixels; tracks.visibility[i] (33,) in [0, 1]
    tracks.world_xyz[i]    # (33, 3) metric landmarks around the hips' centre, camera-aligned axes

MediaPipe 0.10.14 ships the BlazePose "full" landmark model, its detector and the selfie
segmentation model inside its wheel, so nothing is downloaded (later wheels fetch their models at
run time). Its declared dependencies pull the non-headless OpenCV and JAX, which the solutions do
not use, so igavatar installs it with `--no-deps` beside the `video` extra (README, docs/DESIGN.md).

BlazePose tracks one person. The selfie segmentation model sees every person, so a second person
shows up as foreground that the tracked person's mask does not cover (igavatar.capture.video_checks).
"""

from __future__ import annotations

import contextlib
import os
import sys
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from igavatar.errors import InputError

MEDIAPIPE_VERSION = "0.10.14"
INSTALL_HINT = (f"pip install 'igavatar[video]' && pip install --no-deps mediapipe=={MEDIAPIPE_VERSION} "
                "(the README's install commands do both)")
LANDMARK_COUNT = 33

#: BlazePose landmark indices by name (MediaPipe's PoseLandmark order).
LANDMARKS: dict[str, int] = {
    "nose": 0, "left_eye": 2, "right_eye": 5, "left_ear": 7, "right_ear": 8,
    "left_shoulder": 11, "right_shoulder": 12, "left_elbow": 13, "right_elbow": 14,
    "left_wrist": 15, "right_wrist": 16, "left_hip": 23, "right_hip": 24,
    "left_knee": 25, "right_knee": 26, "left_ankle": 27, "right_ankle": 28,
    "left_heel": 29, "right_heel": 30, "left_foot_index": 31, "right_foot_index": 32,
}
#: Landmark index -> its mirror's (left <-> right), for the back-view relabelling.
MIRROR = np.array([0, 4, 5, 6, 1, 2, 3, 8, 7, 10, 9, 12, 11, 14, 13, 16, 15, 18, 17, 20, 19, 22, 21,
                   24, 23, 26, 25, 28, 27, 30, 29, 32, 31])


@dataclass
class PersonTracks:
    """Per-frame outputs of the person tracker (N frames, all arrays float32).

    Attributes:
        detected: (N,) bool, whether a person was found in the frame.
        masks: (N, H, W) probability that a pixel shows the tracked person (0 where none).
        people: (N, H, W) probability that a pixel shows any person (selfie segmentation).
        image_xy: (N, 33, 2) landmark positions in pixels (NaN where not detected).
        visibility: (N, 33) landmark visibility in [0, 1] (0 where not detected).
        world_xyz: (N, 33, 3) metric landmarks, origin between the hips, axes as the camera's
            (x right, y down, z away from the camera); NaN where not detected.
    """

    detected: np.ndarray
    masks: np.ndarray
    people: np.ndarray
    image_xy: np.ndarray
    visibility: np.ndarray
    world_xyz: np.ndarray


def _import_solutions():
    """MediaPipe's pose and selfie-segmentation solutions, or InputError saying how to install them."""
    # MediaPipe's C++ side logs through glog/absl to stderr at import and per graph; quiet it.
    os.environ.setdefault("GLOG_minloglevel", "2")
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            import mediapipe
            from mediapipe.python.solutions import pose, selfie_segmentation
    except ImportError as error:
        raise InputError(f"the video path needs MediaPipe {MEDIAPIPE_VERSION} ({error}); install it: {INSTALL_HINT}") from None
    version = getattr(mediapipe, "__version__", "?")
    if not hasattr(pose, "Pose"):
        raise InputError(f"MediaPipe {version} has no bundled pose model; install {MEDIAPIPE_VERSION}: {INSTALL_HINT}")
    return pose, selfie_segmentation


@contextlib.contextmanager
def _native_stderr_silenced() -> Iterator[None]:
    """Send file descriptor 2 to /dev/null: MediaPipe's C++ side (TFLite, absl) prints a few lines
    of its own when a graph starts ("Created TensorFlow Lite XNNPACK delegate", feedback-tensor
    warnings) that no environment variable turns off."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def track_person(images: Sequence[np.ndarray], on_frame: Callable[[int], None] | None = None) -> PersonTracks:
    """Run BlazePose (with segmentation, in tracking mode) and selfie segmentation over `images`.

    Args:
        images: N frames (H, W, 3) uint8 RGB of one size, in time order.
        on_frame: called with each frame's index once it is done (progress).
    """
    pose_module, selfie_module = _import_solutions()
    n_frames = len(images)
    height, width = images[0].shape[:2]
    tracks = PersonTracks(
        detected=np.zeros(n_frames, bool), masks=np.zeros((n_frames, height, width), np.float32),
        people=np.zeros((n_frames, height, width), np.float32),
        image_xy=np.full((n_frames, LANDMARK_COUNT, 2), np.nan, np.float32),
        visibility=np.zeros((n_frames, LANDMARK_COUNT), np.float32),
        world_xyz=np.full((n_frames, LANDMARK_COUNT, 3), np.nan, np.float32),
    )
    with warnings.catch_warnings(), contextlib.ExitStack() as stack:
        warnings.simplefilter("ignore")  # protobuf deprecation warnings from inside MediaPipe
        with _native_stderr_silenced():  # the graphs start with the objects and their first frame
            pose = stack.enter_context(pose_module.Pose(static_image_mode=False, model_complexity=1,
                                                        enable_segmentation=True, smooth_segmentation=True))
            selfie = stack.enter_context(selfie_module.SelfieSegmentation(model_selection=0))
            _track_frame(pose, selfie, np.ascontiguousarray(images[0]), tracks, 0)
        for index, image in enumerate(images):
            if index:
                _track_frame(pose, selfie, np.ascontiguousarray(image), tracks, index)
            if on_frame is not None:
                on_frame(index)
    return tracks


def _track_frame(pose, selfie, image: np.ndarray, tracks: PersonTracks, index: int) -> None:
    height, width = image.shape[:2]
    people = selfie.process(image).segmentation_mask
    if people is not None:
        tracks.people[index] = people
    result = pose.process(image)
    if result.pose_landmarks is None:
        return
    tracks.detected[index] = True
    landmarks = result.pose_landmarks.landmark
    # MediaPipe's 0..1 spans the image's edges; igavatar's pixel centres are at integers.
    tracks.image_xy[index] = [(lm.x * width - 0.5, lm.y * height - 0.5) for lm in landmarks]
    tracks.visibility[index] = [lm.visibility for lm in landmarks]
    if result.pose_world_landmarks is not None:
        tracks.world_xyz[index] = [(lm.x, lm.y, lm.z) for lm in result.pose_world_landmarks.landmark]
    if result.segmentation_mask is not None:
        tracks.masks[index] = result.segmentation_mask


def person_mask(probability: np.ndarray) -> np.ndarray:
    """(H, W) uint8 0/255: the segmentation thresholded at 0.5, its largest piece, holes filled."""
    binary = (probability > 0.5).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    if count <= 1:
        return binary * 255
    largest = 1 + int(stats[1:, cv2.CC_STAT_AREA].argmax())
    piece = (labels == largest).astype(np.uint8)
    # Fill holes: background that a flood from outside the image cannot reach is the person's.
    flood = np.pad(piece, 1)
    cv2.floodFill(flood, np.zeros((flood.shape[0] + 2, flood.shape[1] + 2), np.uint8), (0, 0), 2)
    return ((piece | (flood[1:-1, 1:-1] == 0)) * 255).astype(np.uint8)
