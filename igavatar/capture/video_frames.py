"""Frames of a video file or a folder of images, thinned and cleaned for the video path.

    frames = read_video_frames(Path("clip.mp4"), FrameSelection(every=2, max_frames=200))
    frames.images[0]            # (H, W, 3) uint8 RGB, longer side <= FrameSelection.max_side
    frames.source_indices[0]    # its index in the source: the frame is named frame_000123

A clip's frames are read in order with imageio (ffmpeg, shipped inside imageio-ffmpeg, for
mp4/mov/webm/avi/mkv; Pillow for gif), or from a folder of png/jpg files sorted by name. Every
`every`-th frame is kept, then blurred frames (variance of the Laplacian far below the clip's
median: motion blur or defocus) and near-duplicates (a still stretch of the video adds nothing but
weight to one pose) are dropped, then at most `max_frames` are kept, evenly spaced.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from igavatar.errors import InputError

VIDEO_SUFFIXES = (".mp4", ".mov", ".webm", ".avi", ".mkv", ".m4v", ".gif")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
#: A frame whose sharpness (variance of the Laplacian) is below this share of the clip's median
#: is dropped as blurred.
BLUR_SHARE = 0.35
#: A frame whose mean absolute difference to the last kept frame is below this (0-255 scale, on
#: a 64 px thumbnail) is dropped as a duplicate.
DUPLICATE_DIFFERENCE = 0.6


@dataclass(frozen=True)
class FrameSelection:
    """Which frames of a source are kept.

    Attributes:
        every: keep every N-th frame of the source (1 = all).
        max_frames: at most this many frames after dropping (evenly spaced), or None for all.
        max_side: frames are resized so that the longer side is at most this many pixels.
        drop_blurred: drop frames much less sharp than the clip's median.
        drop_duplicates: drop frames nearly identical to the previous kept one.
    """

    every: int = 1
    max_frames: int | None = 300
    max_side: int = 1024
    drop_blurred: bool = True
    drop_duplicates: bool = True


@dataclass
class VideoFrames:
    """Kept frames and what happened to the others.

    Attributes:
        images: kept frames, each (H, W, 3) uint8 RGB, all one size.
        source_indices: index of each kept frame in the source (0-based).
        source_count: frames in the source.
        fps: the source's frame rate, or None (a folder, or unknown).
        dropped: reason -> source indices dropped for it ("blurred", "duplicate", "max_frames").
        source_size: (height, width) of the source frames before resizing.
    """

    images: list[np.ndarray]
    source_indices: list[int]
    source_count: int
    fps: float | None
    source_size: tuple[int, int]
    dropped: dict[str, list[int]] = field(default_factory=dict)

    @property
    def names(self) -> list[str]:
        """Frame names: frame_<index in the source, 6 digits>."""
        return [frame_name(i) for i in self.source_indices]


def frame_name(source_index: int) -> str:
    return f"frame_{source_index:06d}"


def _resized(image: np.ndarray, max_side: int) -> np.ndarray:
    height, width = image.shape[:2]
    scale = max_side / max(height, width)
    if scale >= 1.0:
        return image
    size = (max(1, round(width * scale)), max(1, round(height * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def _as_rgb(frame: np.ndarray, where: str) -> np.ndarray:
    frame = np.asarray(frame)
    if frame.ndim == 2:
        frame = np.repeat(frame[..., None], 3, axis=2)
    if frame.ndim != 3 or frame.shape[2] not in (3, 4):
        raise InputError(f"{where}: a frame has shape {frame.shape}, expected (H, W, 3) RGB")
    if frame.dtype != np.uint8:
        frame = np.clip(frame, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(frame[..., :3])


def _iter_source(path: Path):
    """(frames iterator of RGB arrays, fps or None) of a video file or an image folder."""
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise InputError(f"{path}: a folder with no .png/.jpg frames; pass a video file or a folder of frames")

        def folder_frames():
            for file in files:
                bgr = cv2.imread(str(file), cv2.IMREAD_COLOR)
                if bgr is None:
                    raise InputError(f"{file}: not a readable image")
                yield cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

        return folder_frames(), None
    if not path.is_file():
        raise InputError(f"{path}: no such video file or folder of frames")
    import imageio.v3 as iio

    try:
        meta = iio.immeta(path)
    except Exception as error:  # imageio raises many kinds for a file no plugin reads
        raise InputError(
            f"{path}: not a readable video ({type(error).__name__}: {str(error).splitlines()[0][:160] if str(error) else ''}); "
            f"expected one of {', '.join(VIDEO_SUFFIXES)} or a folder of frames"
        ) from None
    fps = meta.get("fps")
    if fps is None and meta.get("duration"):
        fps = 1000.0 / float(meta["duration"])  # gif: milliseconds per frame
    return iio.imiter(path), (float(fps) if fps else None)


def sharpness(rgb: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image: low for blurred frames."""
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def _thumbnail(rgb: np.ndarray) -> np.ndarray:
    return cv2.resize(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), (64, 64), interpolation=cv2.INTER_AREA).astype(np.float32)


