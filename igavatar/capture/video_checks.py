"""Checks that a clip can make an avatar: one person, in frame, seen by a still camera.

    check_tracks(path, tracks, min_frames=8)     # InputError naming the problem, else None
    shift = background_motion_px(images, masks)  # median background motion between frames

Each check raises one InputError that says what was found, in how many frames, and what to do.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from igavatar.capture.person_landmarks import PersonTracks
from igavatar.errors import InputError

#: A person must be found in at least this share of the frames.
MIN_DETECTED_SHARE = 0.5
#: The person touches the image border in more than this share of the frames: "cut by the edge".
MAX_CUT_SHARE = 0.5
#: A frame shows a second person when foreground outside the tracked person (selfie segmentation)
#: covers this share of the tracked person's area in one piece...
SECOND_PERSON_AREA = 0.3
#: ...in at least this share of the frames.
SECOND_PERSON_SHARE = 0.3
#: The background moves by more than this share of the image's longer side between frames
#: (median over pairs): a moving camera.
MAX_BACKGROUND_SHIFT = 0.004


def check_detections(path: Path, tracks: PersonTracks, min_frames: int) -> None:
    """InputError when no person is found, or in too few frames to train on."""
    found = int(tracks.detected.sum())
    total = len(tracks.detected)
    if found == 0:
        raise InputError(f"{path}: no person found in any of {total} frames; film one whole person, well lit")
    if found < MIN_DETECTED_SHARE * total:
        raise InputError(f"{path}: a person was found in only {found} of {total} frames; "
                         "film one whole person who stays in view")
    if found < min_frames:
        raise InputError(f"{path}: {found} usable frames, training needs at least {min_frames}; "
                         "use a longer clip or a smaller --every")


def check_in_frame(path: Path, tracks: PersonTracks) -> None:
    """InputError when the person's mask touches the image border in most frames."""
    masks = tracks.masks[tracks.detected] > 0.5
    border = np.zeros(masks.shape[1:], bool)
    border[:2], border[-2:], border[:, :2], border[:, -2:] = True, True, True, True
    # A few pixels touching is noise; a limb or the head through the edge is tens of pixels.
    touching = (masks & border).sum(axis=(1, 2)) > 0.1 * (masks.shape[1] + masks.shape[2]) / 20
    if touching.mean() > MAX_CUT_SHARE:
        raise InputError(f"{path}: the person is cut by the frame's edge in {int(touching.sum())} of {len(masks)} "
                         "frames; film the whole body, head to feet, with a little room around it")


def check_one_person(path: Path, tracks: PersonTracks) -> None:
    """InputError when a second person shows in a good share of the frames."""
    kernel = np.ones((15, 15), np.uint8)
    second = 0
    frames = np.flatnonzero(tracks.detected)
    for index in frames:
        person = tracks.masks[index] > 0.5
        area = person.sum()
        if area == 0:
            continue
        near_person = cv2.dilate(person.astype(np.uint8), kernel) > 0
        others = ((tracks.people[index] > 0.5) & ~near_person).astype(np.uint8)
        count, _, stats, _ = cv2.connectedComponentsWithStats(others, connectivity=8)
        largest = stats[1:, cv2.CC_STAT_AREA].max() if count > 1 else 0
        second += largest > SECOND_PERSON_AREA * area
    if len(frames) and second >= SECOND_PERSON_SHARE * len(frames):
        raise InputError(f"{path}: a second person is in {second} of {len(frames)} frames; igavatar makes one "
                         "person's avatar: film them alone, or crop the video to one person")


def background_motion_px(images: Sequence[np.ndarray], masks: np.ndarray, pairs: int = 24) -> float:
    """Median over up to `pairs` consecutive frame pairs of the median motion (pixels) of
    background corners tracked with Lucas-Kanade; 0 when the background has nothing to track."""
    kernel = np.ones((31, 31), np.uint8)
    starts = np.unique(np.linspace(0, len(images) - 2, min(pairs, len(images) - 1)).round().astype(int))
    shifts = []
    for i in starts:
        grey0 = cv2.cvtColor(images[i], cv2.COLOR_RGB2GRAY)
        grey1 = cv2.cvtColor(images[i + 1], cv2.COLOR_RGB2GRAY)
        background = ((cv2.dilate((masks[i] > 0.3).astype(np.uint8), kernel) == 0)
                      & (cv2.dilate((masks[i + 1] > 0.3).astype(np.uint8), kernel) == 0)).astype(np.uint8)
        corners = cv2.goodFeaturesToTrack(grey0, maxCorners=200, qualityLevel=0.01, minDistance=7, mask=background)
        if corners is None or len(corners) < 20:
            continue
        moved, status, _ = cv2.calcOpticalFlowPyrLK(grey0, grey1, corners, None)
        ok = status[:, 0] == 1
        if ok.sum() < 10:
            continue
        shifts.append(float(np.median(np.linalg.norm((moved - corners)[ok, 0], axis=1))))
    return float(np.median(shifts)) if shifts else 0.0


def check_still_camera(path: Path, images: Sequence[np.ndarray], masks: np.ndarray) -> float:
    """The background's median motion in pixels; InputError when the camera moves."""
    shift = background_motion_px(images, masks)
    limit = MAX_BACKGROUND_SHIFT * max(images[0].shape[:2])
    if shift > limit:
        raise InputError(f"{path}: the background moves {shift:.1f} px between frames (limit {limit:.1f}): the camera "
                         "moves; igavatar's video path needs a still camera (a tripod, or the phone propped up)")
    return shift
