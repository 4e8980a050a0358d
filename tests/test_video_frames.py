"""Reading clips and frame folders; the clip checks (no person, two people, cut by the edge, moving camera)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from igavatar.capture.person_landmarks import PersonTracks, person_mask
from igavatar.capture.video_checks import (background_motion_px, check_detections, check_in_frame, check_one_person,
                                           check_still_camera)
from igavatar.capture.video_frames import FrameSelection, read_video_frames
from igavatar.errors import InputError


def _textured_frames(n: int, size: int = 96, seed: int = 0, still: int = 0) -> list[np.ndarray]:
    """Frames of a moving bright square on a fixed random texture; `still` repeats of frame 0 first."""
    rng = np.random.default_rng(seed)
    background = rng.integers(0, 255, (size, size, 3), dtype=np.uint8)
    frames = []
    for i in range(n):
        frame = background.copy()
        x = 10 + 3 * max(0, i - still)
        frame[30:60, x:x + 20] = 255
        frames.append(frame)
    return frames


def _write_mp4(path: Path, frames: list[np.ndarray], fps: int = 10) -> None:
    import imageio.v3 as iio

    iio.imwrite(path, np.stack(frames), fps=fps, codec="libx264", quality=10)


def test_video_frames_every_max_and_names(tmp_path):
    clip = tmp_path / "clip.mp4"
    _write_mp4(clip, _textured_frames(20))
    frames = read_video_frames(clip, FrameSelection(every=2, max_frames=None, drop_blurred=False, drop_duplicates=False))
    assert frames.source_count == 20 and frames.source_indices == list(range(0, 20, 2))
    assert frames.names[:2] == ["frame_000000", "frame_000002"] and frames.fps == pytest.approx(10.0)
    assert frames.images[0].shape == (96, 96, 3) and frames.images[0].dtype == np.uint8
    few = read_video_frames(clip, FrameSelection(max_frames=5, drop_blurred=False, drop_duplicates=False))
    assert few.source_indices == [0, 5, 10, 14, 19] and len(few.dropped["max_frames"]) == 15


def test_duplicates_and_blurred_frames_are_dropped(tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    frames = _textured_frames(12, still=3)           # frames 1-3 repeat frame 0
    frames[8] = cv2.GaussianBlur(frames[8], (0, 0), 4.0)  # one frame out of focus
    for i, frame in enumerate(frames):
        cv2.imwrite(str(folder / f"img_{i:03d}.png"), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    result = read_video_frames(folder, FrameSelection(max_frames=None))
    assert result.dropped["duplicate"] == [1, 2, 3]
    assert result.dropped["blurred"] == [8]
    assert 8 not in result.source_indices and result.fps is None


def test_not_a_video(tmp_path):
    fake = tmp_path / "notes.mp4"
    fake.write_text("this is not a video\n")
    with pytest.raises(InputError, match="not a readable video"):
        read_video_frames(fake)
    with pytest.raises(InputError, match="no such video"):
        read_video_frames(tmp_path / "missing.mp4")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no .png/.jpg frames"):
        read_video_frames(tmp_path / "empty")


def _tracks(masks: np.ndarray, people: np.ndarray | None = None, detected: np.ndarray | None = None) -> PersonTracks:
    n = len(masks)
    return PersonTracks(
        detected=np.ones(n, bool) if detected is None else detected, masks=masks.astype(np.float32),
        people=(masks if people is None else people).astype(np.float32),
        image_xy=np.zeros((n, 33, 2), np.float32), visibility=np.ones((n, 33), np.float32),
        world_xyz=np.zeros((n, 33, 3), np.float32))


def _person(size: int = 100, left: int = 40, top: int = 10, bottom: int = 90) -> np.ndarray:
    mask = np.zeros((size, size), np.float32)
    mask[top:bottom, left:left + 20] = 1.0
    return mask


def test_detection_checks():
    masks = np.stack([_person()] * 10)
    check_detections(Path("clip.mp4"), _tracks(masks), min_frames=8)
    with pytest.raises(InputError, match="no person found"):
        check_detections(Path("clip.mp4"), _tracks(masks, detected=np.zeros(10, bool)), min_frames=8)
    with pytest.raises(InputError, match="only 3 of 10"):
        check_detections(Path("clip.mp4"), _tracks(masks, detected=np.arange(10) < 3), min_frames=2)
    with pytest.raises(InputError, match="training needs at least 12"):
        check_detections(Path("clip.mp4"), _tracks(masks), min_frames=12)


def test_person_cut_by_the_frame_edge():
    inside = np.stack([_person()] * 6)
    check_in_frame(Path("clip.mp4"), _tracks(inside))
    cut = np.stack([_person(bottom=100)] * 6)  # feet through the bottom edge in every frame
    with pytest.raises(InputError, match="cut by the frame's edge in 6 of 6"):
        check_in_frame(Path("clip.mp4"), _tracks(cut))


def test_two_people():
    masks = np.stack([_person(left=20)] * 6)
    check_one_person(Path("clip.mp4"), _tracks(masks))
    both = masks + np.stack([_person(left=70)] * 6)
    with pytest.raises(InputError, match="second person is in 6 of 6"):
        check_one_person(Path("clip.mp4"), _tracks(masks, people=both))


def test_moving_camera_is_refused_and_a_still_one_passes():
    rng = np.random.default_rng(1)
    scene = cv2.GaussianBlur(rng.integers(0, 255, (160, 260, 3), dtype=np.uint8), (0, 0), 1.0)
    masks = np.zeros((8, 120, 120), np.float32)
    masks[:, 40:110, 50:70] = 1.0
    still = [scene[20:140, 60:180].copy() for _ in range(8)]
    assert background_motion_px(still, masks) < 0.2
    check_still_camera(Path("clip.mp4"), still, masks)
    panning = [scene[20:140, 60 + 4 * i:180 + 4 * i].copy() for i in range(8)]  # 4 px a frame
    assert background_motion_px(panning, masks) == pytest.approx(4.0, abs=0.5)
    with pytest.raises(InputError, match="the camera moves"):
        check_still_camera(Path("clip.mp4"), panning, masks)


def test_person_mask_keeps_the_largest_piece_and_fills_holes():
    probability = np.zeros((50, 50), np.float32)
    probability[5:45, 10:30] = 0.9
    probability[20:25, 15:20] = 0.1   # a hole inside the person
    probability[2:5, 40:44] = 0.8     # a speck elsewhere
    mask = person_mask(probability)
    assert mask.dtype == np.uint8 and set(np.unique(mask)) == {0, 255}
    assert mask[22, 17] == 255 and mask[3, 41] == 0 and mask[5:45, 10:30].min() == 255