def read_video_frames(path: Path, selection: FrameSelection = FrameSelection()) -> VideoFrames:
    """Read, thin and clean the frames of `path` (see the module docstring).

    Raises:
        InputError: not a video or frame folder, unreadable, no frames, or frames of changing size.
    """
    path = Path(path)
    frames_iter, fps = _iter_source(path)
    images: list[np.ndarray] = []
    indices: list[int] = []
    count = 0
    source_size: tuple[int, int] | None = None
    try:
        for index, frame in enumerate(frames_iter):
            count = index + 1
            if index % selection.every:
                continue
            rgb = _as_rgb(frame, str(path))
            if source_size is None:
                source_size = rgb.shape[:2]
            elif rgb.shape[:2] != source_size:
                raise InputError(f"{path}: frame {index} is {rgb.shape[1]}x{rgb.shape[0]}, "
                                 f"the first was {source_size[1]}x{source_size[0]}; all frames must be one size")
            images.append(_resized(rgb, selection.max_side))
            indices.append(index)
    except InputError:
        raise
    except Exception as error:  # a decoder error partway through a damaged file
        if not images:
            raise InputError(f"{path}: not a readable video ({type(error).__name__}); "
                             f"expected one of {', '.join(VIDEO_SUFFIXES)} or a folder of frames") from None
    if not images or source_size is None:
        raise InputError(f"{path}: holds no frames")
    frames = VideoFrames(images, indices, count, fps, source_size, {})
    if selection.drop_blurred:
        _drop(frames, _blurred(frames.images), "blurred")
    if selection.drop_duplicates:
        _drop(frames, _duplicates(frames.images), "duplicate")
    if selection.max_frames is not None and len(frames.images) > selection.max_frames:
        keep = np.unique(np.linspace(0, len(frames.images) - 1, selection.max_frames).round().astype(int))
        _drop(frames, np.setdiff1d(np.arange(len(frames.images)), keep), "max_frames")
    return frames


def _blurred(images: list[np.ndarray]) -> np.ndarray:
    """Positions of frames far less sharp than the median (none for clips of < 5 frames)."""
    if len(images) < 5:
        return np.zeros(0, dtype=int)
    values = np.array([sharpness(image) for image in images])
    return np.flatnonzero(values < BLUR_SHARE * np.median(values))


def _duplicates(images: list[np.ndarray]) -> np.ndarray:
    """Positions of frames nearly identical to the last kept frame before them."""
    dropped = []
    last = _thumbnail(images[0])
    for position in range(1, len(images)):
        current = _thumbnail(images[position])
        if float(np.abs(current - last).mean()) < DUPLICATE_DIFFERENCE:
            dropped.append(position)
        else:
            last = current
    return np.asarray(dropped, dtype=int)


def _drop(frames: VideoFrames, positions: np.ndarray, reason: str) -> None:
    """Remove the frames at `positions` (in the current lists), recording their source indices."""
    if len(positions) == 0:
        return
    gone = set(int(p) for p in positions)
    frames.dropped.setdefault(reason, []).extend(frames.source_indices[p] for p in sorted(gone))
    frames.images = [image for p, image in enumerate(frames.images) if p not in gone]
    frames.source_indices = [index for p, index in enumerate(frames.source_indices) if p not in gone]
